"""Reference trajectories for tracking: a clip segment, or a gait cycle looped.

The HDF5 fields are already per control step (velocities by finite differences of the
positions, as in the paper). For cyclic behaviours (run) the paper isolates one gait
cycle and blends it circularly by weighted linear interpolation of poses into a
repeating loop whose time input is a sawtooth; `loop_cycle` does that, placing each
repetition where the previous one ended (position and heading carried over).
"""
from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Any, Mapping

import numpy as np

from hvc.mocap.clips import load_clip, root_heading
from hvc.rotations import quat_mul, rot_z, yaw_quat


@dataclass(frozen=True)
class Reference:
    """Per-step reference features, arrays shaped (T, ...); `phase` is the policy's time input."""

    clip_id: str
    dt: float
    cyclic: bool
    joints: np.ndarray            # (T, 56), mocap joint order
    joints_velocity: np.ndarray   # (T, 56)
    position: np.ndarray          # (T, 3) root, world
    quaternion: np.ndarray        # (T, 4) root, world, w first
    velocity: np.ndarray          # (T, 3) root, world
    angular_velocity: np.ndarray  # (T, 3) root, root frame (as the free joint's qvel)
    end_effectors: np.ndarray     # (T, n_ee, 3) egocentric
    phase: np.ndarray             # (T,) normalised time in [0, 1] (sawtooth when cyclic)

    @property
    def num_steps(self) -> int:
        return int(self.joints.shape[0])

    def segment(self, start: int, end: int | None = None) -> "Reference":
        sl = slice(start, end)
        return replace(self, joints=self.joints[sl], joints_velocity=self.joints_velocity[sl],
                       position=self.position[sl], quaternion=self.quaternion[sl], velocity=self.velocity[sl],
                       angular_velocity=self.angular_velocity[sl], end_effectors=self.end_effectors[sl],
                       phase=_linear_phase(len(self.joints[sl])) if not self.cyclic else self.phase[sl])


def cycle_steps(phase: np.ndarray) -> int:
    """Steps of a looped reference's first gait cycle (up to its phase's first wrap); the
    whole length when it does not wrap."""
    wraps = np.flatnonzero(np.diff(phase) < 0)
    return int(wraps[0]) + 1 if len(wraps) else len(phase)


def _linear_phase(n: int) -> np.ndarray:
    return np.linspace(0.0, 1.0, n) if n > 1 else np.zeros(n)


def from_clip(clip, start: int = 0, end: int | None = None) -> Reference:
    """A non-cyclic reference from a loaded clip (hvc.mocap.clips.ReferenceClip)."""
    sl = slice(start, end)
    joints = np.asarray(clip.joints)[sl]
    return Reference(
        clip_id=clip.clip_id, dt=float(clip.dt), cyclic=False, joints=joints,
        joints_velocity=np.asarray(clip.joints_velocity)[sl], position=np.asarray(clip.position)[sl],
        quaternion=np.asarray(clip.quaternion)[sl], velocity=np.asarray(clip.velocity)[sl],
        angular_velocity=np.asarray(clip.angular_velocity)[sl],
        end_effectors=np.asarray(clip.end_effectors)[sl].reshape(len(joints), -1, 3),
        phase=_linear_phase(len(joints)))


def find_cycle(joints: np.ndarray, min_len: int, max_len: int, margin: int) -> tuple[int, int]:
    """(start, length) of the most periodic window: the pose after `length` steps is
    closest to the pose at `start` (mean absolute joint-angle difference)."""
    best, best_err = None, np.inf
    for length in range(min_len, max_len + 1):
        for start in range(margin, len(joints) - length):
            err = float(np.mean(np.abs(joints[start + length] - joints[start])))
            if err < best_err:
                best, best_err = (start, length), err
    if best is None:
        raise ValueError(f"clip of {len(joints)} steps is too short for a cycle of {min_len}-{max_len} steps")
    return best


def loop_cycle(ref: Reference, start: int, length: int, blend: int, repeats: int) -> Reference:
    """Repeats the cycle [start, start+length) `repeats` times, blending its last `blend`
    poses into the poses one cycle earlier so the loop closes smoothly."""
    if start < blend:
        raise ValueError(f"cycle start {start} must leave {blend} blend steps before it")
    idx = np.arange(start, start + length)
    joints = ref.joints[idx].copy()
    ee = ref.end_effectors[idx].copy()
    w = np.clip((np.arange(length) - (length - blend) + 1) / (blend + 1), 0.0, 1.0)[:, None]
    earlier = idx - length  # the same gait phase, one cycle before
    ok = earlier >= 0
    joints[ok] = (1 - w[ok]) * joints[ok] + w[ok] * ref.joints[earlier[ok]]
    ee[ok] = (1 - w[ok, :, None]) * ee[ok] + w[ok, :, None] * ref.end_effectors[earlier[ok]]
    # joint velocities of the closed loop, by central finite differences around the cycle
    joints_velocity = (np.roll(joints, -1, 0) - np.roll(joints, 1, 0)) / (2 * ref.dt)
    heading = root_heading(ref.quaternion[[start, start + length]])  # the walker faces along its root's z
    yaw_drift = float(heading[1] - heading[0])
    displacement = ref.position[start + length] - ref.position[start]
    displacement[2] = 0.0
    positions, quats, vels = [], [], []
    origin = ref.position[start].copy()
    for k in range(repeats):
        rot = rot_z(k * yaw_drift)
        turn = yaw_quat(k * yaw_drift)
        local = ref.position[idx] - ref.position[start]
        positions.append(origin + local @ rot.T)
        quats.append(np.array([quat_mul(turn, q) for q in ref.quaternion[idx]]))
        vels.append(ref.velocity[idx] @ rot.T)
        origin = origin + rot @ displacement
    tile = lambda a: np.concatenate([a] * repeats)  # noqa: E731
    phase = np.tile(np.arange(length) / length, repeats)
    return Reference(clip_id=ref.clip_id, dt=ref.dt, cyclic=True, joints=tile(joints),
                     joints_velocity=tile(joints_velocity), position=np.concatenate(positions),
                     quaternion=np.concatenate(quats), velocity=np.concatenate(vels),
                     angular_velocity=tile(ref.angular_velocity[idx]), end_effectors=tile(ee), phase=phase)


def build_reference(entry: Mapping[str, Any], mocap_file: str, cycle_repeats: int = 4,
                    cycle_blend: int = 4) -> Reference:
    """The reference for one clip-set entry: its frame range, looped if it is cyclic."""
    clip = load_clip(mocap_file, entry["id"])
    start, end = int(entry.get("start") or 0), entry.get("end")
    if not entry.get("cyclic"):
        return from_clip(clip, start, None if end is None else int(end))
    whole = from_clip(clip)
    segment = whole.joints[start:end]
    # the most periodic window (0.4-1.2 s covers run and walk cycles)
    lo, hi = int(round(0.4 / whole.dt)), int(round(1.2 / whole.dt))
    s, length = find_cycle(segment, lo, min(hi, len(segment) - cycle_blend - 1), margin=cycle_blend)
    cycle = (start + s, length)
    steps = entry.get("steps")
    repeats = max(cycle_repeats, -(-int(steps) // int(cycle[1])) if steps else 0)
    looped = loop_cycle(whole, int(cycle[0]), int(cycle[1]), blend=cycle_blend, repeats=repeats)
    return looped.segment(0, int(steps)) if steps else looped
