"""End-to-end (Appendix A.5): the high level emits the body's whole action every step."""
from __future__ import annotations

import numpy as np

from hvc.controllers.base import ActionSpace


class EndToEndController:
    def __init__(self, action_low: np.ndarray, action_high: np.ndarray):
        self.low, self.high = np.asarray(action_low, np.float32), np.asarray(action_high, np.float32)
        self.action_space = ActionSpace(discrete=False, size=len(self.low), low=float(self.low.min()),
                                        high=float(self.high.max()))
        self._action = None

    @classmethod
    def from_config(cls, config, env, skills=None) -> "EndToEndController":
        return cls(env.action_low, env.action_high)

    def reset(self) -> None:
        self._action = None

    def needs_action(self) -> bool:
        return True

    def set_action(self, action) -> None:
        self._action = np.clip(np.asarray(action, np.float32), self.low, self.high)

    def body_action(self, obs) -> np.ndarray:
        return self._action
