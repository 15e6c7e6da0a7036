"""The fast step path: dm_control builds the models, raw mujoco steps them.

Why: composer's `env.step` runs well below the raw physics rate and its reset recompiles
the whole MJCF (docs/results/design_measurements). Here a small pool of models
is compiled once (one per corridor or maze layout), resets write positions into the
model, and a step is: action -> ctrl, the physics substeps, numpy observations.

Stepping follows composer exactly (mj_step2, the substeps, one mj_forward), so states,
sensor readings (the accelerometer included) and contacts equal composer's bit for bit.
"""
from __future__ import annotations

import copy
from dataclasses import dataclass, field
from typing import Any, Mapping

import mujoco
import numpy as np

from hvc.envs import render as render_lib
from hvc.envs.builders import build_composer_env
from hvc.envs.observations import Proprioception
from hvc.envs.steerable_tracking import SteerableTrackingLogic
from hvc.envs.switching_tracking import SwitchingTrackingLogic
from hvc.envs.task_logic import LOGIC_BY_KIND, TaskLogic
from hvc.envs.tracking import TrackingLogic


@dataclass
class Layout:
    """One compiled model of a task (a corridor or maze instance) and what was resolved on it."""

    model: mujoco.MjModel
    data: mujoco.MjData
    proprio: Proprioception
    logic: TaskLogic
    actuators: np.ndarray
    camera: str | None
    renderer: render_lib.CameraRenderer | None = field(default=None, repr=False)


def layout_from_composer(env, task: Mapping[str, Any], body: Mapping[str, Any]) -> Layout:
    """Captures the composer env's current compiled model (call after env.reset())."""
    kind = task["kind"]
    if kind == "tracking" and (task.get("clip") or {}).get("switching"):
        logic_class = SwitchingTrackingLogic
    elif kind == "tracking" and (task.get("clip") or {}).get("steer"):
        logic_class = SteerableTrackingLogic
    elif kind == "tracking":
        logic_class = TrackingLogic
    elif kind in LOGIC_BY_KIND:
        logic_class = LOGIC_BY_KIND[kind]
    else:
        raise ValueError(f"task.kind={kind!r} has no fast env; allowed: {', '.join([*LOGIC_BY_KIND, 'tracking'])}")
    physics = env.physics
    walker = env.task._walker
    proprio = Proprioception(walker, physics, list(body["proprio"]))
    logic = logic_class(task, env)  # resolves ids on this model
    actuators = np.atleast_1d(physics.bind(list(walker.actuators)).element_id).astype(np.intp)
    camera = None
    if task.get("vision"):
        cam = walker.body_camera if body.get("camera") == "bodycam" else walker.egocentric_camera
        camera = cam.full_identifier
    model = copy.copy(physics.model.ptr)  # ours alone: resets edit it
    return Layout(model=model, data=mujoco.MjData(model), proprio=proprio, logic=logic,
                  actuators=actuators, camera=camera)


def forward_without_actuation(model: mujoco.MjModel, data: mujoco.MjData) -> None:
    """mj_forward with actuation off, as dm_control does after a reset (no control yet)."""
    flags = model.opt.disableflags
    model.opt.disableflags = flags | mujoco.mjtDisableBit.mjDSBL_ACTUATION
    try:
        mujoco.mj_forward(model, data)
    finally:
        model.opt.disableflags = flags


class FastEnv:
    """One task + body on the fast path.

    `reset()` -> obs; `step(action)` -> (obs, reward, discount, done). `done` is a
    failure/success termination (discount 0 on failure) or the time limit (discount 1).
    Observations: dict with `proprio` (float32), `task` (float32, e.g. the egocentric
    target) and, for vision tasks when `render` is on, `image` (uint8 64x64x3).
    """

    def __init__(self, layouts: list[Layout], task: Mapping[str, Any],
                 render_settings: Mapping[str, Any] | None = None, seed: int = 0,
                 render: bool | None = None):
        self.task_cfg = task
        self.render_settings = render_settings
        self.rng = np.random.default_rng(seed)
        self.control_timestep = float(task["control_timestep"])
        self.time_limit = float(task["time_limit"])
        self.vision = bool(task.get("vision")) if render is None else bool(render)
        self.layouts = layouts
        self.layout = layouts[0]
        model = self.layout.model
        self.n_substeps = int(round(self.control_timestep / model.opt.timestep))
        self.action_size = int(self.layout.actuators.size)
        self.action_low = model.actuator_ctrlrange[self.layout.actuators, 0].copy()
        self.action_high = model.actuator_ctrlrange[self.layout.actuators, 1].copy()
        self.episode_return = 0.0
        self.episode_steps = 0

    @classmethod
    def build(cls, task: Mapping[str, Any], body: Mapping[str, Any],
              render_settings: Mapping[str, Any] | None = None, seed: int = 0,
              render: bool | None = None) -> "FastEnv":
        """Compiles `task.layout_pool` layouts with dm_control, then never recompiles."""
        env = build_composer_env(task, body, seed=seed)
        layouts = []
        for _ in range(max(1, int(task.get("layout_pool", 1)))):
            env.reset()  # composer compiles a fresh layout
            layouts.append(layout_from_composer(env, task, body))
        env.close()
        fast = cls(layouts, task, render_settings, seed, render)
        if task.get("init_clips"):
            from hvc.mocap.pose_bank import PoseBank

            fast.set_start_poses(PoseBank.from_entries(task["init_clips"], task["mocap_file"]))
        return fast

    def set_start_poses(self, bank) -> None:
        """Episodes start from poses of `bank` (a PoseBank), on every layout."""
        for layout in self.layouts:
            layout.logic.placement.pose_bank = bank

    @classmethod
    def from_composer(cls, env, task, body, render_settings=None, seed: int = 0,
                      render: bool | None = None) -> "FastEnv":
        """A fast env on the composer env's current model (state not copied), for tests."""
        return cls([layout_from_composer(env, task, body)], task, render_settings, seed, render)

    @property
    def model(self) -> mujoco.MjModel:
        return self.layout.model

    @property
    def data(self) -> mujoco.MjData:
        return self.layout.data

    @property
    def observation_sizes(self) -> dict[str, Any]:
        sizes: dict[str, Any] = {"proprio": self.layout.proprio.size, "task": self.layout.logic.observation_size}
        if self.vision:
            s = self.render_settings or {"height": 64, "width": 64}
            sizes["image"] = (int(s["height"]), int(s["width"]), 3)
        return sizes

    def reset(self) -> dict[str, np.ndarray]:
        self.layout = self.layouts[self.rng.integers(len(self.layouts))]
        model, data = self.layout.model, self.layout.data
        mujoco.mj_resetData(model, data)
        self.layout.logic.reset(model, data, self.rng)
        forward_without_actuation(model, data)
        self.layout.logic.after_reset(model, data)
        self.episode_return, self.episode_steps = 0.0, 0
        return self.observation()

    def advance(self, action: np.ndarray) -> None:
        """One control step of the physics under `action`, without the task's bookkeeping
        (reward, termination, its clock): what step() does first."""
        layout = self.layout
        model, data, logic = layout.model, layout.data, layout.logic
        data.ctrl[layout.actuators] = action
        if logic.needs_substep_hook:
            for _ in range(self.n_substeps):
                mujoco.mj_step2(model, data)
                mujoco.mj_step1(model, data)
                logic.after_substep(model, data)
        else:
            mujoco.mj_step2(model, data)
            if self.n_substeps > 1:
                mujoco.mj_step(model, data, self.n_substeps - 1)
        mujoco.mj_forward(model, data)  # composer ends its step with one mj_forward too
        if logic.needs_subtree_vel:
            mujoco.mj_subtreeVel(model, data)

    def step(self, action: np.ndarray):
        self.advance(action)
        model, data, logic = self.layout.model, self.layout.data, self.layout.logic
        logic.after_step(model, data, self.rng)
        reward = logic.reward(model, data)
        failed = logic.terminated()
        discount = 0.0 if getattr(logic, "failure", False) else 1.0
        done = failed or data.time >= self.time_limit
        self.episode_return += reward
        self.episode_steps += 1
        return self.observation(), reward, discount, done

    def observation(self) -> dict[str, np.ndarray]:
        layout = self.layout
        obs = {"proprio": layout.proprio(layout.data),
               "task": layout.logic.observation(layout.model, layout.data)}
        if self.vision:
            obs["image"] = self.render()
        return obs

    def render(self) -> np.ndarray:
        """The egocentric camera image of the current state (renderer made on first use)."""
        layout = self.layout
        if layout.camera is None:
            raise ValueError(f"task {self.task_cfg['name']!r} has no camera (vision is off)")
        if layout.renderer is None:
            settings = self.render_settings or {"height": 64, "width": 64}
            layout.renderer = render_lib.CameraRenderer(layout.model, layout.camera, settings)
        return layout.renderer.render(layout.data)

    def random_action(self) -> np.ndarray:
        return self.rng.uniform(self.action_low, self.action_high).astype(np.float32)

    def close(self) -> None:
        for layout in self.layouts:
            if layout.renderer is not None:
                layout.renderer.close()
                layout.renderer = None
