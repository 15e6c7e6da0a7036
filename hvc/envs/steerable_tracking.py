"""Tracking for the steerable policy (Sec. 2.2): a run cycle steered at random rates.

Each episode draws a turning rate per gait cycle (uniform in `turn_rates`; with
`turn_rate_repeat` p a cycle keeps the previous cycle's rate with probability p, so turns
held for several cycles, as a high level circling toward a target holds them, are in the
training data) and tracks the steered reference (hvc.mocap.steering); the policy sees the phase and the current
cycle's rate, which the high level later sets (held one gait cycle).

With `reanchor` (the default) each new cycle's reference starts from the heading and
place the body has reached, and turns from there (TrackingLogic.anchor): the policy is
scored on the turn it makes in this cycle. Without it the reference's heading runs on from
the episode's start, and once the body lags it by a fraction of a turn the reward stays near
zero whatever the policy does, so there is nothing left to learn from.
"""
from __future__ import annotations

import numpy as np

from hvc.envs.tracking import TrackingLogic
from hvc.mocap.reference import cycle_steps
from hvc.mocap.steering import steer_cycle


class SteerableTrackingLogic(TrackingLogic):
    observation_size = 2
    reference_per_episode = True

    def __init__(self, cfg, env):
        super().__init__(cfg, env)
        ref = self.reference  # the looped cycle: keep one repetition as the template
        self.cycle = ref.segment(0, cycle_steps(ref.phase))
        self.turn_rates = tuple(float(r) for r in cfg.get("turn_rates", (-1.5, 1.5)))
        self.cycles = int(cfg.get("cycle_repeats", 4))
        self.lean = bool(cfg.get("steer_lean", False))
        self.repeat = float(cfg.get("turn_rate_repeat") or 0.0)
        if not 0.0 <= self.repeat <= 1.0:
            raise ValueError(f"turn_rate_repeat={self.repeat} must be a probability in [0, 1]")
        self.rates = np.zeros(self.cycle.num_steps * self.cycles)
        self.held_rate: float | None = None  # evaluation: one commanded rate for every cycle

    def reset(self, model, data, rng):
        rates = self._random_rates(rng) if self.held_rate is None else np.full(self.cycles, self.held_rate)
        self.reference, self.rates = steer_cycle(self.cycle, rates, lean=self.lean)
        if self.reanchor:  # each cycle turns from where the body faces (TrackingLogic.anchor)
            self.anchors = frozenset(range(self.cycle.num_steps, self.reference.num_steps, self.cycle.num_steps))
        super().reset(model, data, rng)

    def _random_rates(self, rng) -> np.ndarray:
        """One rate per cycle: uniform draws, each kept from the cycle before with probability `repeat`."""
        rates = rng.uniform(*self.turn_rates, self.cycles)
        if self.repeat > 0:  # (no extra draw otherwise: the same episodes as before the option)
            keep = rng.random(self.cycles) < self.repeat
            for k in range(1, self.cycles):
                if keep[k]:
                    rates[k] = rates[k - 1]
        return rates

    def observation(self, model, data):
        return np.array([self.reference.phase[self.t], self.rates[self.t]], np.float32)
