"""Retrace targets against the published sum form, computed independently."""
import numpy as np
import pytest
import torch

from hvc.algorithms.retrace import retrace_targets, truncated_traces


def _sum_form(r, d, q, v_next, c, gamma):
    """Q_ret(t) = Q(t) + sum_{k>=t} gamma^{k-t} (prod_{i=t+1..k} d_{i-1} c_i) delta_k,
    delta_k = r_k + gamma d_k V(s_{k+1}) - Q(s_k, a_k)."""
    T, B = r.shape
    out = np.zeros((T, B))
    for b in range(B):
        for t in range(T):
            total, weight = q[t, b], 1.0
            for k in range(t, T):
                if k > t:
                    weight *= gamma * d[k - 1, b] * c[k, b]
                delta = r[k, b] + gamma * d[k, b] * v_next[k, b] - q[k, b]
                total += weight * delta
            out[t, b] = total
    return out


def test_retrace_matches_the_sum_form_on_random_inputs():
    rng = np.random.default_rng(0)
    T, B, gamma = 7, 5, 0.95
    r, q, v = rng.normal(size=(T, B)), rng.normal(size=(T, B)), rng.normal(size=(T, B))
    d = (rng.uniform(size=(T, B)) > 0.2).astype(float)
    log_pi, log_mu = rng.normal(size=(T, B)), rng.normal(size=(T, B))
    c = np.minimum(1.0, np.exp(log_pi - log_mu)) * 0.9
    as_t = lambda x: torch.tensor(x, dtype=torch.float64)  # noqa: E731
    ours = retrace_targets(as_t(r), as_t(d), as_t(q), as_t(v), as_t(c), gamma).numpy()
    np.testing.assert_allclose(ours, _sum_form(r, d, q, v, c, gamma), atol=1e-10)
    np.testing.assert_allclose(truncated_traces(as_t(log_pi), as_t(log_mu), 0.9).numpy(), c, atol=1e-12)


def test_zero_traces_give_one_step_targets():
    rng = np.random.default_rng(1)
    r, q, v = (torch.tensor(rng.normal(size=(4, 3))) for _ in range(3))
    d = torch.ones(4, 3)
    targets = retrace_targets(r, d, q, v, torch.zeros(4, 3), 0.9)
    torch.testing.assert_close(targets, r + 0.9 * v)


def _high_level_critic_loss(log_mu_of):
    """The continuous high-level learner's critic loss on one fixed batch (fresh learner, fixed
    seeds), with behaviour log-probabilities `log_mu_of(log_pi)` of the target policy's log_pi."""


    from hvc.agents.network import AgentSpec, HighLevelAgent
    from hvc.algorithms.svg0_retrace import RecurrentSVG0Retrace
    from hvc.schema import SVG0RetraceConfig

    torch.manual_seed(0)
    agent = HighLevelAgent(AgentSpec(proprio_size=3, task_size=0, action_size=2, discrete=False, lstm_size=16,
                                     value_mlp=(16, 1), critic_takes_action=True))
    learner = RecurrentSVG0Retrace(agent, 0.9, -1.0, 1.0, (0.3, 1.0), SVG0RetraceConfig(
        learning_rate=0.0, target_update_period=10**6, kl_cost=0.0))
    T, B = 5, 4
    g = torch.Generator().manual_seed(1)
    b = {"proprio": torch.randn(T + 1, B, 3, generator=g), "task": torch.zeros(T + 1, B, 0),
         "prev_reward": torch.zeros(T + 1, B), "prev_action": torch.zeros(T + 1, B, 2),
         "first": torch.zeros(T + 1, B), "action": torch.rand(T, B, 2, generator=g) * 2 - 1,
         "reward": torch.rand(T, B, generator=g), "discount": torch.ones(T, B),
         "new_action": torch.ones(T, B), "state": torch.zeros(B, 4, 128)}
    with torch.no_grad():
        _, _, t_out, _ = learner.replay_unrolls(b)
        log_pi = learner.distribution(learner.target, t_out[:-1]).log_prob(b["action"]).sum(-1)
    b["log_mu"] = log_mu_of(log_pi)
    torch.manual_seed(2)  # the same value samples in every call
    return learner.update(b)["critic_loss"]


def test_high_level_retrace_truncates_traces_at_one():
    """c = lambda min(1, pi/mu) (Munos et al. 2016): an action the target policy likes more than
    the behaviour did gets the on-policy trace, never more, or the off-policy correction
    would blow up; so pi/mu = 1, 20 or e^30 give the same targets, and only pi/mu < 1 cuts them."""
    on_policy = _high_level_critic_loss(lambda log_pi: log_pi)
    assert _high_level_critic_loss(lambda log_pi: log_pi - 3.0) == pytest.approx(on_policy, rel=1e-6)
    assert _high_level_critic_loss(lambda log_pi: log_pi - 30.0) == pytest.approx(on_policy, rel=1e-6)
    cut = _high_level_critic_loss(lambda log_pi: log_pi + 3.0)  # pi/mu = e^-3: traces ~0.05
    assert abs(cut - on_policy) > 1e-3 * on_policy  # the traces do reach the loss here


def test_held_steps_get_the_full_trace_whatever_their_ratio():
    """Where the high level chose nothing (held its action) the ratio is 1, so the trace is
    lambda, for ratios above and below one; where it chose, lambda min(1, pi/mu)."""
    log_pi = torch.tensor([[0.0, -2.0, 1.0, -0.5]])
    log_mu = torch.tensor([[-1.0, 0.0, 0.0, 0.0]])
    chose = torch.tensor([[0.0, 0.0, 1.0, 1.0]])
    traces = truncated_traces(log_pi, log_mu, 0.8, chose)
    torch.testing.assert_close(traces, torch.tensor([[0.8, 0.8, 0.8, 0.8 * float(np.exp(-0.5))]]))
