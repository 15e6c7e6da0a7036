"""Pushes: random horizontal shoves of the root during an expert's RL phase (`lowlevel.pushes`).

Why: experts trained only near their reference fall from the states cold switching leaves the
body in (docs/results/composability). Switch starts and cut-ins train from such states of the
library's own fragments; pushes are the generic alternative (issue 23 names them), which needs
no library: a force on the root knocks the body off its reference mid-episode, and the expert
learns to recover or the episode ends as usual. Final evaluations never push.
"""
from __future__ import annotations

import numpy as np


class Pushes:
    """At each control step without a push acting, one starts with `probability`: `force`
    newtons in a uniformly random horizontal direction on body `body` for `steps` control
    steps (written to MuJoCo's `xfrc_applied`, which the physics applies at every substep)."""

    def __init__(self, probability: float, force: float, steps: int, body: int, rng: np.random.Generator,
                 fall_window: int):
        self.probability, self.force, self.steps, self.body = probability, force, steps, body
        self.rng = rng
        self.fall_window = fall_window  # control steps after a push's start that a fall is laid to it
        self.remaining = 0
        self.since_push: int | None = None  # control steps since the last push of this episode began
        self.vector = np.zeros(3)

    def before_step(self, env) -> bool:
        """Sets the force for the coming control step of `env` (a FastEnv); whether a push
        started. A push never carries into a new episode."""
        data = env.data
        if env.episode_steps == 0:
            self.stop(data)
        started = False
        if self.remaining == 0 and self.rng.random() < self.probability:
            angle = self.rng.uniform(0.0, 2.0 * np.pi)
            self.vector = self.force * np.array([np.cos(angle), np.sin(angle), 0.0])
            self.remaining, self.since_push, started = self.steps, 0, True
        if self.remaining > 0:
            data.xfrc_applied[self.body, :3] = self.vector
            self.remaining -= 1
        else:
            data.xfrc_applied[self.body, :3] = 0.0
        if self.since_push is not None:
            self.since_push += 1
        return started

    def fall_follows_push(self) -> bool:
        """Whether a fall now comes within `fall_window` control steps of a push's start."""
        return self.since_push is not None and self.since_push <= self.fall_window

    def stop(self, data) -> None:
        """Ends any push: the episode ended or another skill takes the body over."""
        data.xfrc_applied[self.body, :3] = 0.0
        self.remaining, self.since_push = 0, None
