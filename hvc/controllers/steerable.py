"""The steerable controller (Sec. 2.2): the high level sets a turning rate in the steering
range, held one gait cycle; the steerable expert runs the cycle with that rate as input, its
phase entered at the step whose pose best matches the body's when an episode starts, then
running on."""
from __future__ import annotations

import numpy as np

from hvc.controllers.pose_matching import actuator_order, best_matching_step
from hvc.envs.spaces import ActionSpace
from hvc.mocap.reference import cycle_steps


class SteerableController:
    def __init__(self, expert, steering_range=(-1.5, 1.5)):
        self.expert = expert
        self.low, self.high = (float(v) for v in steering_range)
        self.cycle = cycle_steps(expert.reference.phase)
        self.phase = expert.reference.phase[:self.cycle]
        self.action_space = ActionSpace(discrete=False, size=1, low=self.low, high=self.high)
        self.actuator_order = actuator_order()
        self.rate, self.held, self.t = 0.0, self.cycle, None

    @classmethod
    def from_config(cls, config, env, skills) -> "SteerableController":
        """The job's steerable policy (its library's one expert)."""
        return cls(skills.library.experts[0], config.get("steering_range", (-1.5, 1.5)))

    @property
    def start_references(self) -> list:
        return [self.expert.reference]

    def reset(self) -> None:
        self.rate, self.held, self.t = 0.0, self.cycle, None  # phase chosen from the first pose

    def needs_action(self) -> bool:
        return self.held >= self.cycle

    def set_action(self, action) -> None:
        self.rate = float(np.clip(np.ravel(action)[0], self.low, self.high))
        self.held = 0

    @property
    def record(self) -> float:
        """The turning rate in force (episode records)."""
        return self.rate

    def body_action(self, obs) -> np.ndarray:
        if self.t is None:
            self.t = best_matching_step(self.expert.reference.joints[:self.cycle], obs["proprio"],
                                        self.actuator_order)
        t, self.t = self.t, (self.t + 1) % self.cycle
        self.held += 1
        return self.expert.act(np.concatenate([obs["proprio"], [self.phase[t], self.rate]]).astype(np.float32))
