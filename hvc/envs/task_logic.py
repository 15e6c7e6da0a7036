"""Rewards, terminations and resets of the paper's tasks on raw MjData.

Each class mirrors one dm_control composer task (named in its docstring) step for
step, but reads index arrays resolved once per compiled model and replaces the
per-contact Python loops with one vectorised test on the contact arrays. Resets write
target and spawn positions into the model instead of recompiling the MJCF.
Where dm_control's behaviour is a quirk we deviate on purpose, the docstring says so.
"""
from __future__ import annotations

import numpy as np
from absl import logging as absl_logging
from dm_control import mjcf

from hvc.rotations import quat_mul, yaw_quat


class WalkerPlacement:
    """The walker's upright pose and how to shift it, as dm_control's
    UprightInitializer + Entity.shift_pose do, without the binding overhead."""

    def __init__(self, walker, physics):
        saved = physics.data.qpos.copy(), physics.data.qvel.copy()
        verbosity = absl_logging.get_verbosity()
        absl_logging.set_verbosity(absl_logging.ERROR)  # the ball "cannot set velocity": expected, not news
        try:
            walker.reinitialize_pose(physics, np.random.RandomState(0))  # deterministic upright pose
        finally:
            absl_logging.set_verbosity(verbosity)
        self.qpos_upright = physics.data.qpos.copy()
        physics.data.qpos[:], physics.data.qvel[:] = saved  # leave the caller's state alone
        physics.forward()
        free = mjcf.get_frame_freejoint(walker.mjcf_model)
        self.pose_bank = None
        if free is not None:
            self.free_adr = int(physics.model.jnt_qposadr[physics.bind(free).element_id])
            self.free_dof = int(physics.model.jnt_dofadr[physics.bind(free).element_id])
            self.slide_adr = None
            if hasattr(walker, "mocap_joints"):  # CMU humanoid: mocap poses can be written
                ids = physics.bind(list(walker.mocap_joints)).element_id
                self.joint_qpos = np.asarray(physics.model.jnt_qposadr[ids], np.intp)
                self.joint_dof = np.asarray(physics.model.jnt_dofadr[ids], np.intp)
        else:  # rolling ball: slide joints root_x, root_y on the attachment frame
            self.free_adr = None
            joints = list(walker._root_joints[:2])  # made by create_root_joints on the attachment frame
            self.slide_adr = np.asarray(physics.model.jnt_qposadr[physics.bind(joints).element_id])

    def start(self, data, xy, yaw: float | None, rng: np.random.Generator) -> None:
        """An episode's start state: a pose of the bank when one is set (the paper starts
        from mocap poses), else dm_control's upright pose; `yaw` None keeps the default heading."""
        if self.pose_bank is None:
            self.place(data.qpos, xy, yaw)
            return
        i = int(rng.integers(len(self.pose_bank)))
        self.pose_bank.write(i, data.qpos, data.qvel, self.free_adr, self.free_dof, self.joint_qpos,
                             self.joint_dof, xy, 0.0 if yaw is None else yaw)

    def place(self, qpos: np.ndarray, xy, yaw: float | None) -> None:
        """Writes the upright pose shifted to `xy` and turned by `yaw` into `qpos`."""
        qpos[:] = self.qpos_upright
        if self.free_adr is not None:
            qpos[self.free_adr:self.free_adr + 2] += xy
            if yaw is not None:  # velocities are zero, so rotating them is a no-op
                quat = qpos[self.free_adr + 3:self.free_adr + 7]
                qpos[self.free_adr + 3:self.free_adr + 7] = quat_mul(yaw_quat(yaw), quat)
        else:
            qpos[self.slide_adr] += xy


class ContactTermination:
    """Failure when a walker geom other than the feet touches the ground (the paper's rule)."""

    def __init__(self, model, nonfoot_ids, ground_ids):
        self.nonfoot = np.zeros(model.ngeom, bool)
        self.nonfoot[list(nonfoot_ids)] = True
        self.ground = np.zeros(model.ngeom, bool)
        self.ground[list(ground_ids)] = True

    def __call__(self, data) -> bool:
        if data.ncon == 0:
            return False
        g = data.contact.geom
        a, b = g[:, 0], g[:, 1]
        return bool(np.any((self.nonfoot[a] & self.ground[b]) | (self.ground[a] & self.nonfoot[b])))


class TaskLogic:
    """Interface of one task on one compiled model; `failure` is set by after_step."""

    needs_substep_hook = False
    needs_subtree_vel = False
    observation_size = 0

    def reset(self, model, data, rng: np.random.Generator) -> None: ...
    def after_reset(self, model, data) -> None: ...
    def after_substep(self, model, data) -> None: ...
    def after_step(self, model, data, rng: np.random.Generator) -> None: ...
    def reward(self, model, data) -> float: ...
    def terminated(self) -> bool: ...

    def observation(self, model, data) -> np.ndarray:
        return np.zeros(0, np.float32)


class GoToTargetLogic(TaskLogic):
    """dm_control `tasks.go_to_target.GoToTarget`: reward 1 while within
    `distance_tolerance` of the target (xy), target given egocentrically."""

    observation_size = 3

    def __init__(self, cfg, env):
        task, physics = env.task, env.physics
        self.placement = WalkerPlacement(task._walker, physics)
        self.contact_failure = ContactTermination(physics.model.ptr, task._walker_nonfoot_geomids,
                                                   task._ground_geomids)
        self.root = int(physics.bind(task._walker.root_body).element_id)
        self.site = int(physics.bind(task._target).element_id)
        self.half_size = np.asarray(cfg["arena_size"], float) / 2
        self.tolerance = float(cfg["distance_tolerance"])
        self.moving = bool(cfg["moving_target"])
        self.steps_before_moving = int(cfg["steps_before_moving_target"])
        self.failure = False
        self.counter = 0

    def reset(self, model, data, rng):
        model.site_pos[self.site] = [*rng.uniform(-self.half_size, self.half_size), 0.0]
        self.placement.start(data, rng.uniform(-self.half_size, self.half_size), None, rng)
        self.failure = False
        self.counter = 0

    def after_step(self, model, data, rng):
        self.failure = self.contact_failure(data)
        if self.moving and self.counter >= self.steps_before_moving:
            model.site_pos[self.site] = [*rng.uniform(-self.half_size, self.half_size), 0.0]
            self.counter = 0

    def reward(self, model, data):
        if np.linalg.norm(model.site_pos[self.site, :2] - data.xpos[self.root, :2]) < self.tolerance:
            self.counter += self.moving
            return 1.0
        return 0.0

    def terminated(self):
        return self.failure

    def observation(self, model, data):
        xmat = data.xmat[self.root].reshape(3, 3)
        return ((model.site_pos[self.site] - data.xpos[self.root]) @ xmat).astype(np.float32)


class CorridorLogic(TaskLogic):
    """dm_control `tasks.corridors.RunThroughCorridor` (walls and gaps): reward
    max(0, 1 - |v_x - v*| / v*) on the root subtree's forward velocity; failure on a
    non-foot ground contact or an end effector below `terminate_at_height`."""

    needs_subtree_vel = True

    def __init__(self, cfg, env):
        task, physics = env.task, env.physics
        walker = task._walker
        self.placement = WalkerPlacement(walker, physics)
        self.contact_failure = ContactTermination(physics.model.ptr, task._walker_nonfoot_geomids,
                                                   task._ground_geomids)
        self.root = int(physics.bind(walker.root_body).element_id)
        self.end_effectors = np.atleast_1d(physics.bind(list(walker.end_effectors)).element_id).astype(np.intp)
        self.spawn_xy = np.asarray(cfg["spawn_position"], float)[:2]
        self.velocity = float(cfg["target_velocity"])
        self.min_height = float(cfg["terminate_at_height"])
        self.failure = False

    def reset(self, model, data, rng):
        self.placement.start(data, self.spawn_xy, None, rng)
        self.failure = False

    def after_step(self, model, data, rng):
        self.failure = self.contact_failure(data) or bool(
            np.any(data.xpos[self.end_effectors, 2] < self.min_height))

    def reward(self, model, data):
        error = abs(data.subtree_linvel[self.root, 0] - self.velocity) / self.velocity
        return float(max(0.0, 1.0 - error))

    def terminated(self):
        return self.failure


class MazeLogic(TaskLogic):
    """dm_control `tasks.random_goal_maze.ManyHeterogeneousGoalsMaze` (forage and
    heterogeneous forage): a ball pays its colour's reward once, when anything touches
    it (checked after every physics substep, as the TargetSphere prop does); the
    episode ends when all balls are taken or on a non-foot ground contact.

    Deliberate differences from composer: the colour-to-reward assignment is drawn
    here each reset (composer shuffles builders, the same distribution); the failure
    step has discount 0 (composer reports 1 on that step because it reads the discount
    before deciding to terminate); the walker's aliveness test is omitted because these
    walkers' aliveness is constantly 0."""

    needs_substep_hook = True

    def __init__(self, cfg, env):
        task, physics = env.task, env.physics
        model = physics.model.ptr
        self.placement = WalkerPlacement(task._walker, physics)
        self.contact_failure = ContactTermination(model, task._walker_nonfoot_geomids,
                                                   task._ground_geomids)
        arena = task._maze_arena
        targets = [(kind, t) for kind, group in enumerate(task._active_targets) for t in group]
        self.target_type = np.array([kind for kind, _ in targets], np.intp)
        self.target_geoms = np.array([physics.bind(t.geom).element_id for _, t in targets], np.intp)
        self.target_bodies = np.array(
            [physics.bind(mjcf.get_attachment_frame(t.mjcf_model)).element_id for _, t in targets], np.intp)
        self.target_materials = np.array([physics.bind(t.material).element_id for _, t in targets], np.intp)
        self.target_slots = np.array(arena.target_positions, float)
        self.spawns = np.array(arena.spawn_positions, float)[:, :2]
        self.type_rewards = np.asarray(cfg["target_rewards"], float)
        self.random_spawn_rotation = bool(cfg["randomize_spawn_rotation"])
        self.aliveness_reward = float(cfg["aliveness_reward"])
        self.is_target = np.zeros(model.ngeom, bool)
        self.is_target[self.target_geoms] = True
        self.slot_of_geom = np.full(model.ngeom, -1, np.intp)
        self.slot_of_geom[self.target_geoms] = np.arange(len(targets))
        self.activated = np.zeros(len(targets), bool)
        self.rewarded = np.zeros(len(targets), bool)
        self.reward_of_type = self.type_rewards.copy()
        self.failure = False

    def reset(self, model, data, rng):
        model.body_pos[self.target_bodies] = self.target_slots[rng.permutation(len(self.target_slots))][
            :len(self.target_bodies)]
        model.mat_rgba[self.target_materials, 3] = 1.0
        self.reward_of_type = self.type_rewards[rng.permutation(len(self.type_rewards))]
        yaw = rng.uniform(0, 2 * np.pi) if self.random_spawn_rotation else None
        self.placement.start(data, self.spawns[rng.integers(len(self.spawns))], yaw, rng)
        self.activated[:] = False
        self.rewarded[:] = False
        self.failure = False

    def after_reset(self, model, data):
        self._update_activation(model, data)

    def _update_activation(self, model, data):
        if data.ncon == 0:
            return
        g = data.contact.geom.reshape(-1)
        touched = self.slot_of_geom[g[self.is_target[g]]]
        if touched.size:
            self.activated[touched] = True
            model.mat_rgba[self.target_materials[touched], 3] = 0.0  # taken balls vanish

    def after_substep(self, model, data):
        self._update_activation(model, data)

    def after_step(self, model, data, rng):
        self.failure = self.contact_failure(data)

    def reward(self, model, data):
        new = self.activated & ~self.rewarded
        self.rewarded |= new
        return self.aliveness_reward + float(self.reward_of_type[self.target_type[new]].sum())

    def terminated(self):
        return self.failure or bool(self.activated.all())


LOGIC_BY_KIND = {"go_to_target": GoToTargetLogic, "corridor": CorridorLogic, "maze": MazeLogic}
