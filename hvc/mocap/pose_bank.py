"""Start states sampled from reference clips (the paper initialises every task from
mocap poses): joint angles and velocities, root height, and the root's orientation and
velocities with the heading removed, so a task can face the body wherever it likes."""
from __future__ import annotations

from dataclasses import dataclass
from typing import Iterable, Mapping

import numpy as np

from hvc.mocap.clips import root_heading
from hvc.mocap.reference import build_reference
from hvc.rotations import quat_mul, rot_z, yaw_quat, yaw_rotate


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
            turn = -root_heading(ref.quaternion)  # per step: face +x
            c, s = np.cos(turn), np.sin(turn)
            velocity = np.array(ref.velocity, float)  # rot_z(turn) @ v, step by step
            velocity[:, 0], velocity[:, 1] = c * ref.velocity[:, 0] - s * ref.velocity[:, 1], \
                s * ref.velocity[:, 0] + c * ref.velocity[:, 1]
            parts["joints"].append(ref.joints)
            parts["joints_velocity"].append(ref.joints_velocity)
            parts["height"].append(ref.position[:, 2])
            parts["quaternion"].append(yaw_rotate(ref.quaternion, turn))
            parts["velocity"].append(velocity)
            parts["angular_velocity"].append(ref.angular_velocity)
        return cls(**{k: np.concatenate(v).astype(float) for k, v in parts.items()})

    @classmethod
    def from_entries(cls, entries: Iterable[Mapping], mocap_file: str) -> "PoseBank":
        return cls.from_references(build_reference(e, mocap_file) for e in entries)

    def write(self, i: int, qpos: np.ndarray, qvel: np.ndarray, root_qpos: int, root_dof: int,
              joint_qpos: np.ndarray, joint_dof: np.ndarray, xy, yaw: float) -> None:
        """Writes pose i, facing `yaw` (the walker's heading) at `xy`, into qpos/qvel."""
        qpos[root_qpos:root_qpos + 2] = xy
        qpos[root_qpos + 2] = self.height[i]
        qpos[root_qpos + 3:root_qpos + 7] = quat_mul(yaw_quat(yaw), self.quaternion[i])
        qpos[joint_qpos] = self.joints[i]
        qvel[root_dof:root_dof + 3] = rot_z(yaw) @ self.velocity[i]
        qvel[root_dof + 3:root_dof + 6] = self.angular_velocity[i]
        qvel[joint_dof] = self.joints_velocity[i]
