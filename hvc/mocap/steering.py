"""Steered references for the steerable low-level policy (Sec. 2.2, Fig. 2A).

One gait cycle is repeated; during each repetition the reference heading turns at a
constant rate chosen for that cycle. The root path is re-integrated from the cycle's
per-step displacements rotated by the accumulated heading, the orientation is turned
by the same heading, the world-frame linear velocity rotated with it, and the turning
rate added to the root's angular velocity (expressed in the root frame, like the free
joint's qvel). Joint angles, joint velocities and the egocentric end effectors are
heading-invariant and repeat unchanged.

With `lean`, the root also leans into the turn by atan(speed * rate / g), the angle at
which gravity and the centripetal force sum along the body (a runner's lean; 27 degrees
at 3.4 m/s and 1.5 rad/s), ramped from the previous cycle's lean over `lean_ramp` steps,
and lowered by the cosine of the lean. Without it, the reference asks an upright body to
take a turn's sideways acceleration, which is not physical at the fast rates; the
orientation term (weight 20 of 30) then scores the lean every real turn needs as error.
"""
from __future__ import annotations

from typing import Sequence

import numpy as np

from hvc.mocap.clips import root_heading
from hvc.mocap.reference import Reference
from hvc.rotations import quat_mul, quat_to_mat, rot_z, yaw_quat, yaw_rotate

GRAVITY = 9.81


def axis_angle_quat(axis: np.ndarray, angle: float) -> np.ndarray:
    axis = np.asarray(axis, np.float64) / np.linalg.norm(axis)
    return np.concatenate([[np.cos(angle / 2)], np.sin(angle / 2) * axis])


def lean_angle(speed: float, rate: float) -> float:
    """Roll (rad) about the direction of travel, positive = top to the left: a left turn
    (rate > 0) leans left."""
    return float(np.arctan(speed * rate / GRAVITY))


def steer_cycle(cycle: Reference, rates: Sequence[float], lean: bool = False,
                lean_ramp: int = 6) -> tuple[Reference, np.ndarray]:
    """The cycle (one loop of a cyclic reference, length L) repeated len(rates) times,
    turning at rates[k] rad/s during repetition k. Returns the reference and the per-step
    turning rate (the policy's extra input)."""
    length, dt = cycle.num_steps, cycle.dt
    # straighten the cycle: its own heading drift over one cycle is removed, so rate 0 runs straight
    drift_heading = root_heading(cycle.quaternion[[0, -1]])
    straighten = -float(drift_heading[1] - drift_heading[0]) * length / max(length - 1, 1) / (length * dt)
    steps = np.diff(cycle.position, axis=0, append=cycle.position[-1:] + (cycle.position[-1] - cycle.position[-2]))
    steps[:, 2] = 0.0  # heights are taken from the cycle itself
    position, quaternion, velocity, angular, per_step_rate = [], [], [], [], []
    heading, xy = 0.0, cycle.position[0, :2].copy()
    travel = np.mean(cycle.velocity[:, :2], axis=0)  # the cycle's direction of travel and speed
    forward, speed = np.array([*travel / max(np.linalg.norm(travel), 1e-9), 0.0]), float(np.linalg.norm(travel))
    roll = 0.0
    for rate in rates:
        start_roll, target_roll = roll, (lean_angle(speed, rate) if lean else 0.0)
        for i in range(length):
            turn = rot_z(heading)
            roll = start_roll + (target_roll - start_roll) * min(1.0, (i + 1) / max(lean_ramp, 1))
            # about the backward axis, so that a positive roll takes the top to the left
            q = quat_mul(yaw_quat(heading), quat_mul(axis_angle_quat(-forward, roll), cycle.quaternion[i]))
            position.append(np.array([xy[0], xy[1], cycle.position[i, 2] * np.cos(roll)]))
            quaternion.append(q)
            v = turn @ cycle.velocity[i]
            velocity.append(v)
            angular.append(cycle.angular_velocity[i] + quat_to_mat(q).T @ np.array([0.0, 0.0, rate + straighten]))
            per_step_rate.append(rate)
            xy = xy + (turn @ steps[i])[:2]
            heading += (rate + straighten) * dt
    k = len(rates)
    tile = lambda a: np.concatenate([a] * k)  # noqa: E731
    ref = Reference(clip_id=cycle.clip_id, dt=dt, cyclic=True, joints=tile(cycle.joints),
                    joints_velocity=tile(cycle.joints_velocity), position=np.asarray(position),
                    quaternion=np.asarray(quaternion), velocity=np.asarray(velocity),
                    angular_velocity=np.asarray(angular), end_effectors=tile(cycle.end_effectors),
                    phase=np.tile(np.arange(length) / length, k))
    return ref, np.asarray(per_step_rate)


def turn_from(ref: Reference, t: int, yaw: float, xy: np.ndarray) -> None:
    """Turns the reference from step t on by `yaw` about the world z axis, in place, its root
    path pivoting about step t's position, which moves to `xy`: the rest of the reference then
    starts from a new heading and place. Root-frame features (angular velocity, joints, end
    effectors) are unchanged by a turn about the vertical."""
    turn = rot_z(yaw)
    ref.quaternion[t:] = yaw_rotate(ref.quaternion[t:], yaw)
    ref.velocity[t:] = ref.velocity[t:] @ turn.T
    offset = ref.position[t:, :2] - ref.position[t, :2]
    ref.position[t:, :2] = np.asarray(xy)[:2] + offset @ turn[:2, :2].T
