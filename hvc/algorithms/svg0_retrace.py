"""SVG(0) policy updates through a Retrace-trained Q, at both levels (Sec. 2.1; Appendix A.3, A.5).

Critic: Q(s_t, a_t) regressed on Retrace targets computed with target networks, traces
c = lambda min(1, pi_target / mu) from the behaviour log-probabilities stored in replay.
Actor (SVG(0)): maximise E_{a ~ pi(.|s)} Q_target(s, a) by the reparameterised sample
a = mu(s) + sigma * xi, minus eta KL(pi || pi_target), which keeps each update
conservative. With the low level's fixed sigma the KL is ||mu - mu_target||^2 / (2 sigma^2).
Target networks are hard copies refreshed every `target_update_period` learner steps.
One policy loss (`svg0_policy_loss`) for both levels: `SVG0Retrace`, the low level's MLP
policy and critic on time-major batches (obs [T+1, B], actions/rewards/discounts/log_mu/mask
[T, B]), and `RecurrentSVG0Retrace`, the high-level LSTM agent's for continuous controllers
(steerable, end to end), replaying unrolls from their stored LSTM state.
"""
from __future__ import annotations

import copy
from dataclasses import dataclass
from typing import Mapping

import torch

import numpy as np

from hvc.agents.mlp import GaussianPolicy, QNetwork, gaussian_log_prob
from hvc.agents.network import HighLevelAgent
from hvc.algorithms.learner import Acted, Learner, refresh_on_schedule, restore_optimizer
from hvc.algorithms.optim import clipped_step
from hvc.algorithms.retrace import retrace_targets, truncated_traces
from hvc.errors import NonFiniteLoss
from hvc.schema import GaussianControllerConfig, SVG0Config, SVG0RetraceConfig, typed


@dataclass
class Batch:
    obs: torch.Tensor        # [T+1, B, obs]
    actions: torch.Tensor    # [T, B, act]
    rewards: torch.Tensor    # [T, B]
    discounts: torch.Tensor  # [T, B]  0 after a failure
    log_mu: torch.Tensor     # [T, B]  behaviour log-prob of the action
    mask: torch.Tensor       # [T, B]  0 on padding after an episode ended


def svg0_policy_loss(q_pi: torch.Tensor, weight: torch.Tensor, kl: torch.Tensor, kl_cost: float,
                     bonus: torch.Tensor | float = 0.0) -> torch.Tensor:
    """SVG(0): -E[Q_target(s, a(xi)) - eta KL(pi || pi_target) (+ bonus)] over the weighted steps.
    `q_pi` is Q_target at the reparameterised sample a(xi) = mean + sigma xi: the gradient reaches
    the policy only through the action, since the target networks hold no gradients."""
    return -((q_pi - kl_cost * kl + bonus) * weight).sum()


def kl_fixed_sigma(mean: torch.Tensor, target_mean: torch.Tensor, sigma: float) -> torch.Tensor:
    """KL(N(mean, sigma^2) || N(target_mean, sigma^2)) summed over action dimensions."""
    return ((mean - target_mean) ** 2).sum(-1) / (2 * sigma ** 2)


class SVG0Retrace(Learner):
    """The low level's learner: a Gaussian MLP policy of fixed sigma and an MLP Q."""

    def __init__(self, policy: GaussianPolicy, critic: QNetwork, cfg: Mapping):
        self.policy, self.critic = policy, critic
        self.target_policy = copy.deepcopy(policy).requires_grad_(False)
        self.target_critic = copy.deepcopy(critic).requires_grad_(False)
        self.gamma = float(cfg["gamma"])
        self.retrace_lambda = float(cfg["retrace_lambda"])
        self.kl_cost = float(cfg["kl_cost"])
        self.target_update_period = int(cfg["target_update_period"])
        self.value_samples = int(cfg["value_samples"])
        self.kickstart_cost = float(cfg.get("kickstart_cost", 0.0))
        self.policy_opt = torch.optim.Adam(policy.parameters(), lr=float(cfg["policy_lr"]))
        self.critic_opt = torch.optim.Adam(critic.parameters(), lr=float(cfg["critic_lr"]))
        self.steps = 0

    def act(self, mean: np.ndarray, rng: np.random.Generator) -> tuple[np.ndarray, float]:
        """(a sample of N(mean, sigma^2), its log density) for one step; `mean` comes from the
        actor's numpy copy of the policy (hvc.agents.mlp.NumpyPolicy)."""
        sigma = self.policy.sigma
        noise = rng.standard_normal(mean.shape).astype(np.float32)
        log_mu = -0.5 * float(noise @ noise) - mean.size * (np.log(sigma) + 0.5 * np.log(2 * np.pi))
        return mean + sigma * noise, log_mu

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

    def update(self, b: Batch, train_policy: bool = True,
               teacher: tuple[torch.Tensor, torch.Tensor] | None = None) -> dict[str, float]:
        """One critic step and, unless `train_policy` is False (a fresh critic learning the
        values of a warm-started policy before it may steer it), one policy step. With
        `teacher` = (observations, the teachers' actions there), the policy loss adds
        kickstart_cost KL(pi || teacher) at those states (kickstarting, Schmitt et al. 2018;
        the teachers' Gaussians share pi's fixed sigma), which keeps what the teachers know
        while the RL reward asks for more."""
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
        policy_loss = svg0_policy_loss(q_pi, weight, kl, self.kl_cost)
        info = {}
        if teacher is not None and train_policy:  # a critic warming up has no policy step to add it to
            teacher_kl = kl_fixed_sigma(self.policy.mean(teacher[0]), teacher[1], self.policy.sigma).mean()
            policy_loss = policy_loss + self.kickstart_cost * teacher_kl
            info["teacher_kl"] = float(teacher_kl.detach())
        if not (torch.isfinite(critic_loss) and torch.isfinite(policy_loss)):  # before either network moves
            raise NonFiniteLoss(f"non-finite loss: critic {float(critic_loss.detach())}, policy {float(policy_loss.detach())}")
        clipped_step(self.critic_opt, critic_loss, self.critic.parameters())
        if train_policy:
            clipped_step(self.policy_opt, policy_loss, self.policy.parameters())

        refresh_on_schedule(self, self.target_update_period, self.sync_targets)
        return {"critic_loss": critic_loss.detach().item(), "policy_loss": policy_loss.detach().item(), "kl": float(
            (kl.detach() * weight).sum()), "q": float((q.detach() * weight).sum()), **info}

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
            restore_optimizer(opt, state[key], opt.param_groups[0]["lr"])
        self.steps = int(state["steps"])


MEAN_RAW_LIMIT = 2.0  # |pre-tanh mean| beyond which the policy loss pulls it back (tanh(2) = 0.96)


class RecurrentSVG0Retrace(Learner):
    """SVG(0) + Retrace for the high-level LSTM agent's continuous actions (steerable, end to end).

    The policy head gives a Gaussian (tanh-bounded mean, sigma bounded to `sigma_clip`);
    sampled actions are clipped to [low, high] for the env. Q(h, a) is an MLP on the LSTM
    core's output, regressed on Retrace targets from a target copy of the whole agent; the
    policy maximises Q_target(h, a(xi)) (svg0_policy_loss, the target agent's Q on its own
    features) at steps where a new action was taken, with an entropy bonus and eta KL(pi ||
    pi_target). Batches: time-major tensors plus the LSTM state at the unroll's start.
    """

    schema = SVG0RetraceConfig

    def __init__(self, agent: HighLevelAgent, gamma: float, low: float, high: float, sigma_clip: tuple[float, float],
                 hp: SVG0Config = SVG0RetraceConfig()):
        self.agent, self.gamma, self.hp = agent, float(gamma), hp
        self.target = copy.deepcopy(agent).requires_grad_(False)
        self.optimizer = torch.optim.Adam(agent.parameters(), lr=float(hp.learning_rate))
        self.low, self.high = float(low), float(high)
        self.sigma_clip = tuple(float(v) for v in sigma_clip)
        self.entropy_cost, self.kl_cost = float(hp.entropy_cost), float(hp.kl_cost)
        self.period, self.value_samples = int(hp.target_update_period), int(hp.value_samples)
        self.steps = 0

    @classmethod
    def from_config(cls, agent: HighLevelAgent, cfg, space, controller=None, **extra):
        """From a job's config: gamma from task.agent, the action range from the controller's
        `steering_range` or the action space, sigma bounds from the controller, the rest from
        `algorithm` (hvc.schema)."""
        ctrl = cfg.controller
        low, high = (float(v) for v in ctrl.get("steering_range") or (space.low, space.high))
        return cls(agent, float(cfg.task.agent.gamma), low, high, typed(GaussianControllerConfig, ctrl).sigma_clip,
                   hp=typed(cls.schema, cfg.algorithm), **extra)

    def distribution(self, agent: HighLevelAgent, policy_out: torch.Tensor) -> torch.distributions.Normal:
        mean, sigma = agent.gaussian(policy_out, self.low, self.high, self.sigma_clip)
        return torch.distributions.Normal(mean, sigma)

    def clip(self, action):
        """What the env and Q see of a raw sample (numpy or torch)."""
        if isinstance(action, np.ndarray):
            return np.clip(action, self.low, self.high)
        return torch.clamp(action, self.low, self.high)

    @torch.no_grad()
    def act(self, policy_out: torch.Tensor, h: torch.Tensor) -> Acted:
        """The env gets `clip(raw)`; replay keeps the raw sample, whose density is exact: a
        clipped value has a probability mass at the bound, and a ratio of densities there is not
        the ratio of probabilities Retrace needs. The agent's next input is what the env got."""
        dist = self.distribution(self.agent, policy_out)
        action = dist.sample()
        raw = action.cpu().numpy().astype(np.float32)
        sent = self.clip(raw)
        return Acted(send=sent, action=raw, log_mu=dist.log_prob(action).sum(-1).cpu().numpy(), seen=sent)

    def replay_unrolls(self, b: dict) -> tuple[torch.Tensor, ...]:
        """The online agent (with gradients) and the target agent (without) over the sampled
        unrolls from their stored LSTM states: (out, h, target out, target h)."""
        state = self.agent.unpack_state(b["state"])
        self.target.normalizer.load_state_dict(self.agent.normalizer.state_dict())  # one input scale for both
        args = (b["proprio"], b["task"], b["prev_reward"], b["prev_action"])
        out, h, _ = self.agent(*args, state, image=b.get("image"), done=b["first"])
        with torch.no_grad():
            t_out, t_h, _ = self.target(*args, state, image=b.get("image"), done=b["first"])
        return out, h, t_out, t_h

    def update(self, b: dict) -> dict[str, float]:
        out, h, t_out, t_h = self.replay_unrolls(b)
        with torch.no_grad():
            t_dist = self.distribution(self.target, t_out)
            q_taken = self.target.values(t_h[:-1], self.clip(b["action"]))
            v_next = torch.stack([self.target.values(t_h[1:], self.clip(t_dist.sample()[1:]))
                                  for _ in range(self.value_samples)]).mean(0)
            log_pi = self.distribution(self.target, t_out[:-1]).log_prob(b["action"]).sum(-1)  # raw: exact
            # held steps chose nothing: their trace is lambda (ratio 1)
            traces = truncated_traces(log_pi, b["log_mu"], float(self.hp.retrace_lambda), b["new_action"])
            targets = retrace_targets(b["reward"], b["discount"], q_taken, v_next, traces, self.gamma)
        q = self.agent.values(h[:-1], self.clip(b["action"]))
        critic_loss = 0.5 * ((q - targets) ** 2).mean()
        return self.step(critic_loss, out, b, q, t_out, t_h)

    def step(self, critic_loss: torch.Tensor, out: torch.Tensor, b: dict, q: torch.Tensor,
             target_out: torch.Tensor, target_h: torch.Tensor) -> dict[str, float]:
        """Adds the SVG(0) policy loss to `critic_loss`, takes one optimiser step and refreshes
        the target agent on schedule."""
        dist = self.distribution(self.agent, out[:-1])
        # Q is only ever trained on actions inside the range (actors clip them): a sample outside
        # it is clipped too, so Q's extrapolation cannot drag the mean past the bounds
        q_pi = self.target.values(target_h[:-1], self.clip(dist.rsample()))
        weight = b["new_action"] / b["new_action"].sum().clamp(min=1.0)
        entropy = dist.entropy().sum(-1)
        # keeps the mean's tanh out of saturation, where its gradient vanishes and a policy
        # pinned to a bound could never follow a critic that later changes its mind
        mean_raw = out[:-1].chunk(2, -1)[0]
        saturation = (torch.relu(mean_raw.abs() - MEAN_RAW_LIMIT) ** 2).sum(-1)
        # reported whatever its cost, so a run without the KL term still shows how far pi strays
        kl = torch.distributions.kl_divergence(dist, self.distribution(self.target, target_out[:-1])).sum(-1)
        policy_loss = svg0_policy_loss(q_pi, weight, kl, self.kl_cost, self.entropy_cost * entropy - saturation)
        clipped_step(self.optimizer, critic_loss + policy_loss, self.agent.parameters())
        refresh_on_schedule(self, self.period, lambda: self.target.load_state_dict(self.agent.state_dict()))
        return {"critic_loss": critic_loss.detach().item(), "policy_loss": policy_loss.detach().item(),
                "q": float(q.detach().mean()), "entropy": float((entropy.detach() * weight).sum()),
                "kl": float((kl.detach() * weight).sum())}

    def state_dict(self) -> dict:
        """The high-level checkpoint's learner part (its keys sit at the checkpoint's top level)."""
        return {"agent": self.agent.state_dict(), "optimizer": self.optimizer.state_dict(),
                "target_agent": self.target.state_dict(), "learner_steps": self.steps}

    def load_state_dict(self, state: dict) -> None:
        self.agent.load_state_dict(state["agent"])
        restore_optimizer(self.optimizer, state["optimizer"], self.hp.learning_rate)
        self.target.load_state_dict(state["target_agent"])
        self.steps = int(state.get("learner_steps", state.get("counters", {}).get("updates", 0)))
