"""Entering a reference at the body's pose: the steerable and switching controllers start (or
change) a behaviour at the reference step whose pose best matches the body's, as their
training references were cut (Sec. 2.2)."""
from __future__ import annotations

import numpy as np


def actuator_order() -> np.ndarray:
    """Proprioception lists joints in actuator order, references in mocap order."""
    from dm_control.locomotion.walkers.cmu_humanoid import _CMU_MOCAP_JOINTS

    return np.argsort(_CMU_MOCAP_JOINTS)


def best_matching_step(joints: np.ndarray, proprio: np.ndarray, actuator_order: np.ndarray) -> int:
    """The reference step whose joint angles (T, 56, mocap order) are nearest the body's
    (the joint positions that lead the proprioception)."""
    body = proprio[:joints.shape[1]]
    return int(np.argmin(np.abs(joints[:, actuator_order] - body).mean(1)))
