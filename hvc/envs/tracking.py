"""Time-indexed single-clip tracking (Sec. 2.1) on the fast env path.

Episodes start at a random step of the reference with its pose and velocities; the
policy sees proprioception plus the normalised time in the clip (a sawtooth phase for
looped gait cycles); the reward is the paper's tracking reward against the reference
at the new time; the episode fails when any body part other than the hands and feet
touches the ground (and, with `termination_error`, when the pose strays from the
reference; with `heading_termination`, when the heading does), and ends at the clip's end.
With `switch_states` set (hvc.lowlevel.switch_starts), a share `switch_probability` of the
episodes starts instead from a state other skills' fragments left the body in, placed at the
reference's place and heading: what a fragment of this clip meets after a cold switch; with
`next_start` set (a cut-in), the next episode starts from that one state so.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Mapping

import numpy as np
from dm_control import mjcf

from hvc.envs.task_logic import TaskLogic, ContactTermination
from hvc.envs.tracking_reward import TrackingFeatures, TrackingReward
from hvc.mocap.clips import root_heading
from hvc.mocap.reference import Reference, build_reference
from hvc.mocap.steering import turn_from
from hvc.rotations import quat_conj, quat_mul, quat_to_mat, rot_z, yaw_rotate


def reference_features(ref: Reference, t: int) -> TrackingFeatures:
    """What the reward compares, for the reference at step t."""
    return TrackingFeatures(joints=ref.joints[t], joints_velocity=ref.joints_velocity[t],
                            quaternion=ref.quaternion[t], end_effectors=ref.end_effectors[t],
                            velocity=ref.velocity[t], gyro=ref.angular_velocity[t])


# Bodies allowed to touch the ground: feet and hands (the paper's termination rule).
ALLOWED_CONTACT_BODIES = ("lfoot", "ltoes", "rfoot", "rtoes", "lhand", "lfingers", "lthumb",
                          "rhand", "rfingers", "rthumb")


def heading_frame_vectors(quaternion: np.ndarray, root_vectors: np.ndarray) -> np.ndarray:
    """Root-frame vectors (n, 3) re-expressed in the root's heading frame (world axes turned
    by the root's heading): unchanged by where the body is and which way it faces, which an
    egocentric policy cannot see, but changed by any tilt, which it can (its gravity sensor)."""
    world = np.reshape(root_vectors, (-1, 3)) @ quat_to_mat(quaternion).T
    heading = float(root_heading(np.asarray(quaternion)[None])[0])
    return world @ rot_z(heading)


def pose_error(body: TrackingFeatures, ref: TrackingFeatures) -> float:
    """How far the pose has strayed from the reference: the mean of the mean absolute joint
    error (rad) and the mean absolute error of the end effectors (m) in the heading frame.
    Like dm_control's tracking termination error (0.5 joints + 0.5 bodies) but blind to the
    global position and heading, which the egocentric policy cannot observe."""
    joints = float(np.mean(np.abs(body.joints - ref.joints)))
    ee = np.abs(heading_frame_vectors(body.quaternion, body.end_effectors)
                - heading_frame_vectors(ref.quaternion, ref.end_effectors))
    return 0.5 * joints + 0.5 * float(np.mean(ee))


def heading_error(body_quaternion: np.ndarray, ref_quaternion: np.ndarray) -> float:
    """Body heading minus the reference's (rad, wrapped to [-pi, pi))."""
    body, ref = (float(root_heading(np.asarray(q)[None])[0]) for q in (body_quaternion, ref_quaternion))
    return (body - ref + np.pi) % (2 * np.pi) - np.pi


@dataclass
class SwitchStates:
    """Whole body states (the walker's qpos, qvel, act) with the root at the origin facing +x
    (heading removed, root velocity in that frame), so that one can be placed anywhere."""

    qpos: np.ndarray  # (N, nq)
    qvel: np.ndarray  # (N, nv)
    act: np.ndarray   # (N, na)

    def __len__(self) -> int:
        return len(self.qpos)

    def __getitem__(self, i: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        return self.qpos[i], self.qvel[i], self.act[i]


class TrackingLogic(TaskLogic):
    observation_size = 1
    reference_per_episode = False  # True where each reset draws a new reference

    def __init__(self, cfg: Mapping[str, Any], env, reference: Reference | None = None):
        task, physics = env.task, env.physics
        walker = task._walker
        model = physics.model.ptr
        allowed = {g for name in ALLOWED_CONTACT_BODIES
                   for g in (walker.mjcf_model.find("body", name).find_all("geom", immediate_children_only=True))}
        body_geoms = [g for g in walker.mjcf_model.find_all("geom") if g not in allowed]
        self.contact_failure = ContactTermination(model, physics.bind(body_geoms).element_id,
                                                   task._ground_geomids)
        free = mjcf.get_frame_freejoint(walker.mjcf_model)
        self.root_qpos = int(model.jnt_qposadr[physics.bind(free).element_id])
        self.root_dof = int(model.jnt_dofadr[physics.bind(free).element_id])
        joint_ids = physics.bind(list(walker.mocap_joints)).element_id
        self.joint_qpos = np.asarray(model.jnt_qposadr[joint_ids], np.intp)
        self.joint_dof = np.asarray(model.jnt_dofadr[joint_ids], np.intp)
        self.root = int(physics.bind(walker.root_body).element_id)
        self.end_effectors = np.asarray(physics.bind(list(walker.end_effectors)).element_id, np.intp)
        self.actuators = np.asarray(physics.bind(list(walker.actuators)).element_id, np.intp)
        # position-control mapping (CMUHumanoidPositionControlled.cmu_pose_to_actuation)
        self.actuator_order = np.asarray(walker.actuator_order)
        self.act_offset, self.act_scale = np.asarray(walker._offset), np.asarray(walker._scale)
        self.has_act = model.na > 0  # V2020 actuators filter their input
        if reference is None:
            reference = cfg.get("reference")  # e.g. from an expert library: no mocap file needed
        self.reference = reference if reference is not None else build_reference(
            cfg["clip"], cfg["mocap_file"], int(cfg.get("cycle_repeats", 4)), int(cfg.get("cycle_blend", 4)))
        self.reward_fn = TrackingReward(cfg["reward"])
        self.random_start = bool(cfg.get("random_start", True))
        self.start_window: int | None = None  # random starts among the first this many steps (None: all)
        threshold = cfg.get("termination_error")  # checked with the config (hvc.config.validate)
        self.termination_error = None if threshold is None else float(threshold)
        heading = cfg.get("heading_termination")
        self.heading_termination = None if heading is None else float(heading)
        self.t = 0
        self.failure = False
        self.last_terms: dict[str, float] = {}
        # steps at which the rest of the reference is turned and moved to where the body is
        # (set per episode, with `reanchor`, by references made of parts: steered cycles,
        # behaviour switches)
        self.anchors: frozenset[int] = frozenset()
        self.reanchor = bool(cfg.get("reanchor", True))
        self.switch_states: SwitchStates | None = None  # set by the expert trainer (switch starts)
        self.switch_probability = 0.0
        self.next_start: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None  # set by a cut-in, one reset

    # -- pose bookkeeping ------------------------------------------------------------
    def pose_to_actuation(self, joints: np.ndarray) -> np.ndarray:
        """The position-control action that drives the joints to `joints` (mocap order)."""
        return (2 * joints[self.actuator_order] - self.act_offset) / self.act_scale

    def set_reference_state(self, data, t: int, reference: Reference | None = None) -> None:
        """The body at step t of this task's reference, or of another one."""
        ref = self.reference if reference is None else reference
        data.qpos[self.root_qpos:self.root_qpos + 3] = ref.position[t]
        data.qpos[self.root_qpos + 3:self.root_qpos + 7] = ref.quaternion[t]
        data.qpos[self.joint_qpos] = ref.joints[t]
        data.qvel[self.root_dof:self.root_dof + 3] = ref.velocity[t]
        data.qvel[self.root_dof + 3:self.root_dof + 6] = ref.angular_velocity[t]
        data.qvel[self.joint_dof] = ref.joints_velocity[t]
        if self.has_act:
            data.act[:] = np.clip(self.pose_to_actuation(ref.joints[t]), -1, 1)

    def body_features(self, data) -> TrackingFeatures:
        xmat = data.xmat[self.root].reshape(3, 3)
        return TrackingFeatures(
            joints=data.qpos[self.joint_qpos], joints_velocity=data.qvel[self.joint_dof],
            quaternion=data.qpos[self.root_qpos + 3:self.root_qpos + 7],
            end_effectors=(data.xpos[self.end_effectors] - data.xpos[self.root]) @ xmat,
            velocity=data.qvel[self.root_dof:self.root_dof + 3],
            gyro=data.qvel[self.root_dof + 3:self.root_dof + 6])

    def reference_features(self, t: int) -> TrackingFeatures:
        return reference_features(self.reference, t)

    # -- TaskLogic -------------------------------------------------------------------
    def reset(self, model, data, rng):
        last = self.reference.num_steps - 1
        if self.start_window is not None:
            last = min(last, self.start_window)
        self.t = int(rng.integers(0, last)) if self.random_start else 0
        self.start = self.t
        if self.next_start is not None:
            self.place_state(data, self.next_start, self.t)
        elif self.switch_states is not None and rng.random() < self.switch_probability:
            self.place_state(data, self.switch_states[int(rng.integers(len(self.switch_states)))], self.t)
        else:
            self.set_reference_state(data, self.t)
        self.failure = False

    def heading_free_state(self, data) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(qpos, qvel, act) of the body now, moved to the origin and turned to face +x."""
        qpos, qvel = data.qpos.copy(), data.qvel.copy()
        root, dof = self.root_qpos, self.root_dof
        heading = float(root_heading(qpos[None, root + 3:root + 7])[0])
        qpos[root:root + 2] = 0.0
        qpos[root + 3:root + 7] = yaw_rotate(qpos[None, root + 3:root + 7], -heading)[0]
        qvel[dof:dof + 3] = rot_z(-heading) @ qvel[dof:dof + 3]  # the free joint's angular velocity is local
        return qpos, qvel, data.act.copy()

    def place_state(self, data, state: tuple[np.ndarray, np.ndarray, np.ndarray], t: int) -> None:
        """A heading-free (qpos, qvel, act) at the reference's place and heading at step t (its
        own height)."""
        (qpos, qvel, act), root, dof = state, self.root_qpos, self.root_dof
        heading = float(root_heading(self.reference.quaternion[t:t + 1])[0])
        data.qpos[:], data.qvel[:] = qpos, qvel
        data.qpos[root:root + 2] = self.reference.position[t][:2]
        data.qpos[root + 3:root + 7] = yaw_rotate(qpos[None, root + 3:root + 7], heading)[0]
        data.qvel[dof:dof + 3] = rot_z(heading) @ qvel[dof:dof + 3]
        if self.has_act:
            data.act[:] = act

    def anchor(self, data, t: int) -> None:
        """Turns and moves the reference from step t on so that it starts from the body's
        heading and place: what follows is scored on the motion made from here, not on the
        heading lag gathered before, which the egocentric policy cannot see and which, past
        a fraction of a turn, holds the orientation term (weight 20 of 30) and so the reward
        near zero whatever the policy does."""
        body = data.qpos[self.root_qpos + 3:self.root_qpos + 7]
        yaw = heading_error(body, self.reference.quaternion[t])
        turn_from(self.reference, t, yaw, data.qpos[self.root_qpos:self.root_qpos + 2])

    def after_step(self, model, data, rng):
        if self.t + 1 in self.anchors:
            self.anchor(data, self.t + 1)
        self.t += 1
        self.body_now, self.reference_now = self.body_features(data), self.reference_features(self.t)
        self.failure = self.contact_failure(data) or (
            self.termination_error is not None
            and pose_error(self.body_now, self.reference_now) > self.termination_error) or (
            self.heading_termination is not None
            and abs(heading_error(self.body_now.quaternion, self.reference_now.quaternion)) > self.heading_termination)

    def reward(self, model, data):
        """Against the features `after_step` read for this step (the env calls it right after)."""
        reward, self.last_terms = self.reward_fn(self.body_now, self.reference_now)
        return reward

    def terminated(self):
        return self.failure or self.t >= self.reference.num_steps - 1

    def observation(self, model, data):
        return np.array([self.reference.phase[self.t]], np.float32)

    critic_feature_size = 7

    def critic_features(self, data) -> np.ndarray:
        """What the reward scores but the egocentric policy cannot see, for the critic only:
        the rotation from the body's root to the reference's (q_body^-1 q_ref, w >= 0; the
        orientation term's state, heading included) and the reference's root velocity in the
        body's root frame. Without them Q must guess from proprioception how far the heading
        has drifted, which is most of what a steered cycle is scored on."""
        body = data.qpos[self.root_qpos + 3:self.root_qpos + 7]
        relative = quat_mul(quat_conj(body), self.reference.quaternion[self.t])
        relative = relative if relative[0] >= 0 else -relative
        velocity = quat_to_mat(body).T @ self.reference.velocity[self.t]
        return np.concatenate([relative, velocity]).astype(np.float32)

    @property
    def completion(self) -> float:
        """Fraction of the clip remaining at the episode's start that was tracked."""
        remaining = self.reference.num_steps - 1 - self.start
        return (self.t - self.start) / remaining if remaining > 0 else 1.0
