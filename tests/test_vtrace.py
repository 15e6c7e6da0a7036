"""V-trace against a straightforward implementation of the published formulas."""
import numpy as np
import pytest
import torch

from hvc.algorithms.vtrace import VTraceReturns, vtrace_losses, vtrace_targets


def _reference(log_rhos, d, r, v, boot, gamma, rho_bar, c_bar):
    """v_s = V(x_s) + sum_{t>=s} gamma^{t-s} (prod_{i=s..t-1} c_i d_i) delta_t (Espeholt et al., Eq. 1)."""
    T, B = r.shape
    rhos = np.exp(log_rhos)
    values_next = np.concatenate([v[1:], boot[None]], 0)
    vs = np.zeros((T, B))
    for b in range(B):
        for s in range(T):
            total = v[s, b]
            for t in range(s, T):
                weight = 1.0
                for i in range(s, t):
                    weight *= gamma * d[i, b] * min(c_bar, rhos[i, b])
                delta = min(rho_bar, rhos[t, b]) * (r[t, b] + gamma * d[t, b] * values_next[t, b] - v[t, b])
                total += weight * delta
            vs[s, b] = total
    vs_next = np.concatenate([vs[1:], boot[None]], 0)
    adv = np.minimum(rho_bar, rhos) * (r + gamma * d * vs_next - v)
    return vs, adv


def test_vtrace_matches_the_published_formula_on_random_inputs():
    rng = np.random.default_rng(0)
    T, B, gamma = 6, 4, 0.97
    log_rhos = rng.normal(0, 0.8, (T, B))
    d = (rng.uniform(size=(T, B)) > 0.15).astype(float)
    r, v, boot = rng.normal(size=(T, B)), rng.normal(size=(T, B)), rng.normal(size=B)
    as_t = lambda x: torch.tensor(x, dtype=torch.float64)  # noqa: E731
    out = vtrace_targets(as_t(log_rhos), as_t(d), as_t(r), as_t(v), as_t(boot), gamma)  # IMPALA's defaults:
    vs, adv = _reference(log_rhos, d, r, v, boot, gamma, 1.0, 1.0)                       # rho_bar = c_bar = 1
    np.testing.assert_allclose(out.vs.numpy(), vs, atol=1e-6)
    np.testing.assert_allclose(out.pg_advantages.numpy(), adv, atol=1e-6)


def test_on_policy_vtrace_is_the_n_step_return():
    rng = np.random.default_rng(1)
    T, B, gamma = 5, 3, 0.9
    r, v, boot = rng.normal(size=(T, B)), rng.normal(size=(T, B)), rng.normal(size=B)
    out = vtrace_targets(torch.zeros(T, B, dtype=torch.float64), torch.ones(T, B, dtype=torch.float64),
                         torch.tensor(r), torch.tensor(v), torch.tensor(boot), gamma)
    n_step = sum(gamma ** k * r[k] for k in range(T)) + gamma ** T * boot
    np.testing.assert_allclose(out.vs[0].numpy(), n_step, atol=1e-9)


def test_policy_gradient_only_where_a_new_action_was_sampled():
    torch.manual_seed(0)
    T, B, A = 6, 2, 5
    logits = torch.randn(T, B, A, requires_grad=True)
    values = torch.randn(T, B, requires_grad=True)
    actions = torch.randint(0, A, (T, B))
    returns = vtrace_targets(torch.zeros(T, B), torch.ones(T, B), torch.randn(T, B), values.detach(),
                             torch.zeros(B), 0.99)
    new_action = torch.zeros(T, B)
    new_action[::3] = 1  # a fragment of length 3
    losses = vtrace_losses(logits, actions, values, returns, new_action, torch.ones(T, B), entropy_cost=0.01)
    losses["loss"].backward()
    held = new_action == 0
    assert torch.all(logits.grad[held] == 0)            # no policy gradient while a fragment runs
    assert torch.all(logits.grad[~held].abs().sum(-1) > 0)
    assert torch.all(values.grad != 0)                  # the value is trained at every step


@pytest.mark.parametrize("rho_bar,c_bar", [(1.0, 0.5), (2.0, 1.0), (0.6, 1.5)])
def test_vtrace_clips_rho_and_c_each_by_its_own_bound(rho_bar, c_bar):
    """rho_bar bounds the TD errors' weights (the fixed point), c_bar the traces (the
    contraction speed); with rho_bar = c_bar, as everywhere else, swapping them goes unseen."""
    rng = np.random.default_rng(2)
    T, B, gamma = 6, 5, 0.95
    log_rhos = rng.normal(0, 1.0, (T, B))  # rhos from ~0.1 to ~10: both bounds bind
    d = (rng.uniform(size=(T, B)) > 0.1).astype(float)
    r, v, boot = rng.normal(size=(T, B)), rng.normal(size=(T, B)), rng.normal(size=B)
    as_t = lambda x: torch.tensor(x, dtype=torch.float64)  # noqa: E731
    out = vtrace_targets(as_t(log_rhos), as_t(d), as_t(r), as_t(v), as_t(boot), gamma, rho_clip=rho_bar,
                         c_clip=c_bar)
    vs, adv = _reference(log_rhos, d, r, v, boot, gamma, rho_bar, c_bar)
    np.testing.assert_allclose(out.vs.numpy(), vs, atol=1e-9)
    np.testing.assert_allclose(out.pg_advantages.numpy(), adv, atol=1e-9)
    # the two bounds matter separately here: the swapped reference is far from the published one
    swapped, _ = _reference(log_rhos, d, r, v, boot, gamma, c_bar, rho_bar)
    assert np.abs(swapped - vs).max() > 0.05


def _impala_losses(logits, actions, values, vs, adv, new_action, mask, entropy_cost):
    """IMPALA's loss (Espeholt et al. 2018, Sec. 4.2) in numpy: policy gradient and entropy averaged
    over the steps that sampled a new action, value regression (baseline cost 0.5) over valid steps."""
    log_probs = logits - np.log(np.exp(logits).sum(-1, keepdims=True))
    taken = np.take_along_axis(log_probs, actions[..., None], -1)[..., 0]
    pg_mask = new_action * mask
    n_pg, n = max(pg_mask.sum(), 1.0), max(mask.sum(), 1.0)
    entropy = -(np.exp(log_probs) * log_probs).sum(-1)
    pg_loss = -(taken * adv * pg_mask).sum() / n_pg
    value_loss = 0.5 * ((vs - values) ** 2 * mask).sum() / n
    mean_entropy = (entropy * pg_mask).sum() / n_pg
    return {"loss": pg_loss + 0.5 * value_loss - entropy_cost * mean_entropy, "pg_loss": pg_loss,
            "value_loss": value_loss, "entropy": mean_entropy}


@pytest.mark.parametrize("T,B,A", [(6, 3, 4), (2, 1, 3)])
def test_vtrace_losses_are_impalas_on_masked_batches(T, B, A):
    """The value each loss term reports, with padding after an episode's end (mask 0) and held
    steps (no new action); the (2, 1) batch has one valid step and one sampled action, so the
    averages divide by exactly one. Only gradients' zero pattern was checked before."""
    rng = np.random.default_rng(4)
    logits, values = rng.normal(size=(T, B, A)), rng.normal(size=(T, B))
    actions = rng.integers(0, A, (T, B))
    vs, adv = rng.normal(size=(T, B)), rng.normal(size=(T, B))
    mask = np.ones((T, B))
    mask[-1, 0] = 0  # the first unroll ended before its last step
    new_action = np.zeros((T, B))
    new_action[::2] = 1
    new_action[-1, 0] = 1  # a new action on a padding step does not count
    returns = VTraceReturns(vs=torch.tensor(vs), pg_advantages=torch.tensor(adv))
    ours = vtrace_losses(torch.tensor(logits), torch.tensor(actions), torch.tensor(values), returns,
                         torch.tensor(new_action), torch.tensor(mask), entropy_cost=0.03)
    expected = _impala_losses(logits, actions, values, vs, adv, new_action, mask, 0.03)
    assert set(ours) == set(expected)  # the names the metrics are logged under
    for key, value in expected.items():
        assert float(ours[key]) == pytest.approx(value, rel=1e-9, abs=1e-12), key
