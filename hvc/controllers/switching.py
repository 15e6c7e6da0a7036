"""The switching controller (Sec. 2.2): the high level picks one of k behaviours, held one gait
cycle; on a change the switching expert enters the new behaviour at the step whose pose best
matches the body's (as the training references were cut), and its 1-of-k input follows the
choice."""
from __future__ import annotations

import numpy as np

from hvc.controllers.pose_matching import actuator_order, best_matching_step
from hvc.envs.spaces import ActionSpace
from hvc.errors import ControllerUnavailable
from hvc.mocap.reference import cycle_steps


def gait_cycle_steps(behaviours) -> int:
    """Steps of one gait cycle: the first cyclic behaviour's (the run's), the paper's hold for
    a switching choice ("switch points allowed at the end of gait cycles")."""
    for ref in behaviours:
        if ref.cyclic:
            return cycle_steps(ref.phase)
    raise ValueError("no cyclic behaviour gives a gait cycle to hold the switching choice for; "
                     "set controller.hold_steps")


class SwitchingController:
    def __init__(self, expert, behaviours, hold_steps: int | None = None):
        """`hold_steps`: how long each choice is held; None, one gait cycle (gait_cycle_steps)."""
        self.expert = expert
        self.actuator_order = actuator_order()
        self.behaviours = behaviours  # references of the k behaviours (pose matching and time inputs)
        self.hold = gait_cycle_steps(behaviours) if hold_steps is None else int(hold_steps)
        self.action_space = ActionSpace(discrete=True, n=len(behaviours))
        self.current, self.t, self.held = None, 0, self.hold

    @classmethod
    def from_config(cls, config, env, skills) -> "SwitchingController":
        """The job's switching policy (its library's one expert) over the behaviours it was trained on."""
        library = skills.library
        return cls(library.experts[0], _behaviours(library), config.get("hold_steps"))

    @property
    def start_references(self) -> list:
        return list(self.behaviours)

    def reset(self) -> None:
        self.current, self.t, self.held = None, 0, self.hold

    def needs_action(self) -> bool:
        return self.held >= self.hold

    @property
    def record(self) -> float:
        """The behaviour in force (episode records)."""
        return -1.0 if self.current is None else float(self.current)

    def set_action(self, action) -> None:
        k = int(action)
        if not 0 <= k < len(self.behaviours):
            raise ValueError(f"behaviour {k} outside 0..{len(self.behaviours) - 1}")
        if k != self.current:
            self.current, self.t = k, None  # entry step chosen from the body's pose at the next step
        self.held = 0

    def body_action(self, obs) -> np.ndarray:
        ref = self.behaviours[self.current]
        if self.t is None:
            self.t = best_matching_step(ref.joints, obs["proprio"], self.actuator_order)
        t = min(self.t, ref.num_steps - 1)
        self.t = t + 1 if t + 1 < ref.num_steps else (0 if ref.cyclic else t)
        self.held += 1
        code = np.zeros(len(self.behaviours), np.float32)
        code[self.current] = 1.0
        return self.expert.act(np.concatenate([obs["proprio"], [ref.phase[t]], code]).astype(np.float32))


def _behaviours(library) -> list:
    """The switching policy's behaviour references: stored in the library, or (libraries made
    before they were) rebuilt from the entries it was trained on."""
    if library.behaviours:
        return library.behaviours
    from hvc.mocap.reference import build_reference
    from hvc.mocap.source import find_mocap_file

    entries = library.meta.get("switching_entries")
    if not entries:
        raise ControllerUnavailable("this switching library does not list its behaviours (switching_entries)")
    mocap_file = str(find_mocap_file(None, "2019"))
    return [build_reference(e, mocap_file) for e in entries]
