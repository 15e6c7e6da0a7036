"""The interface every learner has, at both levels.

A learner owns its networks' optimiser(s) and target copies. It acts (samples the behaviour
policy's action and that action's log density, what off-policy corrections need), updates from
a replayed batch, and saves and restores all of that for a checkpoint. The trainers (the
high-level loop in hvc.runtime, the low-level expert trainer, `stage=record`) talk to a
learner only through these methods, so a new learner is one class in a file named after it:
V-trace (vtrace.py), SVG(0) + Retrace (svg0_retrace.py), Wolpertinger (wolpertinger.py).

High-level learners are built from the `algorithm` config: its `_target_` names the class,
whose `from_config` takes what it needs from the job's config.
"""
from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch


@dataclass
class Acted:
    """One batched high-level step's choice, per env."""

    send: np.ndarray         # what the envs get (a clipped action, a fragment index, ...)
    action: np.ndarray       # what replay keeps: the raw sample whose density is log_mu
    log_mu: np.ndarray       # the behaviour policy's log density of `action`
    seen: np.ndarray         # what the agent sees of it as its next input (prev_action)
    query: np.ndarray | None = None  # Wolpertinger: the query that selected `action`


class Learner(ABC):
    """act -> replay -> update; state_dict / load_state_dict for checkpoints."""

    steps: int = 0  # learner updates taken (target refreshes follow it)
    uses_controller: bool = False  # from_config wants the job's controller (Wolpertinger: its keys)
    keeps_query: bool = False  # replay keeps Acted.query beside the action (Wolpertinger)

    @abstractmethod
    def act(self, *args, **kwargs) -> Any:
        """The behaviour policy's sample and its log density."""

    @abstractmethod
    def update(self, batch) -> dict[str, float]:
        """One optimiser step on a replayed batch; the losses, as floats, for the metrics."""

    @abstractmethod
    def state_dict(self) -> dict:
        """Networks, targets, optimiser state and step count: what resuming needs."""

    @abstractmethod
    def load_state_dict(self, state: dict) -> None:
        ...


def restore_optimizer(optimizer: torch.optim.Optimizer, saved: dict, learning_rate: float) -> None:
    """Loads an optimiser's saved moments but keeps the configured rate: torch would restore the
    saved one and silently ignore a learning rate changed on resume."""
    optimizer.load_state_dict(saved)
    for group in optimizer.param_groups:
        group["lr"] = float(learning_rate)


def refresh_on_schedule(learner: Learner, period: int, sync) -> None:
    """Counts one update and calls `sync()` (copy online -> target) every `period` of them."""
    learner.steps += 1
    if learner.steps % int(period) == 0:
        sync()


class Pacer:
    """Learner updates owed to the actors: `per_unroll` for every unroll added (fractions
    accumulate), so the learner's share of the cores is a setting, not a race."""

    def __init__(self, per_unroll: float, credit: float = 0.0):
        self.per_unroll, self.credit = float(per_unroll), float(credit)

    def owed(self, unrolls: int) -> int:
        self.credit += self.per_unroll * unrolls
        due = int(self.credit)
        self.credit -= due
        return due
