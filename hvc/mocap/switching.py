"""Reference sequences for the switching policy (Sec. 2.2, Fig. 2B), cut automatically.

The paper cut its clips by hand to begin and end at similar points of the gait cycle.
Here `best_cut` finds, for a transition a -> b, the pair of steps whose poses match best
(joint angles, root height and heading-free orientation), `splice` joins the two
references there (b moved and turned so its root continues from a's, crossfaded
with a's continuation long enough that the root speed ramps at a human's
acceleration), and `markov_reference` chains behaviours with a
Markov process over a graph of allowed transitions. The per-step behaviour index is the
policy's 1-of-k input.
"""
from __future__ import annotations

from dataclasses import replace
from typing import Mapping, Sequence

import numpy as np

from hvc.mocap.clips import root_heading
from hvc.mocap.reference import Reference
from hvc.rotations import rot_z, slerp, yaw_rotate

#: m/s^2, about a sprinter's start: the fastest root speed change a cut may ask for
MAX_ACCEL = 4.0


def _heading_free(ref: Reference) -> np.ndarray:
    return yaw_rotate(ref.quaternion, -root_heading(ref.quaternion))


def best_cut(a: Reference, b: Reference, min_a: int = 1, max_b: int | None = None) -> tuple[int, int, float]:
    """(i, j, cost): leave a after step i (i >= min_a), enter b at step j (j < max_b)."""
    max_b = b.num_steps - 1 if max_b is None else max_b
    a, b = a.segment(min_a), b.segment(0, max_b)  # only the admissible steps
    fa, fb = _heading_free(a), _heading_free(b)
    joint = np.abs(a.joints[:, None, :] - b.joints[None, :, :]).mean(-1)
    height = np.abs(a.position[:, None, 2] - b.position[None, :, 2])
    tilt = 1.0 - np.abs(fa @ fb.T)
    cost = joint + height + tilt
    i, j = np.unravel_index(np.argmin(cost), cost.shape)
    return int(i) + min_a, int(j), float(cost[i, j])


def splice(a: Reference, i: int, b: Reference, j: int, blend: int = 4, max_accel: float = MAX_ACCEL) -> Reference:
    return _splice(a, i, b, j, blend, max_accel)[0]


def _splice(a: Reference, i: int, b: Reference, j: int, blend: int, max_accel: float) -> tuple[Reference, int]:
    """(the joined reference, the crossfade's length n): a[:i+1] then b[j+1:], b moved so its root continues a's path with a's heading at the cut.

    The first n steps of b are crossfaded with a's continuation (a's last step held if
    it ends there): joints, height, orientation and end effectors blend, the horizontal
    root velocity ramps from a's to b's and the path is integrated from it. n is `blend`,
    or longer when the speeds differ: the ramp never accelerates the root by more than
    `max_accel` m/s^2. Without it, stand -> run asked for 0 -> 3.4 m/s in one 0.03 s
    step, which no body can track (the paper's animators smoothed such cuts by hand).
    """
    ha, hb = root_heading(a.quaternion[[i]])[0], root_heading(b.quaternion[[j]])[0]
    turn = ha - hb
    rot = rot_z(turn)
    tail = replace(b.segment(j + 1), phase=b.phase[j + 1:])  # keep b's own time input
    position = (tail.position - b.position[j]) @ rot.T + a.position[i]
    position[:, 2] = tail.position[:, 2]
    quaternion = yaw_rotate(tail.quaternion, turn)
    velocity = tail.velocity @ rot.T
    joints, angular, ee = tail.joints.copy(), tail.angular_velocity.copy(), tail.end_effectors.copy()

    n = min(len(joints), ramp_steps(a.velocity[i], velocity[0], a.dt, blend, max_accel))
    if n > 0:
        cont = np.minimum(np.arange(i + 1, i + 1 + n), a.num_steps - 1)  # a carried on
        w = np.arange(1, n + 1) / (n + 1)
        joints[:n] = _crossfade(a.joints[cont], joints[:n], w)
        angular[:n] = _crossfade(a.angular_velocity[cont], angular[:n], w)
        ee[:n] = _crossfade(a.end_effectors[cont], ee[:n], w)
        quaternion[:n] = slerp(a.quaternion[cont], quaternion[:n], w)
        velocity[:n] = _crossfade(a.velocity[cont], velocity[:n], w)
        # trapezoidal integration: the stored velocities are central differences
        steps = (np.vstack([a.velocity[i, :2], velocity[:n - 1, :2]]) + velocity[:n, :2]) / 2
        path = a.position[i, :2] + np.cumsum(steps, axis=0) * a.dt
        position[n:, :2] += path[-1] - position[n - 1, :2]  # b goes on from where the ramp ended
        position[:n, :2] = path
        position[:n, 2] = _crossfade(a.position[cont, 2], position[:n, 2], w)
    cat = lambda x, y: np.concatenate([x, y])  # noqa: E731
    head = _keep_phase(a, i + 1)
    all_joints = cat(head.joints, joints)
    joints_velocity = cat(head.joints_velocity, tail.joints_velocity)
    window = slice(i, i + n + 2)  # blended joints (and their neighbours) move at the blend's rate
    joints_velocity[window] = np.gradient(all_joints, a.dt, axis=0)[window]
    return Reference(clip_id=f"{a.clip_id}+{b.clip_id}", dt=a.dt, cyclic=False,
                     joints=all_joints, joints_velocity=joints_velocity,
                     position=cat(head.position, position), quaternion=cat(head.quaternion, quaternion),
                     velocity=cat(head.velocity, velocity),
                     angular_velocity=cat(head.angular_velocity, angular),
                     end_effectors=cat(head.end_effectors, ee),
                     phase=cat(head.phase, tail.phase)), n  # each behaviour keeps its own time input


def ramp_steps(v_from: np.ndarray, v_to: np.ndarray, dt: float, blend: int, max_accel: float) -> int:
    """Steps of a crossfade from root velocity v_from to v_to: `blend`, or as many as keep
    the horizontal acceleration within `max_accel`."""
    if not max_accel > 0:
        raise ValueError(f"max_accel must be a positive acceleration in m/s^2, got {max_accel}")
    change = float(np.linalg.norm(np.asarray(v_to)[:2] - np.asarray(v_from)[:2]))
    return max(int(blend), int(np.ceil(change / (max_accel * dt))))


def _crossfade(x: np.ndarray, y: np.ndarray, w: np.ndarray) -> np.ndarray:
    """(1 - w) x + w y row by row, w of shape (n,)."""
    w = w.reshape(-1, *[1] * (x.ndim - 1))
    return (1 - w) * x + w * y


def _keep_phase(ref: Reference, end: int) -> Reference:
    """The first `end` steps with their phases as they are (segment() renumbers non-cyclic ones)."""
    return replace(ref.segment(0, end), phase=ref.phase[:end])


def markov_reference(references: Sequence[Reference], graph: Mapping[int, Sequence[int]], steps: int,
                     rng: np.random.Generator, start: int | None = None, blend: int = 4,
                     min_stay: int = 10, max_accel: float = MAX_ACCEL) -> tuple[Reference, np.ndarray]:
    """Chains behaviours by a Markov walk on `graph` (behaviour -> allowed next ones) until
    `steps` steps; each transition cut by `best_cut` at least `min_stay` steps after the
    current behaviour's crossfade ended. A behaviour with no next ones ends the walk: with
    none anywhere, each walk is one behaviour as its clip has it, which trains one network
    as every behaviour's expert. Returns the reference and the per-step behaviour index."""
    current = int(rng.integers(len(references))) if start is None else int(start)
    ref = references[current]
    labels = np.full(ref.num_steps, current)
    entered = 0
    while ref.num_steps < steps and graph.get(current):
        nxt = int(rng.choice(list(graph[current])))
        b = references[nxt]
        i, j, _ = best_cut(ref, b, min_a=min(entered + min_stay, ref.num_steps - 1),
                           max_b=max(1, b.num_steps - 1 - min_stay))  # b then lasts min_stay steps at least
        spliced, ramp = _splice(ref, i, b, j, blend, max_accel)
        labels = np.concatenate([labels[:i + 1], np.full(spliced.num_steps - i - 1, nxt)])
        ref, current, entered = spliced, nxt, i + 1 + ramp  # the next cut comes after the ramp
    return ref.segment(0, steps), labels[:steps]
