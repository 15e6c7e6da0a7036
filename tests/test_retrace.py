"""Retrace targets against the published sum form, computed independently."""
import numpy as np
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
