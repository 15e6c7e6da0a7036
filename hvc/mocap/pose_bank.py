"""Start states sampled from reference clips (the paper initialises every task from
mocap poses): joint angles and velocities, root height, and the root's orientation and
velocities with the heading removed, so a task can face the body wherever it likes."""
from __future__ import annotations

from dataclasses import dataclass
from typing import Iterable, Mapping

import numpy as np

from hvc.mocap.clips import root_heading
from hvc.rotations import quat_mul, yaw_quat


def _rot_z(angle: float) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


@dataclass(frozen=True)
class PoseBank:
    joints: np.ndarray            # (N, 56) mocap joint order
    joints_velocity: np.ndarray   # (N, 56)
    height: np.ndarray            # (N,) root z
    quaternion: np.ndarray        # (N, 4) root orientation, heading removed (faces +x)
    velocity: np.ndarray          # (N, 3) root linear velocity in that heading-free frame
    angular_velocity: np.ndarray  # (N, 3) root frame (unchanged by a heading turn)

    def __len__(self) -> int:
        return len(self.height)

    @classmethod
    def from_references(cls, references: Iterable) -> "PoseBank":
        parts = {k: [] for k in cls.__dataclass_fields__}
        for ref in references:
            heading = root_heading(ref.quaternion)
            for t in range(ref.num_steps):
                turn = -heading[t]
                parts["joints"].append(ref.joints[t])
                parts["joints_velocity"].append(ref.joints_velocity[t])
                parts["height"].append(ref.position[t, 2])
                parts["quaternion"].append(quat_mul(yaw_quat(turn), ref.quaternion[t]))
                parts["velocity"].append(_rot_z(turn) @ ref.velocity[t])
                parts["angular_velocity"].append(ref.angular_velocity[t])
        return cls(**{k: np.asarray(v, float) for k, v in parts.items()})

    @classmethod
    def from_entries(cls, entries: Iterable[Mapping], mocap_file: str) -> "PoseBank":
        from hvc.lowlevel.tracking import build_reference

        return cls.from_references(build_reference(e, mocap_file) for e in entries)

    def write(self, i: int, qpos: np.ndarray, qvel: np.ndarray, root_qpos: int, root_dof: int,
              joint_qpos: np.ndarray, joint_dof: np.ndarray, xy, yaw: float) -> None:
        """Writes pose i, facing `yaw` (the walker's heading) at `xy`, into qpos/qvel."""
        qpos[root_qpos:root_qpos + 2] = xy
        qpos[root_qpos + 2] = self.height[i]
        qpos[root_qpos + 3:root_qpos + 7] = quat_mul(yaw_quat(yaw), self.quaternion[i])
        qpos[joint_qpos] = self.joints[i]
        qvel[root_dof:root_dof + 3] = _rot_z(yaw) @ self.velocity[i]
        qvel[root_dof + 3:root_dof + 6] = self.angular_velocity[i]
        qvel[joint_dof] = self.joints_velocity[i]
