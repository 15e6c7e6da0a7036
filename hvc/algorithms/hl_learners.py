"""High-level learners (Sec. 2.3, Appendix A.3-A.5) on replayed unrolls of the LSTM agent.

`vtrace_update` for the discrete controllers (fragments, switching): value loss every step,
policy gradient and entropy only where a new action was sampled. `ContinuousLearner`,
SVG(0) + Retrace with a target copy of the agent, for steerable and end_to_end.
`QueryLearner`, Wolpertinger-style, for query. Each takes a batch from
`hvc.runtime.hl_train.Unrolls.sample` (time-major tensors plus the LSTM state at the
unroll's start) and does one optimiser step.
"""
from __future__ import annotations

import copy

import numpy as np
import torch

from hvc.agents.network import HighLevelAgent
from hvc.algorithms.optim import clipped_step
from hvc.algorithms.retrace import retrace_targets
from hvc.algorithms.vtrace import vtrace_losses, vtrace_targets


def pack_state(state: tuple[torch.Tensor, ...], hidden: int) -> np.ndarray:
    """The agent's LSTM states as one [batch, 4, hidden] array for the replay (split_state undoes it)."""
    out = np.zeros((state[0].shape[1], 4, hidden), np.float32)
    for k, s in enumerate(state):
        out[:, k, :s.shape[-1]] = s[0].cpu().numpy()
    return out


def split_state(agent: HighLevelAgent, packed: torch.Tensor) -> tuple[torch.Tensor, ...]:
    spec = agent.spec
    sizes = (spec.lstm_size, spec.lstm_size, spec.policy_lstm, spec.policy_lstm)
    return tuple(packed[:, k, :n][None].contiguous() for k, n in enumerate(sizes))


def vtrace_update(agent, optimizer, b, gamma: float, entropy_cost: float, algorithm) -> dict[str, float]:
    """One V-trace actor-critic step (IMPALA) for a discrete controller; held steps, where the
    controller chose nothing, have rho = 1 and no policy-gradient term."""
    state = split_state(agent, b["state"])
    logits, h, _ = agent(b["proprio"], b["task"], b["prev_reward"], b["prev_action"], state,
                         image=b.get("image"), done=b["first"])
    values = agent.values(h)
    log_pi = torch.log_softmax(logits[:-1], -1).gather(-1, b["action"][..., None]).squeeze(-1)
    log_rhos = (log_pi.detach() - b["log_mu"]) * b["new_action"]  # held steps chose nothing: rho = 1
    returns = vtrace_targets(log_rhos, b["discount"], b["reward"], values[:-1].detach(), values[-1].detach(), gamma,
                             float(algorithm.rho_clip), float(algorithm.c_clip))
    losses = vtrace_losses(logits[:-1], b["action"], values[:-1], returns, b["new_action"],
                           torch.ones_like(b["reward"]), entropy_cost)
    clipped_step(optimizer, losses["loss"], agent.parameters())
    return {k: float(v.detach()) for k, v in losses.items()}


SIGMA_CLIP = (0.1, 1.0)  # the Gaussian policies' sigma bounds when a controller config names none
MEAN_RAW_LIMIT = 2.0  # |pre-tanh mean| beyond which the policy loss pulls it back (tanh(2) = 0.96)


class ContinuousLearner:
    """SVG(0) + Retrace for continuous high-level actions (steerable, end_to_end), Appendix A.3/A.5.

    The policy head gives a Gaussian (tanh-bounded mean, sigma clipped); sampled actions are
    clipped to the controller's range. Q(h, a) is an MLP on the LSTM core's output,
    regressed on Retrace targets from a target copy of the whole agent (refreshed every
    `target_update_period` learner steps); the policy maximises Q_target(h, a(xi)) through
    the reparameterised sample (the paper's SVG(0), as at the low level: the target agent's
    Q on its own features, so only the policy moves) at steps where a new action was taken,
    with an entropy bonus.
    """

    def __init__(self, agent: HighLevelAgent, algorithm, controller, space):
        self.agent = agent
        self.target = copy.deepcopy(agent).requires_grad_(False)
        self.low, self.high = float(space.low), float(space.high)
        if controller.get("steering_range") is not None:
            self.low, self.high = (float(v) for v in controller.steering_range)
        self.sigma_clip = tuple(controller.get("sigma_clip", SIGMA_CLIP))
        self.entropy_cost = float(algorithm.get("entropy_cost", 1e-5))
        self.lam = float(algorithm.get("retrace_lambda", 1.0))
        self.period = int(algorithm.get("target_update_period", 100))
        self.value_samples = int(algorithm.get("value_samples", 4))
        self.kl_cost = float(algorithm.get("kl_cost", 0.0))
        self.steps = 0

    def distribution(self, agent, policy_out):
        mean, sigma = agent.gaussian(policy_out, self.low, self.high, self.sigma_clip)
        return torch.distributions.Normal(mean, sigma)

    def replay_unrolls(self, b: dict) -> tuple[torch.Tensor, ...]:
        """The online agent (with gradients) and the target agent (without) over the sampled
        unrolls from their stored LSTM states: (out, h, target out, target h)."""
        state = split_state(self.agent, b["state"])
        self.target.normalizer.load_state_dict(self.agent.normalizer.state_dict())  # one input scale for both
        args = (b["proprio"], b["task"], b["prev_reward"], b["prev_action"])
        out, h, _ = self.agent(*args, state, image=b.get("image"), done=b["first"])
        with torch.no_grad():
            t_out, t_h, _ = self.target(*args, state, image=b.get("image"), done=b["first"])
        return out, h, t_out, t_h

    def sample(self, policy_out: torch.Tensor) -> tuple[np.ndarray, np.ndarray]:
        """(the raw Gaussian sample, its log density). The env gets `clip(raw)`; replay keeps
        the raw sample, whose density is exact: a clipped value has a probability mass at the
        bound, and a ratio of densities there is not the ratio of probabilities Retrace needs
        (pi = N(0.9, 0.2) against mu = N(0.9, 0.9) at a clip to 1: 4.0 against 0.68)."""
        dist = self.distribution(self.agent, policy_out)
        action = dist.sample()
        return action.cpu().numpy().astype(np.float32), dist.log_prob(action).sum(-1).cpu().numpy()

    def clip(self, action):
        """What the env and Q see of a raw sample (numpy or torch)."""
        if isinstance(action, np.ndarray):
            return np.clip(action, self.low, self.high)
        return torch.clamp(action, self.low, self.high)

    def update(self, optimizer, b: dict, gamma: float) -> dict[str, float]:
        out, h, t_out, t_h = self.replay_unrolls(b)
        with torch.no_grad():
            t_dist = self.distribution(self.target, t_out)
            q_taken = self.target.values(t_h[:-1], self.clip(b["action"]))
            v_next = torch.stack([self.target.values(t_h[1:], self.clip(t_dist.sample()[1:]))
                                  for _ in range(self.value_samples)]).mean(0)
            log_pi = self.distribution(self.target, t_out[:-1]).log_prob(b["action"]).sum(-1)  # raw: exact
            # held steps chose nothing: their trace is lambda (ratio 1)
            ratio_log = (log_pi - b["log_mu"]) * b["new_action"]
            traces = self.lam * torch.exp(torch.clamp(ratio_log, max=0.0))
            targets = retrace_targets(b["reward"], b["discount"], q_taken, v_next, traces, gamma)
        q = self.agent.values(h[:-1], self.clip(b["action"]))
        critic_loss = 0.5 * ((q - targets) ** 2).mean()
        return self.step(optimizer, critic_loss, out, b, q, t_out, t_h)

    def step(self, optimizer, critic_loss: torch.Tensor, out: torch.Tensor, b: dict, q: torch.Tensor,
             target_out: torch.Tensor, target_h: torch.Tensor) -> dict[str, float]:
        """Adds the SVG(0) policy loss through Q_target to `critic_loss` (with eta KL(pi || pi_target)
        on the target agent's policy, as at the low level), takes one optimiser step and refreshes
        the target agent on schedule."""
        dist = self.distribution(self.agent, out[:-1])
        # Q is only ever trained on actions inside the range (actors clip them): a sample outside
        # it is clipped too, so Q's extrapolation cannot drag the mean past the bounds
        action = self.clip(dist.rsample())
        # SVG(0) through Q_target: the target agent holds no gradients, so they reach the policy
        # only through the action
        q_pi = self.target.values(target_h[:-1], action)
        weight = b["new_action"] / b["new_action"].sum().clamp(min=1.0)
        entropy = dist.entropy().sum(-1)
        # keeps the mean's tanh out of saturation, where its gradient vanishes and a policy
        # pinned to a bound could never follow a critic that later changes its mind
        mean_raw = out[:-1].chunk(2, -1)[0]
        saturation = (torch.relu(mean_raw.abs() - MEAN_RAW_LIMIT) ** 2).sum(-1)
        kl = torch.zeros_like(entropy)
        if self.kl_cost > 0:
            kl = torch.distributions.kl_divergence(dist, self.distribution(self.target, target_out[:-1])).sum(-1)
        policy_loss = -((q_pi + self.entropy_cost * entropy - saturation - self.kl_cost * kl) * weight).sum()
        clipped_step(optimizer, critic_loss + policy_loss, self.agent.parameters())
        self.steps += 1
        if self.steps % self.period == 0:
            self.target.load_state_dict(self.agent.state_dict())
        return {"critic_loss": critic_loss.detach().item(), "policy_loss": policy_loss.detach().item(),
                "q": float(q.detach().mean()), "entropy": float((entropy.detach() * weight).sum()),
                "kl": float((kl.detach() * weight).sum())}


class QueryLearner(ContinuousLearner):
    """Wolpertinger-style query selection (Appendix A.4).

    The policy emits a Gaussian query in fragment-key space; the k nearest keys are scored
    by Q(h, key) and one is chosen with p ~ exp(Q / T). Q is trained with 1-step targets
    r + gamma E_{a ~ pi(.|h')} Q_target(h', a) on both the query and the selected key of each
    replayed step (one Q for both kinds of action, as the paper found most stable); the
    policy follows SVG(0) through Q at steps where a new fragment was chosen.
    """

    def __init__(self, agent, algorithm, controller, space, query_controller):
        super().__init__(agent, algorithm, controller, space)
        self.selector = query_controller
        self.keys = torch.from_numpy(query_controller.keys).to(next(agent.parameters()).device)
        self.temperature = float(controller.get("temperature", 1.0))
        self.rng = np.random.default_rng(0)

    @torch.no_grad()
    def act(self, policy_out: torch.Tensor, h: torch.Tensor):
        """(fragment index to run, query, selected key, log mu of the query) per env."""
        dist = self.distribution(self.agent, policy_out)
        queries = torch.clamp(dist.sample(), self.low, self.high)
        log_mu = dist.log_prob(queries).sum(-1).cpu().numpy()
        host_queries = queries.cpu().numpy().astype(np.float32)
        indices = []
        for e in range(queries.shape[0]):
            candidates = self.selector.nearest(host_queries[e])
            keys = self.keys[candidates]
            q = self.agent.values(h[e].expand(len(candidates), -1), keys)
            p = torch.softmax(q / self.temperature, 0).cpu().numpy().astype(np.float64)
            indices.append(int(candidates[self.rng.choice(len(candidates), p=p / p.sum())]))
        indices = np.asarray(indices)
        return indices, host_queries, self.keys[indices].cpu().numpy(), log_mu

    def update(self, optimizer, b: dict, gamma: float) -> dict[str, float]:
        out, h, t_out, t_h = self.replay_unrolls(b)
        with torch.no_grad():
            t_dist = self.distribution(self.target, t_out[1:])
            v_next = torch.stack([self.target.values(t_h[1:], torch.clamp(t_dist.sample(), self.low, self.high))
                                  for _ in range(self.value_samples)]).mean(0)
            targets = b["reward"] + gamma * b["discount"] * v_next
        q_query = self.agent.values(h[:-1], b["query"])
        q_selected = self.agent.values(h[:-1], b["action"])
        critic_loss = 0.5 * (((q_query - targets) ** 2).mean() + ((q_selected - targets) ** 2).mean())
        return self.step(optimizer, critic_loss, out, b, q_selected, t_out, t_h)
