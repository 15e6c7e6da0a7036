"""Quaternion helpers (w first, as MuJoCo), shared by resets, references and the reward."""
from __future__ import annotations

import numpy as np


def quat_mul(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    w1, x1, y1, z1 = a
    w2, x2, y2, z2 = b
    return np.array([w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2,
                     w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
                     w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2,
                     w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2])


def quat_conj(q: np.ndarray) -> np.ndarray:
    return np.array([q[0], -q[1], -q[2], -q[3]])


def yaw_quat(yaw: float) -> np.ndarray:
    """Rotation by `yaw` radians about the world z axis."""
    return np.array([np.cos(yaw / 2), 0.0, 0.0, np.sin(yaw / 2)])


def quat_to_mat(q: np.ndarray) -> np.ndarray:
    """3x3 rotation matrix of a unit quaternion: maps body-frame vectors to the world frame."""
    w, x, y, z = q
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                     [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                     [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])


def rot_z(angle: float) -> np.ndarray:
    """3x3 rotation by `angle` radians about the world z axis."""
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def yaw_rotate(quaternions: np.ndarray, yaw) -> np.ndarray:
    """yaw_quat(yaw) * q for each row of (N, 4) quaternions; `yaw` a scalar or (N,)."""
    c, s = np.cos(np.asarray(yaw) / 2), np.sin(np.asarray(yaw) / 2)
    w, x, y, z = np.asarray(quaternions, np.float64).T
    return np.stack([c * w - s * z, c * x - s * y, c * y + s * x, c * z + s * w], axis=-1)


def slerp(q0: np.ndarray, q1: np.ndarray, u: np.ndarray) -> np.ndarray:
    """Row-wise spherical interpolation of unit quaternions (N, 4) at fractions u (N,), shortest path."""
    q1 = np.where((np.sum(q0 * q1, axis=1) < 0)[:, None], -q1, q1)
    dot = np.clip(np.sum(q0 * q1, axis=1), -1.0, 1.0)
    theta = np.arccos(dot)
    small = theta < 1e-8
    sin = np.where(small, 1.0, np.sin(theta))
    w0 = np.where(small, 1.0 - u, np.sin((1.0 - u) * theta) / sin)
    w1 = np.where(small, u, np.sin(u * theta) / sin)
    q = w0[:, None] * q0 + w1[:, None] * q1
    return q / np.linalg.norm(q, axis=1, keepdims=True)
