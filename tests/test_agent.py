import pytest
import torch

from hvc.agents.network import AgentSpec, HighLevelAgent, ImageEncoder


def test_image_encoder_on_64x64_uint8():
    enc = ImageEncoder()
    out = enc(torch.randint(0, 255, (2, 3, 64, 64, 3), dtype=torch.uint8))
    assert out.shape == (2, 3, 256)


def test_image_encoder_takes_the_cameras_height_and_width():
    enc = ImageEncoder(image_size=(40, 96))
    assert enc.out.in_features == 32 * 5 * 12  # three stride-2 pools: 40 -> 5, 96 -> 12
    assert enc(torch.randint(0, 255, (2, 40, 96, 3), dtype=torch.uint8)).shape == (2, 256)
    with pytest.raises(RuntimeError):  # a frame of another size does not fit the linear layer
        enc(torch.randint(0, 255, (2, 64, 64, 3), dtype=torch.uint8))


def test_agent_shapes_and_episode_resets():
    spec = AgentSpec(proprio_size=136, task_size=3, action_size=105, discrete=True, lstm_size=128,
                     value_mlp=(128, 1))
    agent = HighLevelAgent(spec)
    T, B = 4, 2
    args = (torch.randn(T, B, 136), torch.randn(T, B, 3), torch.randn(T, B), torch.randint(0, 105, (T, B)))
    logits, h, state = agent(*args, agent.initial_state(B))
    assert logits.shape == (T, B, 105) and h.shape == (T, B, 128) and agent.values(h).shape == (T, B)
    # a done at step 2 makes steps 2.. independent of what came before
    done = torch.zeros(T, B)
    done[2] = 1
    _, h_reset, _ = agent(*args, agent.initial_state(B), done=done)
    tail = tuple(a[2:] for a in args)
    _, h_fresh, _ = agent(*tail, agent.initial_state(B))
    torch.testing.assert_close(h_reset[2:], h_fresh)


def test_acting_step_by_step_matches_the_learner_s_sequence_call():
    """Acting runs one step at a time (the lstm_cell path); the learner replays whole
    unrolls (nn.LSTM): both must give the same outputs, states and gradients."""
    torch.manual_seed(0)
    spec = AgentSpec(proprio_size=12, task_size=3, action_size=2, discrete=False, lstm_size=64,
                     value_mlp=(32, 1), critic_takes_action=True)
    agent = HighLevelAgent(spec)
    T, B = 5, 3
    args = (torch.randn(T, B, 12), torch.randn(T, B, 3), torch.randn(T, B), torch.randn(T, B, 2))
    done = torch.zeros(T, B)
    done[3, 1] = 1
    out_seq, h_seq, state_seq = agent(*args, agent.initial_state(B))
    state, outs = agent.initial_state(B), []
    for t in range(T):
        out, _, state = agent(*(a[t:t + 1] for a in args), state)
        outs.append(out)
    out_steps = torch.cat(outs)
    torch.testing.assert_close(out_steps, out_seq)
    for a, b in zip(state, state_seq):
        torch.testing.assert_close(a, b)
    lstm_weights = list(agent.core.parameters()) + list(agent.policy_core.parameters())
    for g_steps, g_seq in zip(torch.autograd.grad(out_steps.sum(), lstm_weights, retain_graph=True),
                              torch.autograd.grad(out_seq.sum(), lstm_weights, retain_graph=True)):
        torch.testing.assert_close(g_steps, g_seq)
    # with an episode start inside: one-step stretches in the learner take the same path
    out_done, _, _ = agent(*args, agent.initial_state(B), done=done)
    state, outs = agent.initial_state(B), []
    for t in range(T):
        out, _, state = agent(*(a[t:t + 1] for a in args), state, done=done[t:t + 1])
        outs.append(out)
    torch.testing.assert_close(torch.cat(outs), out_done)


def test_vision_and_continuous_heads():
    spec = AgentSpec(proprio_size=136, task_size=0, action_size=1, discrete=False, lstm_size=256,
                     value_mlp=(200, 200, 1), vision=True, critic_takes_action=True)
    agent = HighLevelAgent(spec)
    T, B = 2, 3
    out, h, _ = agent(torch.randn(T, B, 136), torch.zeros(T, B, 0), torch.zeros(T, B), torch.zeros(T, B, 1),
                      agent.initial_state(B), image=torch.randint(0, 255, (T, B, 64, 64, 3), dtype=torch.uint8))
    mean, sigma = agent.gaussian(out, -1.5, 1.5)
    assert mean.shape == (T, B, 1) and torch.all(mean.abs() <= 1.5)
    assert torch.all((sigma >= 0.1) & (sigma <= 1.0))
    assert agent.values(h, mean).shape == (T, B)


def test_continuous_policy_stays_steerable_under_a_critic_that_prefers_a_bound():
    """A critic that grows with the action pushes the mean to the bound; the tanh must not
    saturate there (its gradient would vanish for good) and sigma keeps a gradient at its floor."""

    import numpy as np

    from hvc.algorithms.svg0_retrace import RecurrentSVG0Retrace
    from hvc.schema import SVG0RetraceConfig

    torch.manual_seed(0)
    spec = AgentSpec(proprio_size=3, task_size=0, action_size=2, discrete=False, lstm_size=16,
                     value_mlp=(16, 1), critic_takes_action=True)
    agent = HighLevelAgent(spec)
    learner = RecurrentSVG0Retrace(agent, 0.9, -1.0, 1.0, (0.1, 1.0), SVG0RetraceConfig(
        learning_rate=1e-2, entropy_cost=0.0, target_update_period=10**6, kl_cost=0.0))
    learner.target.value = _linear_critic(16, 2, 5.0)  # Q_target(h, a) = 5 * sum(a): always "more action"
    batch, T, B = _policy_batch()
    for _ in range(300):
        _svg0_policy_step(learner, batch)
    out, _, _ = agent(batch["proprio"], batch["task"], batch["prev_reward"], batch["prev_action"],
                      agent.initial_state(B), done=batch["first"])
    mean, _ = agent.gaussian(out, -1.0, 1.0)
    assert mean.min() > 0.9  # the policy did follow the critic to the bound
    assert out.chunk(2, -1)[0].abs().max() < 3.0  # without saturating its tanh (tanh(3) = 0.995)
    sigma_raw = torch.full((1,), -30.0, requires_grad=True)  # deep below the floor
    _, sigma = agent.gaussian(torch.cat([torch.zeros(1), sigma_raw]), -1.0, 1.0)
    sigma.sum().backward()
    assert np.isclose(float(sigma.detach()), 0.1) and sigma_raw.grad.abs() > 0


def _linear_critic(hidden: int, actions: int, slope: float) -> torch.nn.Linear:
    """Q(h, a) = slope * sum(a)."""
    critic = torch.nn.Linear(hidden + actions, 1).requires_grad_(False)
    critic.weight.zero_()
    critic.weight[0, -actions:] = slope
    critic.bias.zero_()
    return critic


def _policy_batch(T: int = 3, B: int = 8):
    batch = {"proprio": torch.randn(T + 1, B, 3), "task": torch.zeros(T + 1, B, 0),
             "prev_reward": torch.zeros(T + 1, B), "prev_action": torch.zeros(T + 1, B, 2),
             "first": torch.zeros(T + 1, B), "new_action": torch.ones(T, B)}
    return batch, T, B


def _svg0_policy_step(learner, batch) -> None:
    """One step of the policy loss alone (no critic loss)."""
    B = batch["proprio"].shape[1]
    args = (batch["proprio"], batch["task"], batch["prev_reward"], batch["prev_action"])
    out, _, _ = learner.agent(*args, learner.agent.initial_state(B), done=batch["first"])
    with torch.no_grad():
        t_out, t_h, _ = learner.target(*args, learner.target.initial_state(B), done=batch["first"])
    learner.step(torch.zeros(()), out, batch, torch.zeros(batch["new_action"].shape), t_out, t_h)


def test_high_level_svg0_follows_q_target_not_the_online_q():
    """The paper's SVG(0) maximises Q_target(s, a) at both levels: with an online Q that wants
    the opposite, the policy still moves the way the target's Q wants."""


    from hvc.algorithms.svg0_retrace import RecurrentSVG0Retrace
    from hvc.schema import SVG0RetraceConfig

    torch.manual_seed(0)
    agent = HighLevelAgent(AgentSpec(proprio_size=3, task_size=0, action_size=2, discrete=False, lstm_size=16,
                                     value_mlp=(16, 1), critic_takes_action=True))
    learner = RecurrentSVG0Retrace(agent, 0.9, -1.0, 1.0, (0.1, 1.0), SVG0RetraceConfig(
        learning_rate=1e-2, entropy_cost=0.0, target_update_period=10**6, kl_cost=0.0))
    agent.value = _linear_critic(16, 2, +5.0)
    learner.target.value = _linear_critic(16, 2, -5.0)
    batch, _, B = _policy_batch()
    for _ in range(100):
        _svg0_policy_step(learner, batch)
    out, _, _ = agent(batch["proprio"], batch["task"], batch["prev_reward"], batch["prev_action"],
                      agent.initial_state(B), done=batch["first"])
    mean, _ = agent.gaussian(out, -1.0, 1.0)
    assert mean.max() < -0.5


def test_running_normalizer_matches_the_statistics_of_all_inputs_seen():
    import numpy as np

    from hvc.agents.network import RunningNormalizer

    rng = np.random.default_rng(0)
    batches = [rng.normal([3.0, -40.0], [0.5, 20.0], size=(n, 2)) for n in (1, 7, 30)]
    norm = RunningNormalizer(2)
    identity = torch.tensor([[0.5, -2.0]])
    torch.testing.assert_close(norm(identity), identity, rtol=1e-2, atol=0)  # nothing seen: about unchanged
    for batch in batches:
        norm.update(torch.from_numpy(batch).float())
    seen = np.concatenate(batches)
    np.testing.assert_allclose(norm.mean.numpy(), seen.mean(0), rtol=1e-5)
    np.testing.assert_allclose(norm.var.numpy(), seen.var(0), rtol=1e-4)
    out = norm(torch.from_numpy(seen).float()).numpy()
    np.testing.assert_allclose(out.mean(0), 0.0, atol=1e-4)
    assert norm(torch.tensor([[3.0, 1e6]]))[0, 1] == 5.0  # outliers are clipped
    first = RunningNormalizer(1)
    first.update(torch.tensor([[1.0]]))  # one sample: zero variance
    assert abs(float(first(torch.tensor([[1.01]])))) < 0.2  # a small deviation stays small


def test_normalizer_floor_travels_with_the_weights():
    """A trained agent must read its inputs through the floor it was trained with."""
    from hvc.agents.network import RunningNormalizer

    trained = RunningNormalizer(1, var_floor=1e-6)
    trained.update(torch.tensor([[0.0], [0.002]]))  # variance 1e-6
    x = torch.tensor([[0.002]])
    restored = RunningNormalizer(1)  # today's default floor
    restored.load_state_dict(trained.state_dict())
    torch.testing.assert_close(restored(x), trained(x))
    assert float(trained(x)) > 0.5 and abs(float(RunningNormalizer.DEFAULT_VAR_FLOOR)) > 1e-3
    # a state saved before the floor was recorded loads with the default floor
    old = {k: v for k, v in trained.state_dict().items() if k != "var_floor"}
    restored.load_state_dict(old)
    assert float(restored.var_floor) == RunningNormalizer.DEFAULT_VAR_FLOOR


def test_a_nan_loss_stops_before_the_weights_or_optimiser_change():
    """The run's exit checkpoint must hold the last good state, not NaN weights."""
    import pytest

    from hvc.algorithms.vtrace import VTraceLearner
    from hvc.schema import VTraceConfig
    from hvc.errors import NonFiniteLoss

    torch.manual_seed(0)
    spec = AgentSpec(proprio_size=3, task_size=0, action_size=4, discrete=True, lstm_size=16, value_mlp=(16, 1))
    agent = HighLevelAgent(spec)
    learner = VTraceLearner(agent, 0.9, VTraceConfig(learning_rate=1e-2))
    optimizer = learner.optimizer
    T, B = 3, 2
    batch = {"proprio": torch.randn(T + 1, B, 3), "task": torch.zeros(T + 1, B, 0),
             "prev_reward": torch.zeros(T + 1, B), "prev_action": torch.zeros(T + 1, B, dtype=torch.long),
             "first": torch.zeros(T + 1, B), "action": torch.zeros(T, B, dtype=torch.long),
             "log_mu": torch.full((T, B), -1.4), "reward": torch.ones(T, B), "discount": torch.ones(T, B),
             "new_action": torch.ones(T, B), "state": torch.zeros(B, 4, 128)}  # policy LSTM: 128
    learner.update(batch)  # a good step: Adam has moments now
    weights = {k: v.clone() for k, v in agent.state_dict().items()}
    moments = [s["exp_avg"].clone() for s in optimizer.state.values()]
    batch["reward"][1, 0] = float("nan")
    with pytest.raises(NonFiniteLoss, match="non-finite loss"):
        learner.update(batch)
    assert all(torch.equal(weights[k], v) for k, v in agent.state_dict().items())
    assert all(torch.equal(m, s["exp_avg"]) for m, s in zip(moments, optimizer.state.values()))


def test_learning_discounts_end_every_episode_time_limits_included():
    """Actors reset at once, so the step after an end belongs to the next episode."""
    import numpy as np

    from hvc.algorithms.vtrace import vtrace_targets
    from hvc.runtime.acting import learning_discounts

    env_discounts = np.array([1.0, 1.0, 0.0, 1.0], np.float32)   # ... a fall, and a time limit (discount 1)
    dones = np.array([False, True, True, False])
    np.testing.assert_array_equal(learning_discounts(env_discounts, dones), [1.0, 0.0, 0.0, 1.0])
    # an unroll whose episode hits its time limit at step 1: steps 0-1 see nothing of the next episode
    d = torch.from_numpy(learning_discounts(np.ones(3, np.float32), np.array([False, True, False])))[:, None]
    rewards, values = torch.tensor([[1.0], [1.0], [100.0]]), torch.zeros(3, 1)
    vs = vtrace_targets(torch.zeros(3, 1), d, rewards, values, torch.tensor([50.0]), 0.9).vs
    torch.testing.assert_close(vs[:2, 0], torch.tensor([1.9, 1.0]))


def _continuous_batch(T=3, B=4, proprio=3, action=2, seed=0):
    g = torch.Generator().manual_seed(seed)
    return {"proprio": torch.randn(T + 1, B, proprio, generator=g), "task": torch.zeros(T + 1, B, 0),
            "prev_reward": torch.zeros(T + 1, B), "prev_action": torch.zeros(T + 1, B, action),
            "first": torch.zeros(T + 1, B), "action": torch.rand(T, B, action, generator=g) * 2 - 1,
            "query": torch.rand(T, B, action, generator=g) * 2 - 1, "log_mu": torch.zeros(T, B),
            "reward": torch.rand(T, B, generator=g), "discount": torch.zeros(T, B),
            "new_action": torch.ones(T, B), "state": torch.zeros(B, 4, 128)}


def test_continuous_actions_keep_the_raw_sample_and_its_exact_density():
    """The env gets the clipped action; replay keeps the raw sample and its Gaussian log
    density, which the learner's log pi reproduces (a clipped value's density would not
    be its probability), while Q sees the clipped action as the env did."""

    import numpy as np

    from hvc.algorithms.svg0_retrace import RecurrentSVG0Retrace
    from hvc.runtime.acting import carry

    torch.manual_seed(0)
    spec = AgentSpec(proprio_size=3, task_size=0, action_size=2, discrete=False, lstm_size=16,
                     value_mlp=(16, 1), critic_takes_action=True)
    agent = HighLevelAgent(spec)
    learner = RecurrentSVG0Retrace(agent, 0.9, -0.2, 0.2, (0.9, 1.0))  # sigma >> range: most samples clip
    B = 64
    obs = {"proprio": np.random.default_rng(0).normal(size=(B, 3)).astype(np.float32),
           "task": np.zeros((B, 0), np.float32)}
    with torch.no_grad():
        out, h, _ = agent(torch.from_numpy(obs["proprio"][None]), torch.from_numpy(obs["task"][None]),
                          torch.zeros(1, B), torch.zeros(1, B, 2), agent.initial_state(B), done=torch.ones(1, B))
    acted = learner.act(out[0], h[0])
    send, action, log_mu = acted.send, acted.action, acted.log_mu
    assert np.all(np.abs(send) <= 0.2) and np.mean(np.abs(action) > 0.2) > 0.5
    np.testing.assert_array_equal(send, np.clip(action, -0.2, 0.2))
    with torch.no_grad():
        dist = learner.distribution(agent, out[0])
        np.testing.assert_allclose(dist.log_prob(torch.from_numpy(action)).sum(-1).numpy(), log_mu, atol=1e-5)
        clipped = dist.log_prob(torch.from_numpy(send)).sum(-1).numpy()
    assert np.abs(clipped - log_mu).max() > 0.1  # the old, clipped density differs: the test can fail
    infos = [{"new_action": True}] * B
    _, in_force, _, next_input, _ = carry(acted, np.zeros_like(action), np.zeros(B), np.zeros(B, bool), infos)
    np.testing.assert_array_equal(in_force, action)  # replay: the raw sample
    np.testing.assert_array_equal(next_input, send)  # the agent's next input: what the env got


def test_continuous_learner_refreshes_its_target_agent_on_schedule():


    from hvc.algorithms.svg0_retrace import RecurrentSVG0Retrace
    from hvc.schema import SVG0RetraceConfig

    torch.manual_seed(0)
    agent = HighLevelAgent(AgentSpec(proprio_size=3, task_size=0, action_size=2, discrete=False, lstm_size=16,
                                     value_mlp=(16, 1), critic_takes_action=True))
    learner = RecurrentSVG0Retrace(agent, 0.9, -1.0, 1.0, (0.1, 1.0),
                                   SVG0RetraceConfig(learning_rate=1e-2, target_update_period=3, kl_cost=0.0))
    same = lambda: all(torch.equal(a, b) for a, b in zip(agent.state_dict().values(),  # noqa: E731
                                                         learner.target.state_dict().values()))
    history = []
    for _ in range(6):
        learner.update(_continuous_batch())
        history.append(same())
    assert history == [False, False, True, False, False, True]


def test_query_learner_fits_q_to_one_step_targets_on_query_and_selected_key():
    """With discount 0 the 1-step target is the reward: Q(h, query) and Q(h, key) both learn it."""
    from types import SimpleNamespace

    import numpy as np

    from hvc.algorithms.wolpertinger import WolpertingerLearner
    from hvc.schema import WolpertingerConfig

    torch.manual_seed(0)
    agent = HighLevelAgent(AgentSpec(proprio_size=3, task_size=0, action_size=2, discrete=False, lstm_size=16,
                                     value_mlp=(32, 1), critic_takes_action=True))
    selector = SimpleNamespace(keys=np.zeros((5, 2), np.float32))
    learner = WolpertingerLearner(agent, 0.9, -3.0, 3.0, (0.1, 1.0), selector, 1.0,
                                  WolpertingerConfig(learning_rate=3e-3, target_update_period=10))
    batch = _continuous_batch()
    batch["new_action"] = torch.zeros_like(batch["new_action"])  # no policy term: Q alone
    first = learner.update(batch)["critic_loss"]
    for _ in range(400):
        last = learner.update(batch)["critic_loss"]
    assert last < 0.05 * first
    _, h, _ = agent(batch["proprio"], batch["task"], batch["prev_reward"], batch["prev_action"],
                    agent.initial_state(4), done=batch["first"])
    with torch.no_grad():
        for key in ("query", "action"):
            torch.testing.assert_close(agent.values(h[:-1], batch[key]), batch["reward"], atol=0.1, rtol=0)


def test_vtrace_update_sets_rho_to_one_on_held_steps(monkeypatch):
    """Held steps chose nothing, so their stored log mu must not weight the targets."""

    import hvc.algorithms.vtrace as vtrace

    seen = {}
    original = vtrace.vtrace_targets

    def spy(log_rhos, *args, **kwargs):
        seen["log_rhos"] = log_rhos.clone()
        return original(log_rhos, *args, **kwargs)

    monkeypatch.setattr(vtrace, "vtrace_targets", spy)
    torch.manual_seed(0)
    agent = HighLevelAgent(AgentSpec(proprio_size=3, task_size=0, action_size=4, discrete=True, lstm_size=16,
                                     value_mlp=(16, 1)))
    T, B = 4, 2
    new_action = torch.tensor([[1.0, 1.0], [0.0, 0.0], [0.0, 1.0], [1.0, 0.0]])
    batch = {"proprio": torch.randn(T + 1, B, 3), "task": torch.zeros(T + 1, B, 0),
             "prev_reward": torch.zeros(T + 1, B), "prev_action": torch.zeros(T + 1, B, dtype=torch.long),
             "first": torch.zeros(T + 1, B), "action": torch.zeros(T, B, dtype=torch.long),
             "log_mu": torch.full((T, B), -9.0), "reward": torch.ones(T, B), "discount": torch.ones(T, B),
             "new_action": new_action, "state": torch.zeros(B, 4, 128)}
    vtrace.VTraceLearner(agent, 0.9).update(batch)
    log_rhos = seen["log_rhos"]
    assert torch.all(log_rhos[new_action == 0] == 0)
    assert torch.all(log_rhos[new_action == 1] > 5)  # pi / mu with mu = e^-9


def test_the_pacer_owes_the_configured_updates_per_unroll_fractions_included():
    """updates_per_unroll=0.25 is one update per 4 unrolls, whatever the envs' batching."""
    from hvc.algorithms.learner import Pacer

    quarter = Pacer(0.25)
    assert [quarter.owed(1) for _ in range(8)] == [0, 0, 0, 1, 0, 0, 0, 1]
    assert Pacer(0.25).owed(2) + Pacer(0.25, credit=0.5).owed(2) == 0 + 1
    assert Pacer(2).owed(3) == 6 and Pacer(1.5).owed(1) == 1
    resumed = Pacer(0.25, credit=0.75)  # a checkpoint's credit carries over
    assert resumed.owed(1) == 1 and resumed.credit == 0.0


def _discrete_batch(T=4, B=2, vision=False, seed=0):
    g = torch.Generator().manual_seed(seed)
    batch = {"proprio": torch.randn(T + 1, B, 3, generator=g), "task": torch.zeros(T + 1, B, 0),
             "prev_reward": torch.zeros(T + 1, B), "prev_action": torch.zeros(T + 1, B, dtype=torch.long),
             "first": torch.zeros(T + 1, B), "action": torch.randint(0, 4, (T, B), generator=g),
             "log_mu": -torch.rand(T, B, generator=g),  # mu > pi for most steps: rho < 1 matters
             "reward": torch.rand(T, B, generator=g), "discount": torch.ones(T, B), "new_action": torch.ones(T, B),
             "state": torch.zeros(B, 4, 128)}
    if vision:
        batch["image"] = torch.randint(0, 255, (T + 1, B, 64, 64, 3), generator=g, dtype=torch.uint8)
    return batch


def test_vtrace_learner_feeds_the_published_targets_its_own_log_pi_values_and_settings(monkeypatch):
    """What VTraceLearner hands to vtrace_targets / vtrace_losses, against an independent
    replay of the agent: log rho = log softmax(logits)[a] - log mu, V over the unroll and
    its bootstrap, the task's gamma and the configured rho_bar and c_bar."""
    import hvc.algorithms.vtrace as vtrace
    from hvc.schema import VTraceConfig

    calls = {}
    targets, losses = vtrace.vtrace_targets, vtrace.vtrace_losses
    monkeypatch.setattr(vtrace, "vtrace_targets", lambda *a, **k: calls.setdefault("targets", (a, k)) and targets(*a, **k))
    monkeypatch.setattr(vtrace, "vtrace_losses", lambda *a, **k: calls.setdefault("losses", (a, k)) and losses(*a, **k))
    torch.manual_seed(0)
    agent = HighLevelAgent(AgentSpec(3, 0, 4, True, 16, (16, 1)))
    batch = _discrete_batch()
    batch["first"][2, 1] = 1.0  # an episode starts inside the unroll: the LSTM resets there
    with torch.no_grad():
        logits, h, _ = agent(batch["proprio"], batch["task"], batch["prev_reward"], batch["prev_action"],
                             agent.initial_state(2), done=batch["first"])
        values = agent.values(h)
    vtrace.VTraceLearner(agent, 0.9, VTraceConfig(rho_clip=0.7, c_clip=0.4, entropy_cost=0.02)).update(batch)
    (log_rhos, discounts, rewards, v, bootstrap, gamma, rho_clip, c_clip), _ = calls["targets"]
    log_pi = torch.log_softmax(logits[:-1], -1).gather(-1, batch["action"][..., None]).squeeze(-1)
    torch.testing.assert_close(log_rhos, log_pi - batch["log_mu"])
    torch.testing.assert_close(v, values[:-1])
    torch.testing.assert_close(bootstrap, values[-1])
    assert (gamma, rho_clip, c_clip) == (0.9, 0.7, 0.4)
    (l_logits, l_actions, l_values, _, _, _, entropy_cost), _ = calls["losses"]
    torch.testing.assert_close(l_values.detach(), values[:-1])
    torch.testing.assert_close(l_logits.detach(), logits[:-1])
    assert entropy_cost == 0.02 and torch.equal(l_actions, batch["action"])


def test_vtrace_learner_reads_the_frames_of_a_vision_task():
    """The unroll's images reach the agent's encoder: other frames, another loss."""
    torch.manual_seed(0)
    agent = HighLevelAgent(AgentSpec(3, 0, 4, True, 16, (16, 1), vision=True))
    batch = _discrete_batch(T=2, vision=True)
    import copy

    from hvc.algorithms.vtrace import VTraceLearner
    from hvc.schema import VTraceConfig

    first = VTraceLearner(copy.deepcopy(agent), 0.9, VTraceConfig(learning_rate=0.0)).update(batch)
    other = dict(batch, image=255 - batch["image"])
    second = VTraceLearner(copy.deepcopy(agent), 0.9, VTraceConfig(learning_rate=0.0)).update(other)
    assert first["value_loss"] != pytest.approx(second["value_loss"], rel=1e-6)


def test_vtrace_learner_acts_by_sampling_its_policy():
    """act: a categorical sample, sent, kept and seen as is, with its exact log probability."""
    import numpy as np

    from hvc.algorithms.vtrace import VTraceLearner

    agent = HighLevelAgent(AgentSpec(3, 0, 4, True, 16, (16, 1)))
    logits = torch.log(torch.tensor([[0.7, 0.1, 0.1, 0.1]] * 4000))
    torch.manual_seed(0)
    acted = VTraceLearner(agent, 0.9).act(logits, torch.zeros(4000, 16))
    assert np.array_equal(acted.send, acted.action) and np.array_equal(acted.seen, acted.action)
    assert abs(np.mean(acted.action == 0) - 0.7) < 0.03 and set(np.unique(acted.action)) == {0, 1, 2, 3}
    np.testing.assert_allclose(acted.log_mu, np.log([0.7, 0.1, 0.1, 0.1])[acted.action], rtol=1e-5)


@pytest.mark.parametrize("learner_kind", ["svg0", "wolpertinger"])
def test_continuous_learners_replay_frames_and_episode_starts(learner_kind):
    """The unroll's images and episode starts reach the replayed agent (online and target):
    other frames or an LSTM reset mid-unroll give another critic loss."""
    import copy

    import numpy as np

    from hvc.algorithms.svg0_retrace import RecurrentSVG0Retrace
    from hvc.algorithms.wolpertinger import WolpertingerLearner
    from hvc.schema import SVG0RetraceConfig, WolpertingerConfig

    torch.manual_seed(0)
    agent = HighLevelAgent(AgentSpec(3, 0, 2, False, 16, (16, 1), vision=True, critic_takes_action=True))

    def loss(batch):
        torch.manual_seed(1)
        if learner_kind == "svg0":
            learner = RecurrentSVG0Retrace(copy.deepcopy(agent), 0.9, -1.0, 1.0, (0.1, 1.0),
                                           SVG0RetraceConfig(learning_rate=0.0))
        else:
            keys = type("Keys", (), {"keys": np.zeros((3, 2), np.float32), "nearest": lambda self, q: np.arange(3)})()
            learner = WolpertingerLearner(copy.deepcopy(agent), 0.9, -3.0, 3.0, (0.1, 1.0), keys, 1.0,
                                          WolpertingerConfig(learning_rate=0.0))
        return learner.update(batch)["critic_loss"]

    batch = _continuous_batch(T=2, B=2)
    g = torch.Generator().manual_seed(3)
    batch["image"] = torch.randint(0, 255, (3, 2, 64, 64, 3), generator=g, dtype=torch.uint8)
    batch["discount"] = torch.ones(2, 2)
    base = loss(batch)
    assert loss(dict(batch, image=255 - batch["image"])) != pytest.approx(base, rel=1e-6)
    restarted = dict(batch, first=batch["first"].clone())
    restarted["first"][1, 0] = 1.0
    assert loss(restarted) != pytest.approx(base, rel=1e-6)


def test_wolpertinger_acts_among_the_nearest_keys_by_their_q():
    """act: the query's k nearest keys, one drawn with p ~ exp(Q / T); the env gets its index,
    replay and the agent's next input its key, and the query keeps its own log density."""
    import numpy as np

    from hvc.algorithms.wolpertinger import WolpertingerLearner

    class Selector:
        keys = np.array([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0], [5.0, 5.0]], np.float32)

        def nearest(self, query):
            return np.array([0, 1, 2])  # key 3 is never a candidate

    torch.manual_seed(0)
    agent = HighLevelAgent(AgentSpec(3, 0, 2, False, 16, (16, 1), critic_takes_action=True))
    agent.value = _linear_critic(16, 2, 4.0)  # Q(h, key) = 4 * sum(key): keys 1 and 2 beat key 0
    learner = WolpertingerLearner(agent, 0.9, -3.0, 3.0, (0.1, 1.0), Selector(), 0.5, seed=0)
    n = 3000
    policy_out = torch.zeros(n, 4)
    acted = learner.act(policy_out, torch.zeros(n, 16))
    assert set(np.unique(acted.send)) <= {0, 1, 2}
    np.testing.assert_array_equal(acted.action, Selector.keys[acted.send])
    np.testing.assert_array_equal(acted.seen, acted.action)
    share = np.bincount(acted.send, minlength=3) / n  # p ~ exp(Q / T): e^0, e^8, e^8
    assert share[0] < 0.01 and abs(share[1] - share[2]) < 0.05
    dist = learner.distribution(agent, policy_out)
    expected = dist.log_prob(torch.from_numpy(acted.query)).sum(-1).numpy()
    np.testing.assert_allclose(acted.log_mu, expected, rtol=1e-5)
    assert np.all(np.abs(acted.query) <= 3.0)


def test_wolpertinger_critic_regresses_query_and_key_on_targets_through_the_target_policy():
    """critic_loss = 0.5 (mean (Q(h, query) - y)^2 + mean (Q(h, key) - y)^2) with
    y = r + gamma d mean_i Q_target(h', clip(a'_i)), a'_i ~ pi_target(h'): computed here from the
    target agent and the same draws. A wide sigma sends most draws past the range, so the clip
    shows; discounts of 1 make the bootstrap count."""
    from types import SimpleNamespace

    import numpy as np

    from hvc.algorithms.wolpertinger import WolpertingerLearner
    from hvc.schema import WolpertingerConfig

    torch.manual_seed(0)
    agent = HighLevelAgent(AgentSpec(3, 0, 2, False, 16, (16, 1), critic_takes_action=True))
    selector = SimpleNamespace(keys=np.zeros((5, 2), np.float32))
    low, high, gamma = -0.2, 0.2, 0.9
    learner = WolpertingerLearner(agent, gamma, low, high, (2.0, 2.0), selector, 1.0,
                                  WolpertingerConfig(value_samples=3, kl_cost=0.1))
    batch = _continuous_batch(seed=3)
    batch["discount"] = torch.ones_like(batch["discount"])
    args = (batch["proprio"], batch["task"], batch["prev_reward"], batch["prev_action"])
    with torch.no_grad():
        _, h, _ = agent(*args, agent.unpack_state(batch["state"]), done=batch["first"])
        t_out, t_h, _ = learner.target(*args, agent.unpack_state(batch["state"]), done=batch["first"])
        torch.manual_seed(1)
        mean, sigma = learner.target.gaussian(t_out[1:], low, high, (2.0, 2.0))
        draws = [torch.distributions.Normal(mean, sigma).sample() for _ in range(3)]
        assert np.mean([(d.abs() > high).float().mean().item() for d in draws]) > 0.5
        v_next = torch.stack([learner.target.values(t_h[1:], d.clamp(low, high)) for d in draws]).mean(0)
        y = batch["reward"] + gamma * batch["discount"] * v_next
        expected = 0.5 * (((agent.values(h[:-1], batch["query"]) - y) ** 2).mean()
                          + ((agent.values(h[:-1], batch["action"]) - y) ** 2).mean())
    torch.manual_seed(1)
    assert learner.update(batch)["critic_loss"] == pytest.approx(expected.item(), rel=1e-5)


def test_wolpertinger_queries_stay_in_range_and_pick_near_their_own_position():
    """Every env gets a choice, each query is clipped to the key space's range (float32, its
    density that of the clipped value), and the candidates are those near that env's query: a
    query steered to one key picks it."""
    import numpy as np

    from hvc.algorithms.wolpertinger import WolpertingerLearner

    keys = np.array([[-2.5, -2.5], [2.5, 2.5], [2.5, -2.5]], np.float32)

    class Nearest:  # k = 1: the key nearest the query
        def __init__(self):
            self.keys, self.seen = keys, []

        def nearest(self, query):
            self.seen.append(np.array(query))
            return np.array([int(np.argmin(((keys - query) ** 2).sum(1)))])

    torch.manual_seed(0)
    agent = HighLevelAgent(AgentSpec(3, 0, 2, False, 16, (16, 1), critic_takes_action=True))
    selector = Nearest()
    wide = WolpertingerLearner(agent, 0.9, -3.0, 3.0, (4.0, 4.0), selector, 1.0, seed=0)
    n = 400
    acted = wide.act(torch.zeros(n, 4), torch.zeros(n, 16))
    assert len(acted.send) == n and acted.query.dtype == np.float32 and acted.query.shape == (n, 2)
    assert np.abs(acted.query).max() == 3.0 and (acted.query == -3.0).any()  # sigma 4: many clipped
    np.testing.assert_array_equal(np.stack(selector.seen), acted.query)
    narrow = WolpertingerLearner(agent, 0.9, -3.0, 3.0, (0.01, 0.01), selector, 1.0, seed=0)
    towards = torch.zeros(8, 4)
    towards[:4, :2], towards[4:, :2] = 10.0, torch.tensor([10.0, -10.0])  # tanh: means near (3, 3), (3, -3)
    np.testing.assert_array_equal(narrow.act(towards, torch.zeros(8, 16)).send, [1] * 4 + [2] * 4)


def test_wolpertinger_from_config_takes_the_controller_its_temperature_and_the_run_seed():
    """What hvc-run builds: the query controller as selector, the controller's temperature, and
    a selection stream seeded by the run's seed (two runs of one seed choose alike)."""
    from types import SimpleNamespace

    import numpy as np

    from hvc.algorithms.wolpertinger import WolpertingerLearner
    from hvc.config import compose

    cfg = compose(["controller=query", "controller.temperature=0.37", "seed=11"])
    selector = SimpleNamespace(keys=np.eye(3, 2, dtype=np.float32), nearest=lambda q: np.arange(3))
    space = SimpleNamespace(low=-3.0, high=3.0)

    def build():
        torch.manual_seed(0)
        agent = HighLevelAgent(AgentSpec(3, 0, 2, False, 16, (16, 1), critic_takes_action=True))
        return WolpertingerLearner.from_config(agent, cfg, space, selector)

    learner = build()
    assert learner.selector is selector and learner.temperature == pytest.approx(0.37)
    assert (learner.low, learner.high) == (-3.0, 3.0)
    assert learner.rng.bit_generator.state == np.random.default_rng(11).bit_generator.state
    picks = [build().act(torch.zeros(64, 4), torch.zeros(64, 16)).send for _ in range(2)]
    np.testing.assert_array_equal(*picks)


def test_high_level_svg0_critic_regresses_on_retrace_targets_of_the_target_agent():
    """critic_loss = 0.5 mean (Q(h, clip(a)) - Q_ret)^2, Q_ret from the target agent: Q_target of
    the replayed (clipped) action, E over the target policy's clipped draws at the next step,
    and traces lambda min(1, pi/mu) with held steps at ratio 1; episode starts reset both
    agents' LSTMs. Computed here from the same draws."""
    from hvc.algorithms.retrace import retrace_targets, truncated_traces
    from hvc.algorithms.svg0_retrace import RecurrentSVG0Retrace
    from hvc.schema import SVG0RetraceConfig

    torch.manual_seed(0)
    agent = HighLevelAgent(AgentSpec(3, 0, 2, False, 16, (16, 1), critic_takes_action=True))
    low, high, gamma, lam = -0.3, 0.3, 0.9, 0.8
    learner = RecurrentSVG0Retrace(agent, gamma, low, high, (1.0, 1.0),
                                   SVG0RetraceConfig(value_samples=3, retrace_lambda=lam, kl_cost=0.1))
    b = _continuous_batch(T=5, seed=4)
    b["discount"] = torch.ones_like(b["discount"])
    b["action"] = b["action"] * 2                                    # some replayed actions past the range
    b["log_mu"] = torch.randn(b["log_mu"].shape, generator=torch.Generator().manual_seed(5))
    b["new_action"][1:3] = 0.0                                       # held steps
    b["first"][2, 1] = 1.0                                           # an episode starts mid-unroll
    args = (b["proprio"], b["task"], b["prev_reward"], b["prev_action"])
    with torch.no_grad():
        _, h, _ = agent(*args, agent.unpack_state(b["state"]), done=b["first"])
        t_out, t_h, _ = learner.target(*args, agent.unpack_state(b["state"]), done=b["first"])
        torch.manual_seed(2)
        mean, sigma = learner.target.gaussian(t_out, low, high, (1.0, 1.0))
        draws = [torch.distributions.Normal(mean, sigma).sample()[1:] for _ in range(3)]
        v_next = torch.stack([learner.target.values(t_h[1:], d.clamp(low, high)) for d in draws]).mean(0)
        q_taken = learner.target.values(t_h[:-1], b["action"].clamp(low, high))
        log_pi = torch.distributions.Normal(mean[:-1], sigma[:-1]).log_prob(b["action"]).sum(-1)
        traces = truncated_traces(log_pi, b["log_mu"], lam, b["new_action"])
        targets = retrace_targets(b["reward"], b["discount"], q_taken, v_next, traces, gamma)
        expected = 0.5 * ((agent.values(h[:-1], b["action"].clamp(low, high)) - targets) ** 2).mean()
    torch.manual_seed(2)
    assert learner.update(b)["critic_loss"] == pytest.approx(expected.item(), rel=1e-5)


@pytest.mark.parametrize("new_steps", ["some", "one"])
def test_high_level_svg0_policy_loss_and_metrics_from_the_same_draws(new_steps):
    """policy_loss = -sum_t w_t (Q_target(h_t, clip(a(xi))) - eta KL(pi || pi_target) + c H(pi)
    - saturation), w = new_action / max(1, count); saturation = sum (|pre-tanh mean| - 2)_+^2.
    The reported entropy and kl are w-weighted sums, q the critic's mean. Recomputed here with
    pi and pi_target apart (one learner step in between) and means pushed into saturation; with
    a single new action in the batch its weight is 1."""
    from hvc.algorithms.svg0_retrace import MEAN_RAW_LIMIT, RecurrentSVG0Retrace
    from hvc.schema import SVG0RetraceConfig

    torch.manual_seed(0)
    agent = HighLevelAgent(AgentSpec(3, 0, 3, False, 16, (16, 1), critic_takes_action=True))
    with torch.no_grad():
        agent.policy_out.weight.mul_(40.0)                             # pre-tanh means far past the limit
    low, high, eta, c = -0.3, 0.3, 0.7, 0.05
    learner = RecurrentSVG0Retrace(agent, 0.9, low, high, (0.2, 0.9),
                                   SVG0RetraceConfig(value_samples=2, kl_cost=eta, entropy_cost=c,
                                                     learning_rate=1e-2))
    b = _continuous_batch(T=5, seed=6, action=3)
    b["new_action"][1:3] = 0.0
    if new_steps == "one":
        b["new_action"].zero_()
        b["new_action"][3, 1] = 1.0
    learner.update(b)                                                  # pi moves away from pi_target
    args = (b["proprio"], b["task"], b["prev_reward"], b["prev_action"])
    with torch.no_grad():
        out, h, _ = agent(*args, agent.unpack_state(b["state"]), done=b["first"])
        t_out, t_h, _ = learner.target(*args, agent.unpack_state(b["state"]), done=b["first"])
        torch.manual_seed(3)
        for _ in range(2):                                             # the critic's value draws come first
            learner.distribution(learner.target, t_out).sample()
        dist = learner.distribution(agent, out[:-1])
        q_pi = learner.target.values(t_h[:-1], dist.rsample().clamp(low, high))
        w = b["new_action"] / b["new_action"].sum().clamp(min=1.0)
        entropy = dist.entropy().sum(-1)
        kl = torch.distributions.kl_divergence(dist, learner.distribution(learner.target, t_out[:-1])).sum(-1)
        saturation = (torch.relu(out[:-1].chunk(2, -1)[0].abs() - MEAN_RAW_LIMIT) ** 2).sum(-1)
        assert (saturation > 0).any() and kl.abs().max() > 1e-4
        expected = -((q_pi - eta * kl + c * entropy - saturation) * w).sum()
        q = agent.values(h[:-1], b["action"].clamp(low, high))
    torch.manual_seed(3)
    got = learner.update(b)
    assert got["policy_loss"] == pytest.approx(expected.item(), rel=1e-5)
    assert got["entropy"] == pytest.approx((entropy * w).sum().item(), rel=1e-5)
    assert got["kl"] == pytest.approx((kl * w).sum().item(), rel=1e-5)
    assert got["q"] == pytest.approx(q.mean().item(), rel=1e-5)


def test_high_level_svg0_acts_in_float32_which_the_agent_reads_back_as_its_previous_action():
    """The raw sample replay keeps and the clipped action the agent sees next are float32, one
    log density per env: a float64 action would reach the LSTM as float64 inputs and fail."""
    import numpy as np

    from hvc.algorithms.svg0_retrace import RecurrentSVG0Retrace
    from hvc.schema import SVG0RetraceConfig

    torch.manual_seed(0)
    agent = HighLevelAgent(AgentSpec(3, 0, 2, False, 16, (16, 1), critic_takes_action=True))
    learner = RecurrentSVG0Retrace(agent, 0.9, -0.3, 0.3, (0.2, 0.9), SVG0RetraceConfig())
    E = 5
    state = agent.initial_state(E)
    prev = torch.zeros(1, E, 2)
    for _ in range(2):
        out, h, state = agent(torch.randn(1, E, 3), torch.zeros(1, E, 0), torch.zeros(1, E), prev, state)
        acted = learner.act(out[0], h[0])
        assert acted.action.dtype == acted.seen.dtype == acted.send.dtype == np.float32
        assert acted.log_mu.shape == (E,) and np.abs(acted.seen).max() <= 0.3
        prev = torch.from_numpy(acted.seen)[None]


def test_a_bfloat16_image_encoder_computes_its_convolutions_in_bfloat16_and_learns_like_float32():
    """image_precision=bfloat16: the ResNet runs under autocast, its weights and gradients stay
    float32, its features and their gradients agree with float32's to bfloat16's precision."""
    torch.manual_seed(0)
    exact, fast = ImageEncoder(), ImageEncoder(precision="bfloat16")
    fast.load_state_dict(exact.state_dict())
    conv_outputs = []
    fast.body[0].register_forward_hook(lambda module, args, out: conv_outputs.append(out.dtype))
    image = torch.randint(0, 256, (4, 2, 64, 64, 3), dtype=torch.uint8)
    features = {}
    for name, encoder in (("exact", exact), ("fast", fast)):
        features[name] = encoder(image)
        features[name].square().sum().backward()
    assert conv_outputs == [torch.bfloat16] and features["fast"].dtype == torch.float32
    assert not torch.equal(features["fast"], features["exact"])  # it did compute in bfloat16
    scale = features["exact"].abs().max()
    assert (features["fast"] - features["exact"]).abs().max() < 0.05 * scale
    for (name, a), b in zip(exact.named_parameters(), fast.parameters()):
        assert b.dtype == b.grad.dtype == torch.float32, name
        cosine = torch.nn.functional.cosine_similarity(a.grad.flatten(), b.grad.flatten(), dim=0)
        assert cosine > 0.99, (name, float(cosine))
    with pytest.raises(ValueError, match="allowed: float32, bfloat16"):
        ImageEncoder(precision="float16")


def test_the_configs_image_precision_reaches_the_agent_it_builds():
    from types import SimpleNamespace

    from hvc.config import ConfigError, compose, validate
    from hvc.runtime.hl_train import build_agent

    envs = SimpleNamespace(observation_sizes={"proprio": 5, "task": 2, "image": (64, 64, 3)},
                           action_space=SimpleNamespace(discrete=True, n=7))
    for precision in ("float32", "bfloat16"):
        spec, agent, _ = build_agent(compose(["task=gaps", f"image_precision={precision}"]), envs)
        assert spec.image_precision == precision and agent.image.autocast == (precision == "bfloat16")
    with pytest.raises(ConfigError, match="image_precision='half'; allowed: float32, bfloat16"):
        validate(compose(["image_precision=half"]))
