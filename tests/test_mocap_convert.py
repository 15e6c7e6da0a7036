"""Mocap conversion (AMC/BVH -> dm_control HDF5) and clip loading, on real CMU data.

Tests that need the shared CMU clips skip when ../shared/mocap is absent; the loader
tests on dm_control's shipped test_trajectories.h5 always run. Only three short clips
are converted (one walker build), so the file runs in a few seconds.
"""

from __future__ import annotations

import csv
import dataclasses
import re
from pathlib import Path

import h5py
import numpy as np
import pytest
from dm_control.locomotion import mocap as dm_mocap
from dm_control.locomotion.mocap import loader as dm_loader
from dm_control.suite.utils import parse_amc as dm_parse_amc
from hvc.mocap.source import SHARED_CLIPS
from dm_control.utils import transformations as tr

from hvc.mocap import asf_amc, bvh, clips, convert

MOCAP = SHARED_CLIPS.parent
CMU = MOCAP / "cmu"
DM_TEST_H5 = Path(dm_mocap.__file__).parent / "test_trajectories.h5"
needs_mocap = pytest.mark.skipif(
    not CMU.is_dir(), reason=f"real CMU mocap clips not found at {MOCAP} (shared data, not in the repo)"
)
pytestmark = pytest.mark.filterwarnings("ignore:label\\(\\) is deprecated:DeprecationWarning")
DT = 0.03


@pytest.fixture(scope="module")
def poser() -> convert.WalkerPoser:
    return convert.WalkerPoser("2019")


@pytest.fixture(scope="module")
def converted(tmp_path_factory, poser) -> Path:
    """02_01 (AMC walk), 16_41 and 16_43 (BVH runs with a left / right turn) in one HDF5."""
    if not CMU.is_dir():
        pytest.skip(f"real CMU mocap clips not found at {MOCAP}")
    out = tmp_path_factory.mktemp("mocap") / "cmu_2019.h5"
    for rel in ("amc/02/02_01.amc", "bvh/16/16_41.bvh", "bvh/16/16_43.bvh"):
        convert.convert_clip(CMU / rel, out, walker_version="2019", dt=DT, poser=poser)
    return out


def _stance(heights: np.ndarray) -> np.ndarray:
    return heights[convert.stance_minima(heights, DT)]


# --------------------------------------------------------------------------- parsing
@needs_mocap
def test_amc_reader_agrees_with_dm_control_parse_amc():
    path = CMU / "amc/02/02_01.amc"
    ours = asf_amc.read_amc(path)
    theirs = dm_parse_amc.parse(str(path))  # values in file order, names dropped
    assert len(theirs) == 343 == len(ours["root"])
    flat = np.concatenate([v for v in ours.values()], axis=1)
    np.testing.assert_allclose(flat, np.stack(theirs), atol=0)
    # Root pose: README's pos = [x, -z, y] * 0.056444 and Y2Z @ Rz Ry Rx equal dm_control's Amcvals2qpos.
    frames = asf_amc.amc_to_frames(ours, asf_amc.parse_asf(CMU / "asf/02.asf"))
    to_qpos = dm_parse_amc.Amcvals2qpos({i: "" for i in range(63)}, dm_parse_amc._CMU_MOCAP_JOINT_ORDER)
    for t in (0, 100, 342):
        qpos = to_qpos(theirs[t])
        np.testing.assert_allclose(frames.root_pos[t], qpos[:3], atol=1e-12)
        q = frames.root_quat[t] * np.sign(frames.root_quat[t] @ qpos[3:7])
        np.testing.assert_allclose(q, qpos[3:7], atol=1e-9)


@needs_mocap
def test_crlf_amc_parses(tmp_path):
    path = CMU / "amc/131/131_04.amc"
    assert b"\r\n" in path.read_bytes()[:200], "131_04.amc is expected to use CRLF line endings"
    values = asf_amc.read_amc(path)
    assert len(values["root"]) == 1086
    frames = asf_amc.amc_to_frames(values, asf_amc.parse_asf(CMU / "asf/131.asf"))
    assert frames.joints.shape == (1086, 56) and np.isfinite(frames.joints).all()
    # Stray carriage returns inside lines (as in CMU 131_10) parse to the same values.
    lf = (CMU / "amc/02/02_01.amc").read_bytes().replace(b"\r\n", b"\n")
    stray = tmp_path / "02_01.amc"
    stray.write_bytes(lf.replace(b"\n", b"\r\n").replace(b"lowerback ", b"lowerback \r"))
    a, b = asf_amc.read_amc(CMU / "amc/02/02_01.amc"), asf_amc.read_amc(stray)
    assert a.keys() == b.keys() and all(np.array_equal(a[k], b[k]) for k in a)


@needs_mocap
def test_bvh_names_map_onto_asf_bones():
    """Child OFFSETs equal ASF direction*length of the mapped bone; angles on axes a bone lacks are ~0."""
    motion = bvh.read_bvh(CMU / "bvh/16/16_41.bvh")
    skeleton = asf_amc.parse_asf(CMU / "asf/16.asf")
    assert set(motion.joints) == set(bvh.BVH_TO_ASF)
    report = bvh.mapping_report(motion, skeleton)
    assert len(report) >= 25 and max(report.values()) < 1e-3, report
    values, off_axis = bvh.bvh_to_amc_values(motion, skeleton)
    assert max(off_axis.values()) < 1e-3  # degrees; exact up to the BVH's 4 printed decimals
    assert len(values["root"]) == 160  # 161 frames minus the added rest pose
    assert bvh.leg_length_m(motion) == pytest.approx(skeleton.leg_length_m(), abs=1e-4)


# --------------------------------------------------------------------------- conversion
@needs_mocap
def test_converted_walk_stands_on_floor(converted, poser):
    clip = clips.load_clip(converted, "CMU_002_01")
    heights = poser.foot_heights(clip.position, clip.quaternion, clip.joints)
    assert -0.03 < heights.min() <= 0.005, heights.min()  # never deeply below
    stance = _stance(heights)
    assert np.abs(stance).max() < 0.02, stance  # a stance foot touches z=0 through the whole walk
    with h5py.File(converted, "r") as f:
        # Root translation scaled by walker femur+tibia (0.811 m) / subject 02's from the ASF (0.840 m).
        subject_leg = asf_amc.parse_asf(CMU / "asf/02.asf").leg_length_m()
        assert subject_leg == pytest.approx(0.840, abs=1e-3) and poser.leg_length == pytest.approx(0.811, abs=1e-3)
        assert f["CMU_002_01"].attrs["hvc_leg_scale"] == pytest.approx(poser.leg_length / subject_leg, rel=1e-9)


@needs_mocap
def test_converted_walk_joints_equal_amc(converted, poser):
    """deg2rad(AMC) at frames that coincide with the 0.03 s grid (every 5th step = every 18th frame)."""
    values = asf_amc.read_amc(CMU / "amc/02/02_01.amc")
    skeleton = asf_amc.parse_asf(CMU / "asf/02.asf")
    clip = clips.load_clip(converted, "CMU_002_01")
    assert clip.num_steps == 96 and clip.dt == pytest.approx(DT)
    for step in range(0, clip.num_steps, 5):
        frame = round(step * DT * 120)
        for j, name in enumerate(poser.joint_names):
            bone = next(b for b in skeleton.bones.values() if name.startswith(b.name) and name[len(b.name) :] in b.dofs)
            expected = np.deg2rad(values[bone.name][frame, bone.dofs.index(name[len(bone.name) :])])
            assert clip.joints[step, j] == pytest.approx(expected, abs=1e-9), (step, name)


@needs_mocap
def test_converted_file_loads_with_dm_control_loader(converted):
    loader = dm_loader.HDF5TrajectoryLoader(str(converted))
    assert set(loader.keys()) == {"CMU_002_01", "CMU_016_41", "CMU_016_43"}
    traj = loader.get_trajectory("CMU_002_01")
    data = traj.as_dict()
    assert traj.dt == pytest.approx(DT) and traj.num_steps == 96
    assert data["walker/joints"].shape == (96, 56)
    assert data["walker/end_effectors"].shape == (96, 4, 3)
    assert data["walker/appendages"].shape == (96, 5, 3)
    assert data["walker/body_positions"].shape == (96, 30, 3)
    assert data["walker/body_quaternions"].shape == (96, 30, 4)
    with h5py.File(converted, "r") as f, h5py.File(DM_TEST_H5, "r") as ref:
        ours, theirs = f["CMU_002_01"], ref["cmuv2019_001"]
        assert set(ours.attrs) >= set(theirs.attrs)
        w, rw = ours["walkers/walker_0"], theirs["walkers/walker_0"]
        assert set(rw.attrs) == set(w.attrs) and set(rw) == set(w)
        assert w.attrs["model"] == 1  # CMU_2019, as the 2019 walker
        for name, ds in rw.items():
            if isinstance(ds, h5py.Dataset):
                assert w[name].shape == (ds.shape[0], 96), name
        assert "props" in ours and "scaling" in w and "markers" in w
        np.testing.assert_allclose(np.linalg.norm(w["quaternion"][:], axis=0), 1.0, atol=1e-12)


@needs_mocap
def test_velocities_are_central_differences(converted):
    clip = clips.load_clip(converted, "CMU_016_41")
    dt = clip.dt
    np.testing.assert_allclose(clip.velocity[1:-1], (clip.position[2:] - clip.position[:-2]) / (2 * dt), atol=1e-9)
    np.testing.assert_allclose(clip.joints_velocity[1:-1], (clip.joints[2:] - clip.joints[:-2]) / (2 * dt), atol=1e-9)

    def body_rate(q0, q1):  # rotation vector of q0^-1 q1: angular velocity in the root's frame
        return tr.quat_to_axisangle(tr.quat_diff(q0, q1)) / dt

    q = clip.quaternion
    for t in range(1, clip.num_steps - 1):
        expected = 0.5 * (body_rate(q[t - 1], q[t]) + body_rate(q[t], q[t + 1]))
        np.testing.assert_allclose(clip.angular_velocity[t], expected, atol=1e-9)


@needs_mocap
def test_bvh_runs_stand_on_floor_and_turn(converted, poser):
    for clip_id, turn in (("CMU_016_41", 92.0), ("CMU_016_43", -86.0)):
        clip = clips.load_clip(converted, clip_id)
        heights = poser.foot_heights(clip.position, clip.quaternion, clip.joints)
        assert -0.03 < heights.min() <= 0.005, (clip_id, heights.min())
        assert np.abs(_stance(heights)).max() < 0.02, clip_id
        heading = np.rad2deg(clip.heading())
        assert heading[-1] - heading[0] == pytest.approx(turn, abs=6.0), clip_id
        # Joint angles are plausible for the walker: legs within its hinge ranges (+5 deg).
        lo, hi = poser.joint_ranges.T
        legs = [i for i, n in enumerate(poser.joint_names) if n[1:].startswith(("femur", "tibia", "foot"))]
        slack = np.deg2rad(5.0)
        assert ((clip.joints[:, legs] >= lo[legs] - slack) & (clip.joints[:, legs] <= hi[legs] + slack)).all()


@needs_mocap
def test_convert_clip_for_2020_walker(tmp_path):
    out = tmp_path / "v2020.h5"
    clip_id = convert.convert_clip(CMU / "bvh/35/35_17.bvh", out, walker_version="2020")
    assert clip_id == "CMU_035_17"
    with open(MOCAP / "clips.csv", newline="") as f:
        expected_scale = {r["cmu_clip"]: float(r["walker_leg_scale"]) for r in csv.DictReader(f)}["35_17"]
    with h5py.File(out, "r") as f:
        g = f[clip_id]
        assert f[f"{clip_id}/walkers/walker_0"].attrs["model"] == 4  # CMU_2020
        assert f[f"{clip_id}/walkers/walker_0/body_positions"].shape[0] == 31 * 3
        assert g.attrs["hvc_leg_scale"] == pytest.approx(expected_scale, abs=2e-3)
    assert clips.list_clips(out) == [clip_id]
    clip = clips.load_clip(out, clip_id)
    heights = convert.WalkerPoser("2020").foot_heights(clip.position, clip.quaternion, clip.joints)
    assert -0.03 < heights.min() <= 0.005 and np.abs(_stance(heights)).max() < 0.02


def test_clip_id_from_path():
    assert convert.clip_id_from_path("x/amc/09/09_06.amc") == "CMU_009_06"
    assert convert.clip_id_from_path("16_41.bvh") == "CMU_016_41"
    assert convert.clip_id_from_path("131_03.amc") == "CMU_131_03"
    with pytest.raises(ValueError, match="subject"):
        convert.clip_id_from_path("walk.amc")


# --------------------------------------------------------------------------- loading
def test_load_clip_on_dm_control_test_trajectories():
    assert clips.list_clips(DM_TEST_H5) == ["cmuv2019_001", "cmuv2019_002"]
    clip = clips.load_clip(DM_TEST_H5, "cmuv2019_001")
    assert (clip.clip_id, clip.num_steps, clip.dt) == ("cmuv2019_001", 10, pytest.approx(0.05))
    shapes = {f: getattr(clip, f).shape for f in clips.CLIP_FIELDS}
    assert shapes == {
        "joints": (10, 56), "joints_velocity": (10, 56), "position": (10, 3), "quaternion": (10, 4),
        "velocity": (10, 3), "angular_velocity": (10, 3), "end_effectors": (10, 12), "appendages": (10, 15),
        "body_positions": (10, 90), "body_quaternions": (10, 120), "center_of_mass": (10, 3),
    }  # fmt: skip
    assert all(getattr(clip, f).dtype == np.float64 for f in clips.CLIP_FIELDS)
    with h5py.File(DM_TEST_H5, "r") as f:
        np.testing.assert_array_equal(clip.joints, f["cmuv2019_001/walkers/walker_0/joints"][:].T)
    part = clips.load_clip(DM_TEST_H5, "cmuv2019_001", start_step=2, end_step=5)
    assert part.num_steps == 3
    np.testing.assert_array_equal(part.position, clip.position[2:5])
    with pytest.raises(ValueError, match="cannot take steps"):
        clips.load_clip(DM_TEST_H5, "cmuv2019_001", start_step=4, end_step=11)
    with pytest.raises(dataclasses.FrozenInstanceError):
        clip.dt = 1.0  # type: ignore[misc]


def test_missing_clip_id_names_id_and_file():
    with pytest.raises(KeyError) as err:
        clips.load_clip(DM_TEST_H5, "CMU_016_22")
    message = str(err.value)
    assert "CMU_016_22" in message and str(DM_TEST_H5) in message and "\n" not in message
    with pytest.raises(FileNotFoundError, match="nope.h5"):
        clips.load_clip(DM_TEST_H5.parent / "nope.h5", "x")


@needs_mocap
@pytest.mark.parametrize("rel", ["amc/02/02_01.amc", "bvh/16/16_41.bvh"])
def test_converted_root_travels_leg_scale_times_the_captures_distance(converted, poser, rel):
    """Step 2 of the pipeline: the walker's legs are not the subject's, so the root's path is
    scaled by walker leg / subject leg, or the feet slide along the floor with every stride.
    Horizontal displacement (the floor placement only moves z) at steps that fall on capture
    frames equals that ratio times the capture's, the subject's leg read from its own file."""
    path = CMU / rel
    frames = convert.load_frames(path)
    if path.suffix == ".amc":
        subject_leg = asf_amc.parse_asf(CMU / "asf/02.asf").leg_length_m()
    else:
        subject_leg = bvh.leg_length_m(bvh.read_bvh(path))
    scale = poser.leg_length / subject_leg
    clip = clips.load_clip(converted, convert.clip_id_from_path(path))
    steps = np.arange(0, clip.num_steps, 5)  # 5 steps of 0.03 s = 18 frames at 120 fps
    capture = frames.root_pos[np.round(steps * DT * frames.fps).astype(int), :2] - frames.root_pos[0, :2]
    walker = clip.position[steps, :2] - clip.position[0, :2]
    assert np.linalg.norm(capture[-1]) > 2.0  # a clip that travels: a wrong scale shows by metres x (1 - scale)
    np.testing.assert_allclose(walker, scale * capture, atol=2e-3)


def _rotation(rng: np.random.Generator) -> np.ndarray:
    q = rng.normal(size=4)
    w, x, y, z = q / np.linalg.norm(q)
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                     [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                     [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])


def _surface(gtype, size, n=400):
    """Points on a geom's surface in its own frame, sampled densely (MuJoCo's size conventions)."""
    import mujoco

    g = mujoco.mjtGeom
    theta = np.linspace(0, 2 * np.pi, n, endpoint=False)
    phi = np.linspace(0, np.pi, n // 2)
    t, p = np.meshgrid(theta, phi)
    sphere = np.stack([np.sin(p) * np.cos(t), np.sin(p) * np.sin(t), np.cos(p)], -1).reshape(-1, 3)
    if gtype == g.mjGEOM_SPHERE:
        return size[0] * sphere
    if gtype == g.mjGEOM_ELLIPSOID:
        return size[:3] * sphere
    if gtype == g.mjGEOM_CAPSULE:  # radius size[0], half-length size[1] along local z
        return np.concatenate([size[0] * sphere + [0, 0, size[1]], size[0] * sphere - [0, 0, size[1]]])
    if gtype == g.mjGEOM_CYLINDER:
        rim = np.stack([size[0] * np.cos(theta), size[0] * np.sin(theta), np.zeros(n)], -1)
        return np.concatenate([rim + [0, 0, size[1]], rim - [0, 0, size[1]]])
    if gtype == g.mjGEOM_BOX:
        corners = np.array(np.meshgrid([-1, 1], [-1, 1], [-1, 1])).reshape(3, -1).T
        return corners * size[:3]
    raise AssertionError(gtype)


@pytest.mark.parametrize("name", ["SPHERE", "CAPSULE", "BOX", "CYLINDER", "ELLIPSOID"])
def test_a_geoms_lowest_point_matches_its_densely_sampled_surface(name):
    """geom_lowest_z (the floor placement's foot geometry) against the lowest of many surface
    points, for every supported geom type, in random poses."""
    import mujoco

    gtype = int(getattr(mujoco.mjtGeom, f"mjGEOM_{name}"))
    rng = np.random.default_rng(7)
    for _ in range(5):
        size = rng.uniform(0.02, 0.12, 3)
        rot, xpos = _rotation(rng), rng.normal(size=3)
        expected = (xpos + _surface(gtype, size) @ rot.T)[:, 2].min()
        got = convert.geom_lowest_z(gtype, size, xpos, rot.reshape(-1))
        assert got == pytest.approx(expected, abs=2e-5)


def test_an_unsupported_foot_geom_is_an_error_naming_its_type():
    import mujoco

    mesh = int(mujoco.mjtGeom.mjGEOM_MESH)
    with pytest.raises(ValueError, match=f"foot geom type {mesh} is not supported"):
        convert.geom_lowest_z(mesh, np.ones(3), np.zeros(3), np.eye(3).reshape(-1))


def _frames(num_frames: int, fps: float) -> asf_amc.MocapFrames:
    """A clip moving linearly: root along x and up, turning about z at 1 rad/s, joints ramping."""
    t = np.arange(num_frames) / fps
    yaw = 1.0 * t
    quat = np.stack([np.cos(yaw / 2), 0 * t, 0 * t, np.sin(yaw / 2)], -1)
    return asf_amc.MocapFrames(root_pos=np.stack([2.0 * t, 0 * t, 1.0 + 0.5 * t], -1), root_quat=quat,
                               joints=np.stack([t, -3 * t], -1), joint_names=("a", "b"), fps=fps, leg_length=0.9)


@pytest.mark.parametrize("num_frames,fps,dt", [(5, 10.0, 0.03), (5, 10.0, 0.1), (2, 120.0, 1 / 240), (13, 120.0, 0.03)])
def test_resample_samples_the_clip_every_dt_up_to_its_last_frame(num_frames, fps, dt):
    """k * dt for k = 0 .. floor(duration / dt), duration = (frames - 1) / fps; positions and
    joints interpolated linearly (exact for linear motion), the root's yaw by slerp (exact for
    a constant rate), positions scaled by root_scale."""
    frames = _frames(num_frames, fps)
    out = convert.resample(frames, dt, root_scale=0.8)
    duration = (num_frames - 1) / fps
    expected_times = dt * np.arange(int(np.floor(duration / dt + 1e-9)) + 1)
    np.testing.assert_allclose(out.times, expected_times)
    assert out.times[-1] <= duration + 1e-9 and duration - out.times[-1] < dt
    t = out.times
    np.testing.assert_allclose(out.position, 0.8 * np.stack([2.0 * t, 0 * t, 1.0 + 0.5 * t], -1), atol=1e-12)
    np.testing.assert_allclose(out.joints, np.stack([t, -3 * t], -1), atol=1e-12)
    np.testing.assert_allclose(out.quaternion, np.stack([np.cos(t / 2), 0 * t, 0 * t, np.sin(t / 2)], -1), atol=1e-9)
    np.testing.assert_allclose(convert.resample(frames, dt).position, out.position / 0.8)  # unscaled by default


def test_resample_refuses_a_nonpositive_step_or_a_single_frame():
    with pytest.raises(ValueError, match="dt must be positive, got 0"):
        convert.resample(_frames(5, 10.0), 0.0)
    with pytest.raises(ValueError, match="dt must be positive, got -0.1"):
        convert.resample(_frames(5, 10.0), -0.1)
    with pytest.raises(ValueError, match="a clip needs at least two frames to resample"):
        convert.resample(_frames(1, 10.0), 0.03)


@pytest.mark.parametrize("length,dt", [(25, 0.1), (24, 0.1), (100, 0.03), (82, 0.03), (7, 0.5), (5, 1.0)])
def test_stance_minima_are_each_windows_lowest_frame(length, dt):
    """One index per window of about 1 s (round(1 / dt) frames), the last partial window only
    when it holds at least half a window; each the argmin within its window."""
    heights = np.random.default_rng(length).uniform(0, 1, length)
    n = max(1, int(round(1.0 / dt)))
    expected = [s + int(np.argmin(heights[s:s + n])) for s in range(0, length, n) if length - s >= max(1, n // 2)]
    got = convert.stance_minima(heights, dt)
    np.testing.assert_array_equal(got, expected)
    assert got.dtype.kind == "i" and all(heights[i] == heights[s:s + n].min() for i, s in zip(got, range(0, length, n)))


def _walk(slope=(0.02, 0.0), dt=0.03, seconds=8.0, path=(0.5, 0.0), dip_at=None):
    """Foot heights of a walk over a tilted floor: the floor's height under the root plus a gait
    bump (0 at each stance), the root moving at `path` m/s; an optional toe dipping 10 cm at one frame."""
    t = np.arange(0, seconds, dt)
    xy = np.stack([path[0] * t, path[1] * t], -1) + [1.0, -2.0]
    heights = xy @ np.asarray(slope) + 0.08 * np.abs(np.sin(np.pi * t / 0.55)) + 0.3
    if dip_at is not None:
        heights[dip_at] -= 0.1
    return xy, heights, dt


def test_the_floor_slope_is_fitted_along_the_walk_and_ignores_a_dipping_toe():
    xy, h, dt = _walk(slope=(0.02, 0.0))
    np.testing.assert_allclose(convert.fit_floor_slope(xy, h, dt), [0.02, 0.0], atol=2e-3)
    xy, h, dt = _walk(slope=(0.02, 0.0), dip_at=101)  # an outlier window, refitted without it
    np.testing.assert_allclose(convert.fit_floor_slope(xy, h, dt), [0.02, 0.0], atol=2e-3)
    xy, h, dt = _walk(slope=(0.01, -0.03), path=(0.35, 0.35))  # diagonal: one direction of spread
    direction = np.array([1.0, 1.0]) / np.sqrt(2)
    got = convert.fit_floor_slope(xy, h, dt)
    assert got @ direction == pytest.approx(np.array([0.01, -0.03]) @ direction, abs=2e-3)
    assert abs(got @ [direction[1], -direction[0]]) < 1e-9  # across the path: left level


def test_a_floor_slope_is_left_level_when_it_cannot_or_should_not_be_removed():
    xy, h, dt = _walk(slope=(0.08, 0.0))                        # steeper than max_slope: stairs, ramps
    np.testing.assert_array_equal(convert.fit_floor_slope(xy, h, dt), [0.0, 0.0])
    xy, h, dt = _walk(slope=(0.02, 0.0), path=(0.0, 0.0))       # in place: nothing to measure
    np.testing.assert_array_equal(convert.fit_floor_slope(xy, h, dt), [0.0, 0.0])
    xy, h, dt = _walk(slope=(0.02, 0.0), seconds=2.4)           # fewer than 3 stance windows
    np.testing.assert_array_equal(convert.fit_floor_slope(xy, h, dt), [0.0, 0.0])
    xy, h, dt = _walk(slope=(0.02, 0.0), path=(0.1, 0.0))       # spread below min_spread
    assert np.std(xy[:, 0]) < 0.3
    np.testing.assert_array_equal(convert.fit_floor_slope(xy, h, dt), [0.0, 0.0])


def test_the_floor_offset_puts_the_median_stance_on_the_floor_but_bounds_penetration():
    dt = 0.1
    heights = np.tile(np.r_[0.05, np.full(9, 0.3)], 6)         # every stance at 5 cm
    assert convert.floor_offset(heights, dt) == pytest.approx(-0.05)
    heights[33] = -0.2                                         # one frame far below (a bent toe)
    assert convert.floor_offset(heights, dt) == pytest.approx(0.2 - 0.02)  # sinks it by 2 cm, no more
    assert convert.floor_offset(heights, dt, max_penetration=0.0) == pytest.approx(0.2)


@needs_mocap
def test_convert_folder_writes_every_clip_once_preferring_the_amc(tmp_path, capsys):
    """A folder as users have it (asf/, amc/, bvh/ in subfolders): every clip id once, sorted,
    the AMC when a clip is there in both formats (here a BVH of the same id sorts first); at
    the defaults (dt 0.03, floor levelled) the HDF5 holds what convert_clip writes."""
    import shutil

    src = tmp_path / "cmu"
    (src / "asf").mkdir(parents=True)
    shutil.copy(CMU / "asf" / "02.asf", src / "asf")
    for rel in ("amc/02/02_01.amc", "bvh/16/16_41.bvh"):
        (src / rel).parent.mkdir(parents=True, exist_ok=True)
        shutil.copy(CMU / rel, src / rel)
    (src / "a_bvh" / "02").mkdir(parents=True)
    shutil.copy(CMU / "bvh" / "02" / "02_03.bvh", src / "a_bvh" / "02" / "02_01.bvh")  # same id, another take
    (src / "notes.txt").write_text("not a clip")
    assert convert.clip_files(src) == [src / "amc/02/02_01.amc", src / "bvh/16/16_41.bvh"]
    out = tmp_path / "out.h5"
    assert convert.convert_folder(src, out) == ["CMU_002_01", "CMU_016_41"]
    bar = capsys.readouterr().err  # a progress bar by default, named after the file, counting clips
    assert "convert -> out.h5" in bar and "2/2" in bar and "clip/s" in bar
    single = tmp_path / "single.h5"
    convert.convert_clip(CMU / "amc/02/02_01.amc", single)
    with h5py.File(out, "r") as f, h5py.File(single, "r") as g:
        assert sorted(f) == ["CMU_002_01", "CMU_016_41"] and f["CMU_002_01"].attrs["dt"] == 0.03
        np.testing.assert_allclose(f["CMU_002_01/walkers/walker_0/position"][()],
                                   g["CMU_002_01/walkers/walker_0/position"][()])  # the AMC's
        assert np.linalg.norm(f["CMU_002_01"].attrs["hvc_floor_slope"]) > 0.005  # levelled by default
    with pytest.raises(FileNotFoundError, match=f"no .amc or .bvh files under {tmp_path / 'asf_only'}"):
        (tmp_path / "asf_only").mkdir()
        convert.convert_folder(tmp_path / "asf_only", out, progress=False)
    with pytest.raises(ValueError, match=r"walker_version must be one of \['2019', '2020'\], got '2018'"):
        convert.convert_folder(src, out, walker_version="2018", progress=False)


@needs_mocap
def test_the_offline_conversion_takes_in_clips_added_to_the_folder_since(tmp_path, monkeypatch):
    """New clips may appear in the shared folder after a machine converted it: a run then
    converts just those into the file it finds (clips already there are not redone, and with
    nothing new the file is left alone), not fail on an unknown clip id."""
    import shutil

    from hvc.mocap import source

    src = tmp_path / "cmu"
    (src / "asf").mkdir(parents=True)
    shutil.copy(CMU / "asf" / "02.asf", src / "asf")
    (src / "bvh" / "16").mkdir(parents=True)
    shutil.copy(CMU / "bvh/16/16_41.bvh", src / "bvh/16")
    out = tmp_path / "outputs" / "cmu_2019.h5"
    for var in ("HVC_MOCAP_FILE", "DM_CONTROL_DATA"):
        monkeypatch.delenv(var, raising=False)
    monkeypatch.setenv("HOME", str(tmp_path))  # no dm_control file in ~/.dm_control
    monkeypatch.setattr(source, "SHARED_CLIPS", src)
    monkeypatch.setattr(source, "converted_file", lambda version: out)
    assert source.find_mocap_file(None) == out and set(source.clip_lengths(out)) == {"CMU_016_41"}
    with h5py.File(out, "a") as f:
        f["CMU_016_41"].attrs["mark"] = 1  # gone if the clip were converted again
    before = out.stat().st_mtime_ns
    assert source.find_mocap_file(None) == out and out.stat().st_mtime_ns == before

    shutil.copy(CMU / "bvh/16/16_43.bvh", src / "bvh/16")
    assert source.find_mocap_file(None) == out
    assert source.clip_lengths(out) == {"CMU_016_41": 45, "CMU_016_43": 59}
    with h5py.File(out, "r") as f:
        assert f["CMU_016_41"].attrs["mark"] == 1
    assert sorted(p.name for p in out.parent.iterdir()) == ["cmu_2019.h5", "cmu_2019.h5.lock"]  # no partial left

    (src / "bvh/16/walk.bvh").write_text("not a CMU <subject>_<trial> name")  # cannot be converted:
    assert source.find_mocap_file(None) == out and len(source.clip_lengths(out)) == 2  # the usable file stays
    (src / "bvh/16/walk.bvh").unlink()
    out.write_bytes(b"truncated")                                              # unreadable: made again
    assert source.find_mocap_file(None) == out and len(source.clip_lengths(out)) == 2
    other = tmp_path / "elsewhere"
    shutil.copytree(src, other)
    monkeypatch.setattr(source, "SHARED_CLIPS", other)  # a conversion of another folder is not ours to extend
    shutil.copy(CMU / "bvh/35/35_17.bvh", other / "bvh/16")
    assert source.find_mocap_file(None) == out and "CMU_035_17" not in source.clip_lengths(out)


def _update_logging_conversions(src, out, log_file, start):
    """One job of the test below, in its own (spawned) process: update_conversion once every
    job is ready (`start`, a barrier), with each conversion logged and slowed so that the
    other jobs arrive while it runs."""
    import time

    from hvc.mocap import source

    real = convert.convert_folder

    def convert_folder(*args, **kwargs):
        with open(log_file, "a") as f:
            f.write("converted\n")
        time.sleep(0.5)
        return real(*args, **kwargs)

    convert.convert_folder = convert_folder
    start.wait(timeout=120)
    source.update_conversion(src, out, "2019")


@needs_mocap
def test_jobs_started_together_convert_the_new_clips_once(tmp_path):
    """Sweep jobs start at once on a machine that has not converted the new clips: one converts
    them under the lock and the others wait and find them done, none converts again or reads a
    half-written file."""
    import multiprocessing
    import shutil

    from hvc.mocap import source

    src = tmp_path / "cmu"
    (src / "asf").mkdir(parents=True)
    shutil.copy(CMU / "asf" / "02.asf", src / "asf")
    (src / "bvh" / "16").mkdir(parents=True)
    shutil.copy(CMU / "bvh/16/16_41.bvh", src / "bvh/16")
    out = tmp_path / "cmu_2019.h5"
    log_file = tmp_path / "conversions.log"
    spawn = multiprocessing.get_context("spawn")
    start = spawn.Barrier(3)
    jobs = [spawn.Process(target=_update_logging_conversions, args=(src, out, log_file, start)) for _ in range(3)]
    for job in jobs:
        job.start()
    for job in jobs:
        job.join(timeout=120)
    assert [job.exitcode for job in jobs] == [0, 0, 0]
    assert log_file.read_text() == "converted\n"
    assert source.clip_lengths(out) == {"CMU_016_41": 45}
    assert sorted(p.name for p in tmp_path.iterdir()) == ["cmu", "cmu_2019.h5", "cmu_2019.h5.lock", "conversions.log"]


@needs_mocap
def test_compute_features_defaults_and_its_missing_joints_error(poser):
    """dt 0.03, central velocities, a levelled floor and 2 cm of allowed penetration by default;
    the root's path scaled by the legs' ratio; a clip without a walker joint's angle is refused."""
    frames = convert.load_frames(CMU / "amc/02/02_01.amc")
    default = convert.compute_features(frames, poser)
    explicit = convert.compute_features(frames, poser, dt=0.03, velocity_scheme="central", level_floor=True,
                                        max_penetration=0.02)
    assert default.dt == 0.03 and np.linalg.norm(default.floor_slope) > 0.005
    assert default.z_offset == explicit.z_offset and default.leg_scale == poser.leg_length / frames.leg_length
    for k in explicit.fields:
        np.testing.assert_array_equal(default.fields[k], explicit.fields[k])
    travel = default.fields["position"][-1, :2] - default.fields["position"][0, :2]
    capture = frames.root_pos[-1, :2] - frames.root_pos[0, :2]
    assert np.linalg.norm(travel) == pytest.approx(default.leg_scale * np.linalg.norm(capture), rel=2e-3)
    short = dataclasses.replace(frames, joints=frames.joints[:, 1:], joint_names=frames.joint_names[1:])
    missing = [n for n in poser.joint_names if n not in short.joint_names]
    with pytest.raises(ValueError, match=f"^{re.escape(f'clip has no angles for walker joints {missing}')}$"):
        convert.compute_features(short, poser)


def test_walker_defaults_errors_and_mass():
    import mujoco

    poser = convert.WalkerPoser()
    assert poser.walker_version == "2019" and type(convert.make_walker()) is type(poser.walker)
    model = poser.physics.model.ptr
    assert poser.mass == pytest.approx(float(model.body_mass.sum()), rel=1e-6) and poser.mass > 30
    poser.set_pose(np.array([0, 0, 1.0]), np.array([1.0, 0, 0, 0]), np.zeros(len(poser.joint_names)))
    assert not np.any(poser.physics.data.qvel)  # no velocities given: at rest
    with pytest.raises(ValueError, match=r"^walker_version must be one of \['2019', '2020'\], got '2018'$"):
        convert.make_walker("2018")
    with pytest.raises(ValueError, match=r"walks.txt: expected a .amc or .bvh file$"):
        convert.load_frames("walks.txt")
    with pytest.raises(ValueError, match="^a clip needs at least two frames to resample$"):
        convert.resample(_frames(1, 10.0), 0.03)
    assert mujoco.mjtGeom.mjGEOM_CAPSULE  # the enum the geometry test uses


def test_stance_minima_of_too_short_a_clip_is_empty_and_of_integers():
    got = convert.stance_minima(np.zeros(10), 0.03)  # under half of a 33-step window
    assert got.shape == (0,) and got.dtype.kind == "i"


@needs_mocap
def test_write_clip_records_its_provenance_and_the_walker_in_dm_controls_layout(tmp_path, poser):
    """The group's attrs (date, source, leg scale, floor fit, highest stance foot), the walker's
    (class, model, mass, end effectors, appendages) and the per-step fields, into a new nested dir."""
    import datetime

    frames = convert.load_frames(CMU / "amc/09/09_06.amc")
    feats = convert.compute_features(frames, poser, dt=DT)
    out = tmp_path / "a" / "b" / "clips.h5"
    convert.write_clip(out, "CMU_009_06", feats, poser, source="09_06.amc", date=datetime.date(2026, 3, 14))
    walker = poser.walker
    with h5py.File(out, "r") as f:
        g = f["CMU_009_06"]
        assert (g.attrs["year"], g.attrs["month"], g.attrs["day"]) == (2026, 3, 14)
        assert g.attrs["hvc_source"] == b"09_06.amc" and g.attrs["dt"] == DT
        assert g.attrs["num_steps"] == len(feats.fields["position"])
        assert g.attrs["hvc_leg_scale"] == feats.leg_scale and g.attrs["hvc_z_offset"] == feats.z_offset
        np.testing.assert_array_equal(g.attrs["hvc_floor_slope"], feats.floor_slope)
        assert g.attrs["hvc_floor_slope"].dtype == np.float64
        stance = feats.foot_heights[convert.stance_minima(feats.foot_heights, DT)]
        assert g.attrs["hvc_max_stance_foot_height"] == stance.max()
        w = g["walkers/walker_0"]
        assert w.attrs["name"] == type(walker).__name__.encode() and w.attrs["mass"] == poser.mass
        assert list(w.attrs["end_effector_names"]) == [b.name.encode() for b in walker.end_effectors]
        assert list(w.attrs["appendage_names"]) == [b.name.encode() for b in walker.end_effectors] + [
            walker.head.name.encode()]
        np.testing.assert_array_equal(w["position"][()].T, feats.fields["position"])
    convert.write_clip(out, "CMU_009_06", feats, poser)  # replaced in place, today's date, no source
    with h5py.File(out, "r") as f:
        assert f["CMU_009_06"].attrs["hvc_source"] == b"" and f["CMU_009_06"].attrs["year"] == datetime.date.today().year


def test_finite_difference_velocities_forward_and_central(poser):
    """Per hinge dof, forward: (q[t+1] - q[t]) / dt with the last repeated; central: the mean of
    the forward differences on either side, one-sided at both ends; a single frame: zeros."""
    model = poser.physics.model.ptr
    rng = np.random.default_rng(0)
    steps, dt = 7, 0.03
    qpos = np.tile(poser.qpos(), (steps, 1))
    hinge = [j for j in range(model.njnt) if model.jnt_type[j] == 3]  # mjJNT_HINGE
    qadr, vadr = model.jnt_qposadr[hinge], model.jnt_dofadr[hinge]
    qpos[:, qadr] += np.cumsum(rng.normal(0, 0.05, (steps, len(hinge))), 0)  # uneven steps
    fwd = np.diff(qpos[:, qadr], axis=0) / dt
    forward = convert.finite_difference_qvel(model, qpos, dt, "forward")
    np.testing.assert_allclose(forward[:, vadr], np.concatenate([fwd, fwd[-1:]]), atol=1e-9)
    central = convert.finite_difference_qvel(model, qpos, dt, "central")
    expected = np.concatenate([fwd[:1], 0.5 * (fwd[:-1] + fwd[1:]), fwd[-1:]])
    np.testing.assert_allclose(central[:, vadr], expected, atol=1e-9)
    assert np.abs(central[:, :6]).max() < 1e-9  # the free joint did not move
    np.testing.assert_array_equal(convert.finite_difference_qvel(model, qpos[:1], dt, "central"), np.zeros((1, model.nv)))
    two = convert.finite_difference_qvel(model, qpos[:2], dt, "central")
    np.testing.assert_allclose(two[:, vadr], np.concatenate([fwd[:1], fwd[:1]]), atol=1e-9)
    with pytest.raises(ValueError, match="velocity_scheme must be 'central' or 'forward', got 'backward'"):
        convert.finite_difference_qvel(model, qpos, dt, "backward")


def test_wrap_to_ranges_moves_each_angle_by_whole_turns_to_nearest_its_ranges_centre():
    ranges = np.array([[-1.0, 1.0], [0.5, 2.5], [-3.0, -1.0]])
    centre = ranges.mean(axis=1)
    rng = np.random.default_rng(3)
    base = centre + rng.uniform(-np.pi + 1e-3, np.pi - 1e-3, (50, 3))   # within half a turn: unchanged
    np.testing.assert_allclose(convert.wrap_to_ranges(base, ranges), base)
    turned = base + 2 * np.pi * rng.integers(-3, 4, (50, 3))
    np.testing.assert_allclose(convert.wrap_to_ranges(turned, ranges), base, atol=1e-9)


def _asf_layout(root: Path, asf_names, clip_rel: str) -> Path:
    (root / "asf").mkdir(parents=True, exist_ok=True)
    for name in asf_names:
        (root / "asf" / name).write_text("")
    clip = root / clip_rel
    clip.parent.mkdir(parents=True, exist_ok=True)
    clip.write_text("")
    return clip


def test_find_asf_follows_the_cmu_layout(tmp_path, monkeypatch):
    """AMC: its subject's ASF beside it or in <root>/asf; BVH: 16.asf first, else the first ASF
    there is; a miss names what was looked for and where."""
    amc = _asf_layout(tmp_path / "a", ["07.asf", "16.asf"], "amc/07/07_05.amc")
    assert convert.find_asf(amc, bvh=False) == tmp_path / "a/asf/07.asf"
    (amc.parent / "07.asf").write_text("")
    assert convert.find_asf(amc, bvh=False) == amc.parent / "07.asf"       # beside the clip wins
    bvh = _asf_layout(tmp_path / "b", ["02.asf", "09.asf", "16.asf"], "bvh/35/35_17.bvh")
    assert convert.find_asf(bvh, bvh=True) == tmp_path / "b/asf/16.asf"
    bvh = _asf_layout(tmp_path / "c", ["09.asf", "02.asf"], "bvh/35/35_17.bvh")
    assert convert.find_asf(bvh, bvh=True) == tmp_path / "c/asf/02.asf"   # any: the first by name
    named = _asf_layout(tmp_path / "d", ["16.asf"], "bvh/x/walk.bvh")      # no CMU id in the name
    assert convert.find_asf(named, bvh=True) == tmp_path / "d/asf/16.asf"
    flat = _asf_layout(tmp_path / "e", [], "bvh/49_02.bvh")
    (tmp_path / "e" / "asf" / "49.asf").write_text("")
    monkeypatch.chdir(tmp_path / "e")
    assert convert.find_asf(Path("bvh/49_02.bvh"), bvh=True) == Path("asf/49.asf")  # a path of two parts only
    lone = _asf_layout(tmp_path / "f", ["02.asf"], "amc/07/07_05.amc")
    with pytest.raises(FileNotFoundError, match=r"07_05.amc: no ASF found; looked for subject 07's ASF in \[.*"
                                                r"amc/07', .*amc/asf', .*f/asf'\]; pass asf_path="):
        convert.find_asf(lone, bvh=False)
    bare = tmp_path / "g" / "bvh" / "16" / "16_41.bvh"
    bare.parent.mkdir(parents=True)
    with pytest.raises(FileNotFoundError, match=r"looked for any CMU ASF \(for bone axes\) in"):
        convert.find_asf(bare, bvh=True)
    assert flat.exists()


@needs_mocap
def test_convert_clip_passes_its_options_through(tmp_path, poser):
    """dt, the velocity scheme, floor levelling, the ASF, the id and the date reach the file."""
    import datetime
    import shutil

    amc = tmp_path / "elsewhere" / "02_01.amc"                 # no CMU layout: the ASF must be given
    amc.parent.mkdir()
    shutil.copy(CMU / "amc/02/02_01.amc", amc)
    out = tmp_path / "out.h5"
    common = dict(walker_version="2019", asf_path=CMU / "asf/02.asf", poser=poser)
    convert.convert_clip(amc, out, dt=0.05, clip_id="plain", level_floor=False, velocity_scheme="forward",
                         date=datetime.date(2020, 1, 2), **common)
    convert.convert_clip(amc, out, dt=0.05, clip_id="levelled", **common)
    frames = convert.load_frames(CMU / "amc/02/02_01.amc")
    with h5py.File(out, "r") as f:
        plain, levelled = f["plain"], f["levelled"]
        assert plain.attrs["dt"] == 0.05 and plain.attrs["num_steps"] == int(np.floor((frames.num_frames - 1) / 120 / 0.05 + 1e-9)) + 1
        assert plain.attrs["hvc_source"] == b"02_01.amc" and (plain.attrs["year"], plain.attrs["day"]) == (2020, 2)
        np.testing.assert_array_equal(plain.attrs["hvc_floor_slope"], [0.0, 0.0])
        assert np.linalg.norm(levelled.attrs["hvc_floor_slope"]) > 0.005  # subject 02's floor is tilted
        pos = plain["walkers/walker_0/position"][()].T
        vel = plain["walkers/walker_0/velocity"][()].T
        np.testing.assert_allclose(vel[:-1], np.diff(pos, axis=0) / 0.05, atol=1e-6)  # forward differences
    with pytest.raises(ValueError, match="poser is for walker 2019, walker_version='2020'"):
        convert.convert_clip(amc, out, walker_version="2020", poser=poser)


def test_find_asf_looks_two_levels_up_from_a_clip_three_parts_deep(tmp_path, monkeypatch):
    clip = _asf_layout(tmp_path, ["16.asf"], "bvh/16/16_41.bvh")
    monkeypatch.chdir(tmp_path)
    assert convert.find_asf(Path("bvh/16/16_41.bvh"), bvh=True) == Path("asf/16.asf")
    assert clip.exists()


def test_the_floor_slope_is_fitted_in_both_directions_of_a_walk_that_spreads_in_both():
    """A walk around a square (both directions spread): the gradient's two components add up."""
    dt, seconds = 0.03, 16.0
    t = np.arange(0, seconds, dt)
    side = (t % 16.0) / 4.0                      # four legs of 4 s, 0.5 m/s
    leg, f = side.astype(int), side % 1.0
    corners = np.array([[0, 0], [2, 0], [2, 2], [0, 2], [0, 0]], float)
    xy = corners[leg] + (corners[leg + 1] - corners[leg]) * f[:, None]
    slope = np.array([0.015, -0.025])
    heights = xy @ slope + 0.08 * np.abs(np.sin(np.pi * t / 0.55)) + 0.3
    np.testing.assert_allclose(convert.fit_floor_slope(xy, heights, dt), slope, atol=2e-3)
