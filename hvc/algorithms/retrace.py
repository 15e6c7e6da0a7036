"""Retrace(lambda) targets for Q (Munos et al. 2016), time-major [T, B] tensors.

Q_ret(s_t, a_t) = r_t + gamma d_t (V(s_{t+1}) + c_{t+1} (Q_ret(s_{t+1}, a_{t+1}) - Q(s_{t+1}, a_{t+1}))),
with c = lambda * min(1, pi(a|s) / mu(a|s)), V(s) = E_pi Q(s, .), d_t the env discount
(0 after a failure), and the last step bootstrapping from V alone.
"""
from __future__ import annotations

import torch


@torch.no_grad()
def retrace_targets(rewards: torch.Tensor, discounts: torch.Tensor, q_taken: torch.Tensor,
                    v_next: torch.Tensor, traces: torch.Tensor, gamma: float) -> torch.Tensor:
    """rewards, discounts: r_t, d_t; q_taken: Q_target(s_t, a_t); v_next: E_pi Q_target(s_{t+1}, .);
    traces: c_t = lambda min(1, pi/mu) at step t. All [T, B]; returns Q_ret [T, B]."""
    horizon = rewards.shape[0]
    targets = torch.empty_like(rewards)
    targets[-1] = rewards[-1] + gamma * discounts[-1] * v_next[-1]
    for t in range(horizon - 2, -1, -1):
        correction = traces[t + 1] * (targets[t + 1] - q_taken[t + 1])
        targets[t] = rewards[t] + gamma * discounts[t] * (v_next[t] + correction)
    return targets


def truncated_traces(log_pi: torch.Tensor, log_mu: torch.Tensor, lam: float,
                     chose: torch.Tensor | None = None) -> torch.Tensor:
    """c_t = lambda * min(1, pi(a_t|s_t) / mu(a_t|s_t)); where `chose` is 0 (a high-level step
    that held its action: the behaviour chose nothing) the ratio is 1."""
    log_ratio = log_pi - log_mu
    if chose is not None:
        log_ratio = log_ratio * chose
    return lam * torch.exp(torch.clamp(log_ratio, max=0.0))
