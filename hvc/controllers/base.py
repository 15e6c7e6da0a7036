"""Controller interface and the env wrapper that drives a body through a controller."""
from __future__ import annotations

from typing import Any, Protocol

import numpy as np

from hvc.envs.spaces import ActionSpace


class Controller(Protocol):
    """What ControlledEnv drives. A controller class is named by its config's `_target_` and
    built by `from_config(config, env, skills)` (hvc.controllers.factory); `start_references`
    (optional) are the mocap references whose poses start the tasks' episodes."""

    action_space: ActionSpace

    @classmethod
    def from_config(cls, config: Any, env: Any, skills: Any) -> "Controller": ...
    def reset(self) -> None: ...
    def needs_action(self) -> bool: ...
    def set_action(self, action: Any) -> None: ...
    def body_action(self, obs: dict[str, np.ndarray]) -> np.ndarray: ...


class ControlledEnv:
    """A FastEnv driven through a controller. `step(hl_action)` consumes `hl_action` only
    when `needs_action` is true (pass None otherwise); `info["new_action"]` says whether it
    was consumed, which is where the paper's policy-gradient loss applies."""

    def __init__(self, env, controller: Controller):
        self.env, self.controller = env, controller
        self.obs: dict[str, np.ndarray] | None = None
        references = getattr(controller, "start_references", ())
        if references and env.task_cfg.get("init_from_clips"):
            # the paper starts tasks from mocap poses: those the controller's own skills track
            # (a steerable policy from its run cycle), stored in its library, so no mocap file is needed
            from hvc.mocap.pose_bank import PoseBank

            env.set_start_poses(PoseBank.from_references(references))

    @property
    def action_space(self) -> ActionSpace:
        return self.controller.action_space

    @property
    def needs_action(self) -> bool:
        return self.controller.needs_action()

    def reset(self) -> dict[str, np.ndarray]:
        self.obs = self.env.reset()
        self.controller.reset()
        return self.obs

    def step(self, hl_action=None):
        new_action = self.controller.needs_action()
        if new_action:
            if hl_action is None:
                raise ValueError("the controller needs a new high-level action (needs_action is true)")
            self.controller.set_action(hl_action)
        self.obs, reward, discount, done = self.env.step(self.controller.body_action(self.obs))
        return self.obs, reward, discount, done, {"new_action": new_action,
                                                  "hl_action": getattr(self.controller, "record", np.nan)}

    def close(self) -> None:
        self.env.close()
