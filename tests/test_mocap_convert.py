"""Mocap conversion (AMC/BVH -> dm_control HDF5) and clip loading, on real CMU data.

Tests that need the shared CMU clips skip when ../shared/mocap is absent; the loader
tests on dm_control's shipped test_trajectories.h5 always run. Only three short clips
are converted (one walker build), so the file runs in a few seconds.
"""

from __future__ import annotations

import csv
import dataclasses
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
