"""Convert CMU AMC / cgspeed BVH clips to dm_control's mocap HDF5 layout.

The output is read by dm_control's own `mocap.loader.HDF5TrajectoryLoader`, so our
clips and dm_control's fitted `cmu_2020_*.h5` go through one loader. Pipeline per clip:

1. parse to root pose + 56 hinge angles at 120 fps (`asf_amc`, `bvh`);
2. scale the root translation by walker leg / subject leg (left femur + tibia), since
   the walker's legs differ from the subject's and the feet would otherwise float or
   sink;
3. resample to the control step `dt`: linear for positions and angles, slerp for the
   root quaternion; then put the feet on the floor: remove a tilt of the capture floor
   (`fit_floor_slope`) and add a per-clip z offset (`floor_offset`) so the stance foot's
   lowest geom point is at z = 0 and no step sinks more than 2 cm;
4. pose the dm_control walker at each step and read every field with
   `reference_pose.utils.get_features`, after writing finite-difference velocities into
   qvel. Velocities are *central* differences of the resampled poses (one-sided at the
   two ends), taken with `mj_differentiatePos`, so they use MuJoCo's free-joint
   convention that `get_features` reports: linear velocity in the world frame, angular
   velocity in the root body's frame. `velocity_scheme="forward"` gives the forward
   differences of dm_control's `suite.utils.parse_amc` instead (last step repeated).
5. write the HDF5 groups and attributes exactly as dm_control's `test_trajectories.h5`.
"""

from __future__ import annotations

import dataclasses
import datetime
import re
from collections.abc import Collection, Iterable
from pathlib import Path
from typing import Literal

import h5py
import mujoco
import numpy as np
from dm_control import mjcf
from dm_control.locomotion.arenas import floors
from dm_control.locomotion.tasks.reference_pose import utils as ref_utils
from dm_control.locomotion.walkers import cmu_humanoid

from hvc.mocap.asf_amc import MocapFrames, load_amc
from hvc.mocap.bvh import load_bvh
from hvc.rotations import slerp

#: dm_control `mocap_pb2.Walker.Model` values, recorded so a file says which body its poses are for.
WALKER_MODELS: dict[str, int] = {"2019": 1, "2020": 4}
VelocityScheme = Literal["central", "forward"]
_CLIP_RE = re.compile(r"^(\d+)_(\d+)")
_FOOT_BODIES = ("lfoot", "rfoot")  # their subtrees include the toes
_FIELDS = (
    "position", "quaternion", "velocity", "angular_velocity", "joints", "joints_velocity",
    "center_of_mass", "end_effectors", "appendages", "body_positions", "body_quaternions",
)  # fmt: skip


# --------------------------------------------------------------------------- walker
def make_walker(walker_version: str = "2019") -> cmu_humanoid.CMUHumanoidPositionControlled:
    """The position-controlled CMU humanoid the clip is converted for ("2019" or "2020")."""
    if walker_version == "2019":
        return cmu_humanoid.CMUHumanoidPositionControlled()
    if walker_version == "2020":
        return cmu_humanoid.CMUHumanoidPositionControlledV2020()
    raise ValueError(f"walker_version must be one of {sorted(WALKER_MODELS)}, got {walker_version!r}")


class WalkerPoser:
    """The walker on a floor arena in an mjcf Physics, posed kinematically (no simulation).

    Building the walker and compiling the model is slow next to posing, so one poser serves a whole folder.
    """

    def __init__(self, walker_version: str = "2019") -> None:
        self.walker_version = walker_version
        self.walker = make_walker(walker_version)
        arena = floors.Floor()
        self.walker.create_root_joints(arena.attach(self.walker))
        self.physics = mjcf.Physics.from_mjcf_model(arena.mjcf_model)
        self._freejoint = self.physics.bind(mjcf.get_attachment_frame(self.walker.mjcf_model).freejoint)
        self._joints = self.physics.bind(self.walker.mocap_joints)
        self.joint_names: tuple[str, ...] = tuple(j.name for j in self.walker.mocap_joints)
        feet = [g for b in _FOOT_BODIES for g in self.walker.mjcf_model.find("body", b).find_all("geom")]
        self._feet = self.physics.bind(feet)
        body = self.walker.mjcf_model.find
        pos = self.physics.bind([body("body", "ltibia"), body("body", "lfoot")]).pos
        #: Walker femur + tibia (m): the distances hip -> knee -> ankle in the model.
        self.leg_length = float(np.linalg.norm(pos, axis=1).sum())
        self.mass = float(self.physics.bind(self.walker.root_body).subtreemass)

    def set_pose(
        self, position: np.ndarray, quaternion: np.ndarray, joints: np.ndarray, qvel: np.ndarray | None = None
    ) -> None:
        """Root pose + joint angles (walker.mocap_joints order), full qvel (default zero), then kinematics."""
        self._freejoint.qpos = np.concatenate([position, quaternion])
        self._joints.qpos = joints
        self.physics.data.qvel[:] = 0.0 if qvel is None else qvel
        self.physics.forward()

    @property
    def joint_ranges(self) -> np.ndarray:
        """(56, 2) hinge limits in radians, walker.mocap_joints order."""
        return np.array(self._joints.range)

    def lowest_foot_z(self) -> float:
        """Height of the lowest point of any foot/toe geom in the current pose (m)."""
        return min(geom_lowest_z(int(gtype), size, xpos, xmat)
                   for gtype, size, xpos, xmat in zip(self._feet.type, self._feet.size, self._feet.xpos, self._feet.xmat))

    def foot_heights(self, position: np.ndarray, quaternion: np.ndarray, joints: np.ndarray) -> np.ndarray:
        """Per step (rows of the (T, .) inputs) the lowest foot point's height (m)."""
        out = np.empty(len(position))
        for t in range(len(position)):
            self.set_pose(position[t], quaternion[t], joints[t])
            out[t] = self.lowest_foot_z()
        return out

    def qpos(self) -> np.ndarray:
        return np.array(self.physics.data.qpos)


def geom_lowest_z(gtype: int, size: np.ndarray, xpos: np.ndarray, xmat: np.ndarray) -> float:
    """Height of a geom's lowest point (m) from its MuJoCo type, size, world position and
    row-major rotation (local to world): the support point against -z, in closed form."""
    zaxis_row = np.asarray(xmat).reshape(3, 3)[2]  # z components of the geom's local axes
    if gtype == mujoco.mjtGeom.mjGEOM_SPHERE:
        low = xpos[2] - size[0]
    elif gtype == mujoco.mjtGeom.mjGEOM_CAPSULE:
        low = xpos[2] - abs(zaxis_row[2]) * size[1] - size[0]
    elif gtype == mujoco.mjtGeom.mjGEOM_BOX:
        low = xpos[2] - np.abs(zaxis_row) @ size
    elif gtype == mujoco.mjtGeom.mjGEOM_CYLINDER:
        low = xpos[2] - abs(zaxis_row[2]) * size[1] - np.hypot(*zaxis_row[:2]) * size[0]
    elif gtype == mujoco.mjtGeom.mjGEOM_ELLIPSOID:
        low = xpos[2] - np.sqrt(np.sum((zaxis_row * size) ** 2))
    else:
        raise ValueError(f"foot geom type {gtype} is not supported for floor placement")
    return float(low)


# --------------------------------------------------------------------------- resampling
@dataclasses.dataclass(frozen=True)
class Resampled:
    times: np.ndarray  # (T,) seconds from the first frame
    position: np.ndarray  # (T, 3)
    quaternion: np.ndarray  # (T, 4)
    joints: np.ndarray  # (T, J), same joint order as the input


def resample(frames: MocapFrames, dt: float, root_scale: float = 1.0) -> Resampled:
    """Sample the clip at t = k * dt up to its last frame (positions lerped, root quaternion slerped)."""
    if dt <= 0:
        raise ValueError(f"dt must be positive, got {dt}")
    if frames.num_frames < 2:
        raise ValueError("a clip needs at least two frames to resample")
    duration = (frames.num_frames - 1) / frames.fps
    times = np.arange(int(np.floor(duration / dt + 1e-9)) + 1) * dt
    x = times * frames.fps  # fractional source frame
    i0 = np.minimum(np.floor(x + 1e-9).astype(int), frames.num_frames - 2)
    u = np.clip(x - i0, 0.0, 1.0)

    def lerp(a: np.ndarray) -> np.ndarray:
        return a[i0] * (1.0 - u)[:, None] + a[i0 + 1] * u[:, None]

    return Resampled(
        times=times,
        position=lerp(frames.root_pos) * root_scale,
        quaternion=slerp(frames.root_quat[i0], frames.root_quat[i0 + 1], u),
        joints=lerp(frames.joints),
    )


def finite_difference_qvel(model: mujoco.MjModel, qpos: np.ndarray, dt: float, scheme: VelocityScheme) -> np.ndarray:
    """qvel (T, nv) from qpos (T, nq) with MuJoCo's position differencing (free joint quaternions included)."""
    steps, nv = qpos.shape[0], model.nv
    forward = np.zeros((max(steps - 1, 0), nv))
    for t in range(steps - 1):
        mujoco.mj_differentiatePos(model, forward[t], dt, qpos[t], qpos[t + 1])
    if steps == 1:
        return np.zeros((1, nv))
    if scheme == "forward":
        return np.concatenate([forward, forward[-1:]])
    if scheme != "central":
        raise ValueError(f"velocity_scheme must be 'central' or 'forward', got {scheme!r}")
    # The mean of the backward and forward differences is the central difference; for the
    # free joint both rotation vectors are the same body-frame angular velocity at t.
    qvel = np.empty((steps, nv))
    qvel[0], qvel[-1] = forward[0], forward[-1]
    qvel[1:-1] = 0.5 * (forward[:-1] + forward[1:])
    return qvel


def wrap_to_ranges(joints: np.ndarray, ranges: np.ndarray) -> np.ndarray:
    """Shift each angle by whole turns to the copy nearest its hinge range's centre (same pose).

    Some AMC channels accumulate turns (131_03's right thumb reaches 696 deg). Velocities
    are taken before this on the continuous angles; only stored positions are wrapped.
    Values within half a turn of the range centre, i.e. all normal data, are unchanged.
    """
    centre = ranges.mean(axis=1)
    return joints - 2 * np.pi * np.round((joints - centre) / (2 * np.pi))


def stance_minima(foot_heights: np.ndarray, dt: float, window_s: float = 1.0) -> np.ndarray:
    """Indices of the lowest-foot minimum in each `window_s` window (the last partial window if >= half).

    A window of about one gait cycle always contains a stance phase, so these minima trace
    the floor under the subject; their heights show how well the clip sits on z = 0.
    """
    n = max(1, int(round(window_s / dt)))
    starts = [s for s in range(0, len(foot_heights), n) if len(foot_heights) - s >= max(1, n // 2)]
    return np.array([s + int(np.argmin(foot_heights[s : s + n])) for s in starts], dtype=int)


def fit_floor_slope(
    xy: np.ndarray, foot_heights: np.ndarray, dt: float, min_spread: float = 0.3, max_slope: float = 0.05
) -> np.ndarray:
    """Gradient (dz/dx, dz/dy) of the capture floor under the stance feet, or zeros if not measurable.

    Some CMU sessions (subjects 02, 07, 08) were captured with the floor tilted in the
    capture frame: the stance foot rises over a walk, so a constant z offset leaves the feet
    floating by the end (docs/results/design_measurements/). The floor is fitted as a plane through the
    per-window stance minima at the root's xy, refitted once without outliers (a toe bent
    beyond the walker's range dips through the floor). Directions in which the root moves
    less than `min_spread` (std, m) are left level (a straight walk measures the slope only
    along its path, a clip in place not at all); slopes above `max_slope` (stairs, ramps)
    are not removed.
    """
    idx = stance_minima(foot_heights, dt)
    keep = np.ones(len(idx), dtype=bool)
    grad = np.zeros(2)
    for _ in range(2):
        if keep.sum() < 3:
            return np.zeros(2)
        p = xy[idx[keep]] - xy[idx[keep]].mean(axis=0)
        h = foot_heights[idx[keep]] - foot_heights[idx[keep]].mean()
        u, sv, vt = np.linalg.svd(p, full_matrices=False)
        grad = np.zeros(2)
        for k in range(len(sv)):
            if sv[k] / np.sqrt(len(p)) >= min_spread:
                grad += vt[k] * (u[:, k] @ h) / sv[k]
        resid = foot_heights[idx] - xy[idx] @ grad
        resid -= np.median(resid[keep])
        keep = np.abs(resid) <= max(0.01, 3.0 * np.median(np.abs(resid)))
    return grad if np.linalg.norm(grad) <= max_slope else np.zeros(2)


def floor_offset(foot_heights: np.ndarray, dt: float, max_penetration: float = 0.02) -> float:
    """z shift that puts the typical (median) stance foot on z = 0, but sinks no step more than `max_penetration`.

    Plain "lowest point over the clip on the floor" lets one odd frame (a toe bent beyond
    the walker's range, as in 131_09) lift the whole clip off the floor; bounding the
    penetration instead keeps typical stance on the floor. `max_penetration=0` gives
    the plain rule.
    """
    stance = foot_heights[stance_minima(foot_heights, dt)]
    return float(max(-np.median(stance), -foot_heights.min() - max_penetration))


# --------------------------------------------------------------------------- clips
def clip_id_from_path(path: str | Path) -> str:
    """`.../16_41.bvh` -> `CMU_016_41` (dm_control's naming of CMU clips)."""
    m = _CLIP_RE.match(Path(path).stem)
    if not m:
        raise ValueError(f"cannot read a CMU <subject>_<trial> id from file name {Path(path).name!r}")
    return f"CMU_{int(m.group(1)):03d}_{int(m.group(2)):02d}"


def find_asf(path: str | Path, bvh: bool) -> Path:
    """The ASF for a clip in the CMU layout `<root>/{amc,bvh}/<subject>/<id>.<ext>` + `<root>/asf/`.

    AMC needs its own subject's ASF; BVH only needs bone axes, identical for every CMU
    subject, so it prefers 16.asf and accepts any.
    """
    path = Path(path)
    subject = _CLIP_RE.match(path.stem).group(1) if _CLIP_RE.match(path.stem) else ""
    dirs = [path.parent, path.parent.parent / "asf"]
    if len(path.parents) > 2:
        dirs.append(path.parents[2] / "asf")
    names = [f"{subject}.asf", f"{int(subject):02d}.asf"] if subject else []
    if bvh:
        names.append("16.asf")
    for d in dirs:
        for name in names:
            if (d / name).is_file():
                return d / name
    if bvh:
        for d in dirs:
            found = sorted(d.glob("*.asf")) if d.is_dir() else []
            if found:
                return found[0]
    what = "any CMU ASF (for bone axes)" if bvh else f"subject {subject}'s ASF"
    raise FileNotFoundError(f"{path}: no ASF found; looked for {what} in {[str(d) for d in dirs]}; pass asf_path=")


def load_frames(path: str | Path, asf_path: str | Path | None = None) -> MocapFrames:
    """Parse an .amc (with its subject's ASF) or a cgspeed .bvh into `MocapFrames` at 120 fps."""
    path = Path(path)
    ext = path.suffix.lower()
    if ext not in (".amc", ".bvh"):
        raise ValueError(f"{path}: expected a .amc or .bvh file")
    asf = Path(asf_path) if asf_path is not None else find_asf(path, bvh=ext == ".bvh")
    return load_amc(path, asf) if ext == ".amc" else load_bvh(path, asf)


@dataclasses.dataclass(frozen=True)
class ClipFeatures:
    """Everything written for one clip: dm_control's per-step fields as (T, dim) plus conversion facts."""

    fields: dict[str, np.ndarray]
    dt: float
    leg_scale: float
    z_offset: float  # added to root z after levelling
    floor_slope: np.ndarray  # (2,) dz/dx, dz/dy removed from the capture floor
    foot_heights: np.ndarray  # (T,) lowest foot point per step, as written


def compute_features(
    frames: MocapFrames,
    poser: WalkerPoser,
    dt: float = 0.03,
    velocity_scheme: VelocityScheme = "central",
    level_floor: bool = True,
    max_penetration: float = 0.02,
) -> ClipFeatures:
    """Steps 2-4 of the pipeline: scale, resample, floor the feet, pose the walker, read features.

    With `level_floor`, a tilt of the capture floor (see `fit_floor_slope`) is removed by
    shifting root height linearly with the root's xy; then a constant z offset
    (`floor_offset`) puts the stance feet on the floor.
    """
    missing = [n for n in poser.joint_names if n not in frames.joint_names]
    if missing:
        raise ValueError(f"clip has no angles for walker joints {missing}")
    leg_scale = poser.leg_length / frames.leg_length
    rs = resample(frames, dt, root_scale=leg_scale)
    order = [frames.joint_names.index(n) for n in poser.joint_names]
    joints = rs.joints[:, order]
    position = rs.position.copy()
    heights = poser.foot_heights(position, rs.quaternion, joints)
    slope = fit_floor_slope(position[:, :2], heights, dt) if level_floor else np.zeros(2)
    position[:, 2] -= (position[:, :2] - position[0, :2]) @ slope
    heights -= (position[:, :2] - position[0, :2]) @ slope
    z_offset = floor_offset(heights, dt, max_penetration)
    position[:, 2] += z_offset

    qpos = np.empty((len(position), poser.physics.model.nq))
    feet = np.empty(len(position))
    for t in range(len(position)):
        poser.set_pose(position[t], rs.quaternion[t], joints[t])
        qpos[t] = poser.qpos()
        feet[t] = poser.lowest_foot_z()
    qvel = finite_difference_qvel(poser.physics.model.ptr, qpos, dt, velocity_scheme)
    stored = wrap_to_ranges(joints, poser.joint_ranges)

    rows: dict[str, list[np.ndarray]] = {k: [] for k in _FIELDS}
    for t in range(len(position)):
        poser.set_pose(position[t], rs.quaternion[t], stored[t], qvel=qvel[t])
        feats = ref_utils.get_features(poser.physics, poser.walker)
        for k in _FIELDS:
            rows[k].append(np.asarray(feats[k], dtype=np.float64).reshape(-1))
    fields = {k: np.stack(v) for k, v in rows.items()}
    return ClipFeatures(
        fields=fields, dt=dt, leg_scale=leg_scale, z_offset=z_offset, floor_slope=slope, foot_heights=feet
    )


def write_clip(
    out_h5: str | Path,
    clip_id: str,
    feats: ClipFeatures,
    poser: WalkerPoser,
    source: str = "",
    date: datetime.date | None = None,
) -> None:
    """Write (replace) one clip group in dm_control's HDF5 layout; extra `hvc_*` attrs are provenance only."""
    date = date or datetime.date.today()
    steps = len(feats.fields["position"])
    walker = poser.walker
    Path(out_h5).parent.mkdir(parents=True, exist_ok=True)
    with h5py.File(out_h5, "a") as f:
        if clip_id in f:
            del f[clip_id]
        g = f.create_group(clip_id)
        g.attrs["dt"] = np.float64(feats.dt)
        g.attrs["num_steps"] = np.int64(steps)
        g.attrs["year"], g.attrs["month"], g.attrs["day"] = (np.int64(v) for v in (date.year, date.month, date.day))
        # Not proto fields, so dm_control's loader ignores them.
        g.attrs["hvc_source"] = np.bytes_(source)
        g.attrs["hvc_leg_scale"] = np.float64(feats.leg_scale)
        g.attrs["hvc_z_offset"] = np.float64(feats.z_offset)
        g.attrs["hvc_floor_slope"] = np.asarray(feats.floor_slope, dtype=np.float64)
        stance = feats.foot_heights[stance_minima(feats.foot_heights, feats.dt)]
        g.attrs["hvc_max_stance_foot_height"] = np.float64(stance.max())
        w = g.create_group("walkers/walker_0")
        w.attrs["name"] = np.bytes_(type(walker).__name__)
        w.attrs["model"] = np.int64(WALKER_MODELS[poser.walker_version])
        w.attrs["mass"] = np.float64(poser.mass)
        w.attrs["end_effector_names"] = np.array([b.name for b in walker.end_effectors], dtype="S")
        w.attrs["appendage_names"] = np.array([b.name for b in walker.end_effectors] + [walker.head.name], dtype="S")
        w.create_group("scaling")
        w.create_group("markers")
        for k in _FIELDS:
            w.create_dataset(k, data=np.ascontiguousarray(feats.fields[k].T))
        g.create_group("props")


def _convert(
    path: Path,
    out_h5: str | Path,
    poser: WalkerPoser,
    dt: float,
    asf_path: str | Path | None,
    clip_id: str | None,
    date: datetime.date | None,
    velocity_scheme: VelocityScheme,
    level_floor: bool,
) -> str:
    clip_id = clip_id or clip_id_from_path(path)
    frames = load_frames(path, asf_path)
    feats = compute_features(frames, poser, dt=dt, velocity_scheme=velocity_scheme, level_floor=level_floor)
    write_clip(out_h5, clip_id, feats, poser, source=path.name, date=date)
    return clip_id


def _check_version(walker_version: str) -> None:
    if walker_version not in WALKER_MODELS:
        raise ValueError(f"walker_version must be one of {sorted(WALKER_MODELS)}, got {walker_version!r}")


def convert_clip(
    path: str | Path,
    out_h5: str | Path,
    walker_version: str = "2019",
    dt: float = 0.03,
    asf_path: str | Path | None = None,
    clip_id: str | None = None,
    velocity_scheme: VelocityScheme = "central",
    level_floor: bool = True,
    date: datetime.date | None = None,
    poser: WalkerPoser | None = None,
) -> str:
    """Convert one .amc/.bvh clip into `out_h5` (created or appended; a same-id clip is replaced).

    `asf_path` defaults to the CMU layout's `asf/` folder (`find_asf`). Pass a `poser` to
    reuse one walker over many calls. Returns the clip id (`CMU_016_41` from `16_41.bvh`
    unless `clip_id` is given).
    """
    _check_version(walker_version)
    if poser is None:
        poser = WalkerPoser(walker_version)
    elif poser.walker_version != walker_version:
        raise ValueError(f"poser is for walker {poser.walker_version}, walker_version={walker_version!r}")
    return _convert(Path(path), out_h5, poser, dt, asf_path, clip_id, date, velocity_scheme, level_floor)


def clip_files(source_dir: Path) -> list[Path]:
    """All .amc/.bvh files under `source_dir`; when a clip exists in both, the AMC (the original) wins."""
    by_id: dict[str, Path] = {}
    for p in sorted(source_dir.rglob("*")):
        if p.suffix.lower() in (".amc", ".bvh") and p.is_file():
            cid = clip_id_from_path(p)
            if cid not in by_id or p.suffix.lower() == ".amc":
                by_id[cid] = p
    return [by_id[k] for k in sorted(by_id)]


def convert_folder(
    source_dir: str | Path,
    out_h5: str | Path,
    walker_version: str = "2019",
    dt: float = 0.03,
    progress: bool = True,
    velocity_scheme: VelocityScheme = "central",
    level_floor: bool = True,
    skip: Collection[str] = (),
) -> list[str]:
    """Convert every clip under a CMU folder (`amc/`, `bvh/`, `asf/`) into one HDF5, but those
    whose ids are in `skip`; returns the ids written."""
    _check_version(walker_version)
    source_dir = Path(source_dir)
    files = clip_files(source_dir)
    if not files:
        raise FileNotFoundError(f"no .amc or .bvh files under {source_dir}")
    files = [p for p in files if clip_id_from_path(p) not in skip]
    poser = WalkerPoser(walker_version)
    it: Iterable[Path] = files
    if progress:
        from tqdm import tqdm

        it = tqdm(files, desc=f"convert -> {Path(out_h5).name}", unit="clip")
    return [_convert(p, out_h5, poser, dt, None, None, None, velocity_scheme, level_floor) for p in it]
