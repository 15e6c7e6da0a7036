"""V-trace actor-critic (Espeholt et al. 2018, IMPALA) for the discrete controllers.

Targets, time-major [T, B]:
  rho_t = min(rho_bar, pi/mu), c_t = lambda min(c_bar, pi/mu)
  delta_t = rho_t (r_t + gamma d_t V(x_{t+1}) - V(x_t))
  v_s = V(x_s) + delta_s + gamma d_s c_s (v_{s+1} - V(x_{s+1})),  v_T = V(x_T) (bootstrap)
Policy-gradient advantage: rho_t (r_t + gamma d_t v_{t+1} - V(x_t)).
As in the paper, the value loss applies at every step but the policy-gradient and
entropy terms only where a new high-level action was sampled (`new_action` mask); with
an N-step unroll the bootstrap is from the unroll's last state.
"""
from __future__ import annotations

from dataclasses import dataclass

import torch


@dataclass
class VTraceReturns:
    vs: torch.Tensor              # [T, B] value targets
    pg_advantages: torch.Tensor   # [T, B]


@torch.no_grad()
def vtrace_targets(log_rhos: torch.Tensor, discounts: torch.Tensor, rewards: torch.Tensor, values: torch.Tensor,
                   bootstrap_value: torch.Tensor, gamma: float, rho_clip: float = 1.0, c_clip: float = 1.0,
                   lam: float = 1.0) -> VTraceReturns:
    """log_rhos = log pi(a_t|x_t) - log mu(a_t|x_t); discounts d_t; values V(x_t), [T, B];
    bootstrap_value V(x_T), [B]."""
    rhos = torch.exp(log_rhos)
    clipped_rhos = torch.clamp(rhos, max=rho_clip)
    cs = lam * torch.clamp(rhos, max=c_clip)
    next_values = torch.cat([values[1:], bootstrap_value[None]], 0)
    gd = gamma * discounts
    deltas = clipped_rhos * (rewards + gd * next_values - values)
    acc = torch.zeros_like(bootstrap_value)
    corrections = []
    for t in range(values.shape[0] - 1, -1, -1):
        acc = deltas[t] + gd[t] * cs[t] * acc
        corrections.append(acc)
    vs = values + torch.stack(corrections[::-1])
    next_vs = torch.cat([vs[1:], bootstrap_value[None]], 0)
    return VTraceReturns(vs=vs, pg_advantages=clipped_rhos * (rewards + gd * next_vs - values))


def vtrace_losses(logits: torch.Tensor, actions: torch.Tensor, values: torch.Tensor, returns: VTraceReturns,
                  new_action: torch.Tensor, mask: torch.Tensor, entropy_cost: float,
                  baseline_cost: float = 0.5) -> dict[str, torch.Tensor]:
    """logits [T, B, A]; actions [T, B] (long); new_action, mask [T, B] in {0, 1}."""
    log_probs = torch.log_softmax(logits, -1)
    taken = log_probs.gather(-1, actions[..., None]).squeeze(-1)
    pg_mask = new_action * mask
    n_pg = pg_mask.sum().clamp(min=1.0)
    n = mask.sum().clamp(min=1.0)
    pg_loss = -(taken * returns.pg_advantages * pg_mask).sum() / n_pg
    entropy = -(log_probs.exp() * log_probs).sum(-1)
    entropy_loss = -(entropy * pg_mask).sum() / n_pg
    value_loss = 0.5 * (((returns.vs - values) ** 2) * mask).sum() / n
    total = pg_loss + baseline_cost * value_loss + entropy_cost * entropy_loss
    return {"loss": total, "pg_loss": pg_loss, "value_loss": value_loss, "entropy": (entropy * pg_mask).sum() / n_pg}
