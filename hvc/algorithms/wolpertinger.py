"""Wolpertinger-style learner for query-based selection (Appendix A.4; Dulac-Arnold et al. 2015).

The policy emits a Gaussian query in fragment-key space; the k nearest keys are scored by
Q(h, key) and one is chosen with p ~ exp(Q / T). Q is trained with 1-step targets
r + gamma E_{a ~ pi(.|h')} Q_target(h', a) on both the query and the selected key of each
replayed step (one Q for both kinds of action, as the paper found most stable); the policy
follows SVG(0) through Q_target at steps where a new fragment was chosen (svg0_retrace).
"""
from __future__ import annotations

import json

import numpy as np
import torch

from hvc.algorithms.learner import Acted
from hvc.algorithms.svg0_retrace import RecurrentSVG0Retrace
from hvc.schema import QueryControllerConfig, WolpertingerConfig, typed


class WolpertingerLearner(RecurrentSVG0Retrace):
    """`selector` is the query controller (hvc.controllers.query): its normalised `keys` and
    `nearest(query)`; the index of the chosen fragment is what the envs get."""

    uses_controller = True
    keeps_query = True
    schema = WolpertingerConfig

    def __init__(self, agent, gamma: float, low: float, high: float, sigma_clip, selector, temperature: float,
                 hp: WolpertingerConfig = WolpertingerConfig(), seed: int = 0):
        super().__init__(agent, gamma, low, high, sigma_clip, hp)
        self.selector = selector
        self.keys = torch.from_numpy(np.asarray(selector.keys)).to(next(agent.parameters()).device)
        self.temperature = float(temperature)
        self.rng = np.random.default_rng(seed)

    @classmethod
    def from_config(cls, agent, cfg, space, controller=None):
        return super().from_config(agent, cfg, space, selector=controller, seed=int(cfg.seed),
                                   temperature=typed(QueryControllerConfig, cfg.controller).temperature)

    @torch.no_grad()
    def act(self, policy_out: torch.Tensor, h: torch.Tensor) -> Acted:
        """The envs get the fragment index; replay keeps the selected key as the action (the
        agent's next input too) and the query beside it, with the query's log density."""
        dist = self.distribution(self.agent, policy_out)
        queries = torch.clamp(dist.sample(), self.low, self.high)
        log_mu = dist.log_prob(queries).sum(-1).cpu().numpy()
        host_queries = queries.cpu().numpy().astype(np.float32)
        indices = []
        for e in range(queries.shape[0]):
            candidates = self.selector.nearest(host_queries[e])
            q = self.agent.values(h[e].expand(len(candidates), -1), self.keys[candidates])
            p = torch.softmax(q / self.temperature, 0).cpu().numpy().astype(np.float64)
            indices.append(int(candidates[self.rng.choice(len(candidates), p=p / p.sum())]))
        indices = np.asarray(indices)
        keys = self.keys[indices].cpu().numpy()
        return Acted(send=indices, action=keys, log_mu=log_mu, seen=keys, query=host_queries)

    def update(self, b: dict) -> dict[str, float]:
        out, h, t_out, t_h = self.replay_unrolls(b)
        with torch.no_grad():
            t_dist = self.distribution(self.target, t_out[1:])
            v_next = torch.stack([self.target.values(t_h[1:], torch.clamp(t_dist.sample(), self.low, self.high))
                                  for _ in range(self.value_samples)]).mean(0)
            targets = b["reward"] + self.gamma * b["discount"] * v_next
        q_query = self.agent.values(h[:-1], b["query"])
        q_selected = self.agent.values(h[:-1], b["action"])
        critic_loss = 0.5 * (((q_query - targets) ** 2).mean() + ((q_selected - targets) ** 2).mean())
        return self.step(critic_loss, out, b, q_selected, t_out, t_h)

    def state_dict(self) -> dict:
        return {**super().state_dict(), "selection_rng": json.dumps(self.rng.bit_generator.state)}

    def load_state_dict(self, state: dict) -> None:
        super().load_state_dict(state)
        if "selection_rng" in state:  # checkpoints from before it was saved go on with a fresh stream
            self.rng.bit_generator.state = json.loads(state["selection_rng"])
