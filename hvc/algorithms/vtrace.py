"""V-trace actor-critic (Espeholt et al. 2018, IMPALA) for the discrete controllers.

Targets, time-major [T, B]:
  rho_t = min(rho_bar, pi/mu), c_t = lambda min(c_bar, pi/mu)
  delta_t = rho_t (r_t + gamma d_t V(x_{t+1}) - V(x_t))
  v_s = V(x_s) + delta_s + gamma d_s c_s (v_{s+1} - V(x_{s+1})),  v_T = V(x_T) (bootstrap)
Policy-gradient advantage: rho_t (r_t + gamma d_t v_{t+1} - V(x_t)).
As in the paper, the value loss applies at every step but the policy-gradient and
entropy terms only where a new high-level action was sampled (`new_action` mask); with
an N-step unroll the bootstrap is from the unroll's last state. `VTraceLearner` is the
high-level LSTM agent's learner for the discrete controllers (fragments, switching).
"""
from __future__ import annotations

from dataclasses import dataclass

import torch

from hvc.agents.network import HighLevelAgent
from hvc.algorithms.learner import Acted, Learner, restore_optimizer
from hvc.algorithms.optim import clipped_step
from hvc.schema import VTraceConfig, typed


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


class VTraceLearner(Learner):
    """V-trace actor-critic on replayed unrolls of the LSTM agent (a categorical policy and V(h)).
    Held steps, where the controller chose nothing, have rho = 1 and no policy-gradient term."""

    def __init__(self, agent: HighLevelAgent, gamma: float, hp: VTraceConfig = VTraceConfig()):
        self.agent, self.gamma, self.hp = agent, float(gamma), hp
        self.optimizer = torch.optim.Adam(agent.parameters(), lr=float(hp.learning_rate))
        self.steps = 0

    @classmethod
    def from_config(cls, agent: HighLevelAgent, cfg, space=None, controller=None):
        return cls(agent, float(cfg.task.agent.gamma), typed(VTraceConfig, cfg.algorithm))

    @torch.no_grad()
    def act(self, policy_out: torch.Tensor, h: torch.Tensor) -> Acted:
        dist = torch.distributions.Categorical(logits=policy_out)
        action = dist.sample()
        chosen = action.cpu().numpy()
        return Acted(send=chosen, action=chosen, log_mu=dist.log_prob(action).cpu().numpy(), seen=chosen)

    def update(self, b: dict) -> dict[str, float]:
        agent = self.agent
        logits, h, _ = agent(b["proprio"], b["task"], b["prev_reward"], b["prev_action"],
                             agent.unpack_state(b["state"]), image=b.get("image"), done=b["first"])
        values = agent.values(h)
        log_pi = torch.log_softmax(logits[:-1], -1).gather(-1, b["action"][..., None]).squeeze(-1)
        log_rhos = (log_pi.detach() - b["log_mu"]) * b["new_action"]  # held steps chose nothing: rho = 1
        returns = vtrace_targets(log_rhos, b["discount"], b["reward"], values[:-1].detach(), values[-1].detach(),
                                 self.gamma, float(self.hp.rho_clip), float(self.hp.c_clip))
        losses = vtrace_losses(logits[:-1], b["action"], values[:-1], returns, b["new_action"],
                               torch.ones_like(b["reward"]), float(self.hp.entropy_cost))
        clipped_step(self.optimizer, losses["loss"], agent.parameters())
        self.steps += 1
        return {k: float(v.detach()) for k, v in losses.items()}

    def state_dict(self) -> dict:
        """The high-level checkpoint's learner part (its keys sit at the checkpoint's top level)."""
        return {"agent": self.agent.state_dict(), "optimizer": self.optimizer.state_dict(), "learner_steps": self.steps}

    def load_state_dict(self, state: dict) -> None:
        self.agent.load_state_dict(state["agent"])
        restore_optimizer(self.optimizer, state["optimizer"], self.hp.learning_rate)
        self.steps = int(state.get("learner_steps", state.get("counters", {}).get("updates", 0)))
