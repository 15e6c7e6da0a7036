"""Builds the paper's tasks and bodies from dm_control's own walkers, arenas and tasks.

These composer environments are the reference: the fast env (`hvc.envs.fast_env`) takes
its compiled models from them and re-implements only the per-step loop, and the tests
and `hvc-bench` compare against them. Settings follow the paper and dm_control's
`locomotion/examples/basic_cmu_2019.py`.
"""
from __future__ import annotations

import functools
from typing import Any, Mapping

import numpy as np
from dm_control import composer
from dm_control.composer.variation import distributions
from dm_control.locomotion.arenas import corridors as corridor_arenas
from dm_control.locomotion.arenas import floors, labmaze_textures, mazes
from dm_control.locomotion.props import target_sphere
from dm_control.locomotion.tasks import corridors as corridor_tasks
from dm_control.locomotion.tasks import go_to_target, random_goal_maze
from dm_control.locomotion.walkers import cmu_humanoid, jumping_ball
from labmaze import fixed_maze

BODY_KINDS = ("cmu_humanoid", "rolling_ball")


class FloorTask(composer.Task):
    """The walker alone on dm_control's floor: the model for motion-capture tracking.

    dm_control's own tracking task (reference_pose.tracking) loads its clips through
    the HDF5 loader at construction and steps through composer; our tracking logic
    (hvc.envs.tracking) runs on the fast path instead, so this task only has to
    build the model and mirror the contact bookkeeping of the other tasks.
    """

    def __init__(self, walker, arena, physics_timestep: float, control_timestep: float):
        self._walker = walker
        self._arena = arena
        self._walker.create_root_joints(self._arena.attach(self._walker))
        for obs in (self._walker.observables.proprioception + self._walker.observables.kinematic_sensors):
            obs.enabled = True
        self.set_timesteps(physics_timestep=physics_timestep, control_timestep=control_timestep)

    @property
    def root_entity(self):
        return self._arena

    def initialize_episode(self, physics, random_state):
        self._walker.reinitialize_pose(physics, random_state)
        foot = set(self._walker.ground_contact_geoms)
        self._walker_nonfoot_geomids = set(physics.bind(
            [g for g in self._walker.mjcf_model.find_all("geom") if g not in foot]).element_id)
        self._ground_geomids = set(physics.bind(self._arena.ground_geoms).element_id)

    def get_reward(self, physics):
        return 0.0


def build_walker(body: Mapping[str, Any]):
    """A fresh dm_control walker for the body config (cameras stay disabled: we render ourselves)."""
    kind = body["kind"]
    if kind == "cmu_humanoid":
        if str(body["model_version"]) == "2020":
            return cmu_humanoid.CMUHumanoidPositionControlledV2020()
        return cmu_humanoid.CMUHumanoidPositionControlled(model_version=str(body["model_version"]))
    if kind == "rolling_ball":
        return jumping_ball.RollingBallWithHead()
    raise ValueError(f"body.kind={kind!r} is not one of {', '.join(BODY_KINDS)}")


def _uniform(bounds) -> distributions.Uniform:
    low, high = bounds
    return distributions.Uniform(float(low), float(high))


def _maze_textures():
    return dict(
        skybox_texture=labmaze_textures.SkyBox(style="sky_03"),
        wall_textures=labmaze_textures.WallTextures(style="style_01"),
        floor_textures=labmaze_textures.FloorTextures(style="style_01"),
    )


def _target_builders(task: Mapping[str, Any]):
    return [
        functools.partial(target_sphere.TargetSphere, radius=float(task["target_radius"]),
                          rgb1=tuple(colors[0]), rgb2=tuple(colors[1]))
        for colors in task["target_colors"]
    ]


def _go_to_target(task: Mapping[str, Any], walker, timesteps: dict) -> composer.Task:
    return go_to_target.GoToTarget(
        walker=walker, arena=floors.Floor(size=tuple(task["arena_size"])),
        moving_target=bool(task["moving_target"]),
        steps_before_moving_target=int(task["steps_before_moving_target"]),
        distance_tolerance=float(task["distance_tolerance"]), **timesteps)


def _corridor(task: Mapping[str, Any], walker, timesteps: dict) -> composer.Task:
    if task["arena"] == "walls":
        arena = corridor_arenas.WallsCorridor(
            wall_gap=float(task["wall_gap"]), wall_width=_uniform(task["wall_width"]),
            wall_height=float(task["wall_height"]), corridor_width=float(task["corridor_width"]),
            corridor_length=float(task["corridor_length"]), include_initial_padding=False)
    elif task["arena"] == "gaps":
        arena = corridor_arenas.GapsCorridor(
            platform_length=_uniform(task["platform_length"]),
            gap_length=_uniform(task["gap_length"]),
            corridor_width=float(task["corridor_width"]),
            corridor_length=float(task["corridor_length"]))
    else:
        raise ValueError(f"task.arena={task['arena']!r} is not one of walls, gaps")
    return corridor_tasks.RunThroughCorridor(
        walker=walker, arena=arena, walker_spawn_position=tuple(task["spawn_position"]),
        target_velocity=float(task["target_velocity"]),
        terminate_at_height=float(task["terminate_at_height"]), **timesteps)


def _maze(task: Mapping[str, Any], walker, timesteps: dict) -> composer.Task:
    builders = _target_builders(task)
    common = dict(randomize_spawn_rotation=bool(task["randomize_spawn_rotation"]),
                  aliveness_reward=float(task["aliveness_reward"]), **timesteps)
    if task["maze"] == "random":
        arena = mazes.RandomMazeWithTargets(
            x_cells=int(task["x_cells"]), y_cells=int(task["y_cells"]),
            xy_scale=float(task["xy_scale"]), max_rooms=int(task["max_rooms"]),
            room_min_size=int(task["room_min_size"]), room_max_size=int(task["room_max_size"]),
            spawns_per_room=int(task["spawns_per_room"]),
            targets_per_room=int(task["targets_per_room"]), **_maze_textures())
    elif task["maze"] == "fixed":
        maze = fixed_maze.FixedMazeWithRandomGoals(
            entity_layer=str(task["level"]), variations_layer=None, num_spawns=1,
            num_objects=int(task["num_targets"]))
        arena = mazes.MazeWithTargets(maze=maze, xy_scale=float(task["xy_scale"]),
                                      z_height=float(task["z_height"]), **_maze_textures())
    else:
        raise ValueError(f"task.maze={task['maze']!r} is not one of random, fixed")
    # Types keep a fixed colour here (no builder shuffling): the fast env assigns the
    # rewards to colours at random each episode, which is the same distribution.
    return random_goal_maze.ManyHeterogeneousGoalsMaze(
        walker=walker, maze_arena=arena, target_builders=builders,
        target_type_rewards=[float(r) for r in task["target_rewards"]],
        target_type_proportions=[1] * len(builders), shuffle_target_builders=False, **common)


def _tracking(task: Mapping[str, Any], walker, timesteps: dict) -> composer.Task:
    return FloorTask(walker, floors.Floor(size=tuple(task["arena_size"])), **timesteps)


# task.kind -> the builder of its dm_control composer task
TASK_BUILDERS = {"go_to_target": _go_to_target, "corridor": _corridor, "maze": _maze, "tracking": _tracking}


def build_task(task: Mapping[str, Any], walker) -> composer.Task:
    """The dm_control composer task for a task config, with the paper's timesteps."""
    kind = task["kind"]
    if kind not in TASK_BUILDERS:
        raise ValueError(f"task.kind={kind!r} has no environment; allowed: {', '.join(TASK_BUILDERS)}")
    timesteps = dict(physics_timestep=float(task["physics_timestep"]),
                     control_timestep=float(task["control_timestep"]))
    return TASK_BUILDERS[kind](task, walker, timesteps)


def build_composer_env(task: Mapping[str, Any], body: Mapping[str, Any], seed: int | None = None):
    """dm_control's composer Environment for (task, body): the reference implementation."""
    walker = build_walker(body)
    composer_task = build_task(task, walker)
    # Composer's camera observables render with dm_control's own GL context on every
    # step; we render with hvc.envs.render instead, so switch them off here.
    for name in ("egocentric_camera", "body_camera"):
        if hasattr(walker.observables, name):
            getattr(walker.observables, name).enabled = False
    return composer.Environment(
        task=composer_task, time_limit=float(task["time_limit"]),
        random_state=np.random.RandomState(seed), strip_singleton_obs_buffer_dim=True)
