"""Reference clips from dm_control-format HDF5 files, by clip id.

Loading goes through dm_control's `HDF5TrajectoryLoader`, so dm_control's fitted
`cmu_2020_*.h5`, its `test_trajectories.h5` and files written by `hvc.mocap.convert`
are read by the same code the dm_control tracking tasks use. The result is a plain
frozen dataclass of (T, dim) float64 arrays, which is what reward and fragment code
want to index.
"""

from __future__ import annotations

import dataclasses
import warnings
from pathlib import Path

import h5py
import numpy as np
from dm_control.locomotion.mocap import loader as mocap_loader

from hvc.errors import ClipNotFoundError  # noqa: F401  (raised here, re-exported)
from hvc.mocap.source import check_mocap_file

#: ReferenceClip array fields; each is a `walker/<field>` entry of dm_control's Trajectory.
CLIP_FIELDS: tuple[str, ...] = (
    "joints", "joints_velocity", "position", "quaternion", "velocity", "angular_velocity",
    "end_effectors", "appendages", "body_positions", "body_quaternions", "center_of_mass",
)  # fmt: skip


@dataclasses.dataclass(frozen=True)
class ReferenceClip:
    """One walker's reference trajectory; every array is float64 shaped (num_steps, dim).

    `velocity` is world-frame, `angular_velocity` is in the root body frame (MuJoCo free
    joint convention); `end_effectors`/`appendages` are egocentric, relative to the root.
    """

    clip_id: str
    dt: float
    num_steps: int
    joints: np.ndarray
    joints_velocity: np.ndarray
    position: np.ndarray
    quaternion: np.ndarray
    velocity: np.ndarray
    angular_velocity: np.ndarray
    end_effectors: np.ndarray
    appendages: np.ndarray
    body_positions: np.ndarray
    body_quaternions: np.ndarray
    center_of_mass: np.ndarray

    def heading(self) -> np.ndarray:
        """Unwrapped root heading (rad, counter-clockwise from +x seen from above) per step."""
        return root_heading(self.quaternion)


def root_heading(quaternion: np.ndarray) -> np.ndarray:
    """Heading (rad, unwrapped) of the CMU walker root's forward axis from (T, 4) w-first quaternions.

    The root body's local z axis is the ASF root's forward (+Z) axis and stays horizontal
    for an upright walker, so its azimuth is the facing direction.
    """
    w, x, y, z = np.asarray(quaternion, np.float64).T
    fwd_x, fwd_y = 2 * (x * z + w * y), 2 * (y * z - w * x)  # third column of the rotation matrix
    return np.unwrap(np.arctan2(fwd_y, fwd_x))


def list_clips(h5_path: str | Path) -> list[str]:
    """Clip ids (top-level groups) in a dm_control-format HDF5 file, sorted."""
    with h5py.File(_existing(h5_path), "r") as f:
        return sorted(f.keys())


def load_clip(h5_path: str | Path, clip_id: str, start_step: int = 0, end_step: int | None = None) -> ReferenceClip:
    """Steps [start_step, end_step) of a clip (Python slice semantics; end_step=None is the end).

    The slicing is done here rather than by dm_control's `Trajectory`, whose `end_step` is
    inclusive and treats 0 as "not given".
    """
    path = _existing(h5_path)
    loader = mocap_loader.HDF5TrajectoryLoader(str(path))
    try:
        if clip_id not in loader.keys():
            ids = loader.keys()
            some = ", ".join(ids[:5]) + (", ..." if len(ids) > 5 else "")
            raise ClipNotFoundError(f"clip {clip_id!r} not found in {path} ({len(ids)} clips: {some})")
        with warnings.catch_warnings():
            # protobuf 6 deprecates FieldDescriptor.label, which dm_control's loader calls per field.
            warnings.filterwarnings("ignore", message=r"label\(\) is deprecated", category=DeprecationWarning)
            trajectory = loader.get_trajectory(clip_id, zero_out_velocities=False)
        data = trajectory.as_dict()
        dt = float(trajectory.dt)
    finally:
        # The loader keeps its h5py file open and has no close(); close it so the file can be rewritten.
        h5 = getattr(loader, "_h5_file", None)
        if h5 is not None:
            h5.close()
    total = len(data["walker/position"])
    stop = total if end_step is None else end_step
    if not 0 <= start_step < stop <= total:
        raise ValueError(f"clip {clip_id!r} has {total} steps; cannot take steps [{start_step}, {end_step})")
    steps = stop - start_step
    arrays = {
        k: np.ascontiguousarray(np.asarray(data[f"walker/{k}"], dtype=np.float64)[start_step:stop].reshape(steps, -1))
        for k in CLIP_FIELDS
    }
    return ReferenceClip(clip_id=clip_id, dt=dt, num_steps=steps, **arrays)


def _existing(h5_path: str | Path) -> Path:
    return check_mocap_file(Path(h5_path))
