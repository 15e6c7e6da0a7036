"""The paper's tracking reward (Sec. 2.1, Eqs. 1-2), exactly.

E_qpos, E_qvel: mean absolute joint angle / velocity errors; E_ori: norm of the
quaternion log of q * q_ref^-1; E_ee: mean Euclidean error of the egocentric
root-to-end-effector vectors; E_vel: vel_scale x mean absolute global velocity error;
E_gyro: gyro_scale x Euclidean root angular velocity error.
r = exp(-beta * sum_i w_i E_i / sum_i w_i), so perfect tracking gives 1.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Mapping

import numpy as np

from hvc.rotations import quat_conj, quat_mul

TERMS = ("qpos", "qvel", "ori", "ee", "vel", "gyro")


@dataclass(frozen=True)
class TrackingFeatures:
    """The quantities the reward compares, for the body or the reference at one step."""

    joints: np.ndarray            # (56,) joint angles, mocap joint order
    joints_velocity: np.ndarray   # (56,)
    quaternion: np.ndarray        # (4,) root orientation, w first, world frame
    end_effectors: np.ndarray     # (n_ee, 3) egocentric root-to-end-effector vectors
    velocity: np.ndarray          # (3,) global translational velocity of the root
    gyro: np.ndarray              # (3,) root angular velocity, root frame


def quat_log_norm(q: np.ndarray) -> float:
    """||log q|| for a unit quaternion: half the rotation angle, taking the shorter of
    q and -q (they are the same rotation), so it lies in [0, pi/2]. arctan2 of the vector
    part's norm against |w| is scale-free, so a product drifted off unit norm needs no
    renormalising."""
    return float(np.arctan2(np.linalg.norm(q[1:]), abs(q[0])))


def energies(body: TrackingFeatures, ref: TrackingFeatures, vel_scale: float, gyro_scale: float) -> dict[str, float]:
    """The six error terms; end effectors may come as (n, 3) or flattened (3n,)."""
    return {
        "qpos": float(np.mean(np.abs(body.joints - ref.joints))),
        "qvel": float(np.mean(np.abs(body.joints_velocity - ref.joints_velocity))),
        "ori": quat_log_norm(quat_mul(body.quaternion, quat_conj(ref.quaternion))),
        "ee": float(np.mean(np.linalg.norm(np.reshape(body.end_effectors, (-1, 3))
                                           - np.reshape(ref.end_effectors, (-1, 3)), axis=1))),
        "vel": vel_scale * float(np.mean(np.abs(body.velocity - ref.velocity))),
        "gyro": gyro_scale * float(np.linalg.norm(body.gyro - ref.gyro)),
    }


class TrackingReward:
    """r = exp(-beta * E_total / w_total) with the weights of a `conf/reward/` file."""

    def __init__(self, cfg: Mapping[str, float]):
        self.weights = {t: float(cfg[f"w_{t}"]) for t in TERMS}
        self.w_total = sum(self.weights.values())
        if self.w_total <= 0:
            raise ValueError(f"reward weights must sum to a positive number, got {self.weights}")
        self.beta = float(cfg["beta"])
        self.vel_scale = float(cfg["vel_scale"])
        self.gyro_scale = float(cfg["gyro_scale"])

    def __call__(self, body: TrackingFeatures, ref: TrackingFeatures) -> tuple[float, dict[str, float]]:
        terms = energies(body, ref, self.vel_scale, self.gyro_scale)
        total = sum(self.weights[t] * terms[t] for t in TERMS)
        return float(np.exp(-self.beta * total / self.w_total)), terms
