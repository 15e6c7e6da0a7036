"""Tracking for the steerable policy (Sec. 2.2): a run cycle steered at random rates.

Each episode draws a turning rate per gait cycle (uniform in `turn_rates`) and tracks the
steered reference (hvc.mocap.steering); the policy sees the phase and the current
cycle's rate, which the high level later sets (held one gait cycle).

With `steer_reanchor` (the default) each new cycle's reference starts from the heading and
place the body has reached, and turns from there: the policy is scored on the turn it makes
in this cycle. Without it the reference's heading runs on from the episode's start, and
once the body lags it by a fraction of a turn the orientation term (weight 20 of 30) holds
the reward near zero whatever the policy does, so there is nothing left to learn from.
"""
from __future__ import annotations

import numpy as np

from hvc.lowlevel.tracking import TrackingLogic
from hvc.mocap.clips import root_heading
from hvc.mocap.steering import steer_cycle, turn_from


class SteerableTrackingLogic(TrackingLogic):
    observation_size = 2
    reference_per_episode = True

    def __init__(self, cfg, env):
        super().__init__(cfg, env)
        ref = self.reference  # the looped cycle: keep one repetition as the template
        wrap = np.flatnonzero(np.diff(ref.phase) < 0)
        self.cycle = ref.segment(0, int(wrap[0]) + 1 if len(wrap) else ref.num_steps)
        self.turn_rates = tuple(float(r) for r in cfg.get("turn_rates", (-1.5, 1.5)))
        self.cycles = int(cfg.get("cycle_repeats", 4))
        self.rates = np.zeros(self.cycle.num_steps * self.cycles)
        self.held_rate: float | None = None  # evaluation: one commanded rate for every cycle
        self.reanchor = bool(cfg.get("steer_reanchor", True))

    def reset(self, model, data, rng):
        rates = (rng.uniform(*self.turn_rates, self.cycles) if self.held_rate is None
                 else np.full(self.cycles, self.held_rate))
        self.reference, self.rates = steer_cycle(self.cycle, rates)
        super().reset(model, data, rng)

    def after_step(self, model, data, rng):
        start = self.t + 1
        if self.reanchor and start % self.cycle.num_steps == 0 and start < self.reference.num_steps:  # a new cycle
            body = data.qpos[self.root_qpos + 3:self.root_qpos + 7]
            h_body, h_ref = (float(root_heading(q[None])[0]) for q in (body, self.reference.quaternion[start]))
            yaw = (h_body - h_ref + np.pi) % (2 * np.pi) - np.pi
            turn_from(self.reference, start, yaw, data.qpos[self.root_qpos:self.root_qpos + 2])
        super().after_step(model, data, rng)

    def observation(self, model, data):
        return np.array([self.reference.phase[self.t], self.rates[self.t]], np.float32)
