"""SVG(0) policy updates through a Retrace-trained Q (Sec. 2.1, low-level RL; Appendix A).

Critic: Q(s_t, a_t) regressed on Retrace targets computed with target networks, traces
c = lambda min(1, pi_target / mu) from the behaviour log-probabilities stored in replay.
Actor (SVG(0)): maximise E_{a ~ pi(.|s)} Q_target(s, a) by the reparameterised sample
a = mu(s) + sigma * xi, minus eta KL(pi || pi_target), which keeps each update
conservative. With the low level's fixed sigma the KL is ||mu - mu_target||^2 / (2 sigma^2).
Target networks are hard copies refreshed every `target_update_period` learner steps.
Batches are time-major sequences: obs [T+1, B], actions/rewards/discounts/log_mu/mask [T, B].
"""
from __future__ import annotations

import copy
from dataclasses import dataclass
from typing import Mapping

import torch

from hvc.agents.mlp import GaussianPolicy, QNetwork, gaussian_log_prob
from hvc.algorithms.optim import clipped_step
from hvc.errors import NonFiniteLoss
from hvc.algorithms.retrace import retrace_targets, truncated_traces


@dataclass
class Batch:
    obs: torch.Tensor        # [T+1, B, obs]
    actions: torch.Tensor    # [T, B, act]
    rewards: torch.Tensor    # [T, B]
    discounts: torch.Tensor  # [T, B]  0 after a failure
    log_mu: torch.Tensor     # [T, B]  behaviour log-prob of the action
    mask: torch.Tensor       # [T, B]  0 on padding after an episode ended


def kl_fixed_sigma(mean: torch.Tensor, target_mean: torch.Tensor, sigma: float) -> torch.Tensor:
    """KL(N(mean, sigma^2) || N(target_mean, sigma^2)) summed over action dimensions."""
    return ((mean - target_mean) ** 2).sum(-1) / (2 * sigma ** 2)


class SVG0Retrace:
    def __init__(self, policy: GaussianPolicy, critic: QNetwork, cfg: Mapping):
        self.policy, self.critic = policy, critic
        self.target_policy = copy.deepcopy(policy).requires_grad_(False)
        self.target_critic = copy.deepcopy(critic).requires_grad_(False)
        self.gamma = float(cfg["gamma"])
        self.retrace_lambda = float(cfg.get("retrace_lambda", 1.0))
        self.kl_cost = float(cfg["kl_cost"])
        self.target_update_period = int(cfg["target_update_period"])
        self.value_samples = int(cfg.get("value_samples", 4))
        self.policy_opt = torch.optim.Adam(policy.parameters(), lr=float(cfg["policy_lr"]))
        self.critic_opt = torch.optim.Adam(critic.parameters(), lr=float(cfg["critic_lr"]))
        self.steps = 0

    def sync_targets(self) -> None:
        self.target_policy.load_state_dict(self.policy.state_dict())
        self.target_critic.load_state_dict(self.critic.state_dict())

    @torch.no_grad()
    def critic_targets(self, b: Batch, target_mean: torch.Tensor | None = None) -> torch.Tensor:
        """Retrace targets; `target_mean` = target_policy.mean(b.obs) when the caller has it."""
        sigma = self.policy.sigma
        obs, next_obs = b.obs[:-1], b.obs[1:]
        if target_mean is None:
            target_mean = self.target_policy.mean(b.obs)
        next_mean = target_mean[1:]
        q_taken = self.target_critic(obs, b.actions)
        # the value samples in one critic call (the learner's cost is mostly per-call overhead)
        noise = torch.stack([torch.randn_like(next_mean) for _ in range(self.value_samples)])
        samples = next_mean + sigma * noise
        v_next = self.target_critic(next_obs.expand(self.value_samples, *next_obs.shape), samples).mean(0)
        log_pi = gaussian_log_prob(b.actions, target_mean[:-1], sigma)
        traces = truncated_traces(log_pi, b.log_mu, self.retrace_lambda) * b.mask
        return retrace_targets(b.rewards, b.discounts, q_taken, v_next, traces, self.gamma)

    def update(self, b: Batch, train_policy: bool = True) -> dict[str, float]:
        """One critic step and, unless `train_policy` is False (a fresh critic learning the
        values of a warm-started policy before it may steer it), one policy step."""
        with torch.no_grad():
            target_mean_all = self.target_policy.mean(b.obs)
        targets = self.critic_targets(b, target_mean_all)
        obs = b.obs[:-1]
        weight = b.mask / b.mask.sum().clamp(min=1.0)
        q = self.critic(obs, b.actions)
        critic_loss = 0.5 * ((q - targets) ** 2 * weight).sum()

        mean = self.policy.mean(obs)
        action = mean + self.policy.sigma * torch.randn_like(mean)
        q_pi = self.target_critic(obs, action)  # the target critic: the critic's step below does not change it
        kl = kl_fixed_sigma(mean, target_mean_all[:-1], self.policy.sigma)
        policy_loss = ((-q_pi + self.kl_cost * kl) * weight).sum()
        if not (torch.isfinite(critic_loss) and torch.isfinite(policy_loss)):  # before either network moves
            raise NonFiniteLoss(f"non-finite loss: critic {float(critic_loss)}, policy {float(policy_loss)}")
        clipped_step(self.critic_opt, critic_loss, self.critic.parameters())
        if train_policy:
            clipped_step(self.policy_opt, policy_loss, self.policy.parameters())

        self.steps += 1
        if self.steps % self.target_update_period == 0:
            self.sync_targets()
        return {"critic_loss": critic_loss.detach().item(), "policy_loss": policy_loss.detach().item(), "kl": float(
            (kl.detach() * weight).sum()), "q": float((q.detach() * weight).sum())}

    def state_dict(self) -> dict:
        return {"policy": self.policy.state_dict(), "critic": self.critic.state_dict(),
                "target_policy": self.target_policy.state_dict(), "target_critic": self.target_critic.state_dict(),
                "policy_opt": self.policy_opt.state_dict(), "critic_opt": self.critic_opt.state_dict(),
                "steps": self.steps}

    def load_state_dict(self, state: dict) -> None:
        self.policy.load_state_dict(state["policy"])
        self.critic.load_state_dict(state["critic"])
        self.target_policy.load_state_dict(state["target_policy"])
        self.target_critic.load_state_dict(state["target_critic"])
        for opt, key in ((self.policy_opt, "policy_opt"), (self.critic_opt, "critic_opt")):
            configured = [group["lr"] for group in opt.param_groups]
            opt.load_state_dict(state[key])
            for group, lr in zip(opt.param_groups, configured):  # torch would restore the saved rate and
                group["lr"] = lr                                 # silently ignore a changed *_lr on resume
        self.steps = int(state["steps"])
