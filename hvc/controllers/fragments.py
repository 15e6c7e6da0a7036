"""Control fragments (Sec. 2.2): cold switching among short pieces of the experts.

Fragment j of clip c starts at time index j * T of that clip's expert; choosing it runs
the expert from there for T control steps (fewer for a clip's last fragment), the time
input ticking as during tracking. Nothing was trained for the switches themselves.
"""
from __future__ import annotations

import numpy as np

from hvc.controllers.base import ActionSpace
from hvc.lowlevel.library import policy_observation
from hvc.mocap.clip_sets import Fragment


class FragmentsController:
    def __init__(self, skills):
        """`skills`: the job's hvc.skills.Skills, whose fragments are cut once per job."""
        self.library = skills.library
        self.fragments: list[Fragment] = skills.fragments
        self.action_space = ActionSpace(discrete=True, n=len(self.fragments))
        self.current: Fragment | None = None
        self.index = -1  # the running fragment's index (episode records)
        self.step_in_fragment = 0

    @classmethod
    def from_config(cls, config, env, skills) -> "FragmentsController":
        return cls(skills)

    @property
    def start_references(self) -> list:
        return [e.reference for e in self.library.experts]

    def reset(self) -> None:
        self.current, self.step_in_fragment, self.index = None, 0, -1

    def needs_action(self) -> bool:
        return self.current is None or self.step_in_fragment >= self.current.length

    def set_action(self, action) -> None:
        index = int(action)
        if not 0 <= index < len(self.fragments):
            raise ValueError(f"fragment {index} outside 0..{len(self.fragments) - 1}")
        self.current, self.step_in_fragment = self.fragments[index], 0
        self.index = index

    def body_action(self, obs) -> np.ndarray:
        fragment = self.current
        expert = self.library.experts[fragment.clip]
        t = min(fragment.start + self.step_in_fragment, expert.reference.num_steps - 1)
        self.step_in_fragment += 1
        ll_obs = policy_observation({"proprio": obs["proprio"], "task": expert.reference.phase[t:t + 1]})
        return expert.act(ll_obs)

    @property
    def fragment_index(self) -> tuple[int, int] | None:
        """(clip, start) of the running fragment."""
        return None if self.current is None else (self.current.clip, self.current.start)

    @property
    def record(self) -> float:
        """What an episode record stores per step: the running fragment's index."""
        return float(self.index)
