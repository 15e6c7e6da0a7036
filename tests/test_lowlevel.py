"""Low-level experts: pre-training, the SVG(0) + Retrace losses, the library format."""
import json

import numpy as np
import pytest
import torch

from hvc.agents.mlp import GaussianPolicy, NumpyPolicy, QNetwork, gaussian_log_prob
from hvc.algorithms.svg0_retrace import Batch, SVG0Retrace
from hvc.lowlevel.library import ExpertLibrary, Expert, LibraryVersionError
from hvc.lowlevel.train import load_warm_start, pretrain
from hvc.mocap.reference import Reference

CFG = dict(gamma=0.9, retrace_lambda=1.0, kl_cost=0.5, target_update_period=3, value_samples=2, policy_lr=1e-3,
           critic_lr=1e-3)


def _batch(T=5, B=4, obs=6, act=3, seed=0):
    g = torch.Generator().manual_seed(seed)
    mask = torch.ones(T, B)
    mask[3:, 0] = 0  # an unroll that ended early
    return Batch(obs=torch.randn(T + 1, B, obs, generator=g), actions=torch.rand(T, B, act, generator=g) * 2 - 1,
                 rewards=torch.rand(T, B, generator=g), discounts=(torch.rand(T, B, generator=g) > 0.2).float(),
                 log_mu=torch.randn(T, B, generator=g), mask=mask)


def _learner(seed=0):
    torch.manual_seed(seed)
    return SVG0Retrace(GaussianPolicy(6, 3, [16], 0.1), QNetwork(6, 3, [16]), CFG)


def _independent_retrace(pol, crit, b, seed):
    """Retrace targets (Munos et al. 2016, sum form) by plain python loops from the networks
    `pol` and `crit`, with the value-sample noise of torch seed `seed` (as critic_targets draws it)."""
    torch.manual_seed(seed)
    with torch.no_grad():
        next_mean = pol.mean(b.obs[1:])
        v = torch.stack([crit(b.obs[1:], next_mean + 0.1 * torch.randn_like(next_mean)) for _ in range(2)]).mean(0)
        q = crit(b.obs[:-1], b.actions)
        c = torch.clamp(torch.exp(gaussian_log_prob(b.actions, pol.mean(b.obs[:-1]), 0.1) - b.log_mu), max=1) * b.mask
    T, B = b.rewards.shape
    expected = np.zeros((T, B))
    for j in range(B):
        for t in range(T):
            total, w = float(q[t, j]), 1.0
            for k in range(t, T):
                if k > t:
                    w *= 0.9 * float(b.discounts[k - 1, j]) * float(c[k, j])
                total += w * (float(b.rewards[k, j]) + 0.9 * float(b.discounts[k, j]) * float(v[k, j]) - float(q[k, j]))
            expected[t, j] = total
    return expected


def test_critic_loss_matches_an_independent_retrace_computation():
    learner, b = _learner(), _batch()
    torch.manual_seed(123)
    targets = learner.critic_targets(b)
    expected = _independent_retrace(learner.target_policy, learner.target_critic, b, 123)
    np.testing.assert_allclose(targets.numpy(), expected, atol=1e-5)


def test_critic_regresses_on_targets_from_the_target_networks_once_they_have_diverged():
    """Retrace targets come from the target critic and target policy (Appendix A), which lag
    the online ones; right after a refresh both are equal, so only diverged networks can show
    a target computed with the online critic (a moving target the critic chases)."""
    learner, b = _learner(), _batch()
    g = torch.Generator().manual_seed(5)
    with torch.no_grad():  # online networks moved on since the last refresh
        for p in (*learner.critic.parameters(), *learner.policy.parameters()):
            p.add_(0.3 * torch.randn(p.shape, generator=g))
    from_target = _independent_retrace(learner.target_policy, learner.target_critic, b, 123)
    from_online = _independent_retrace(learner.policy, learner.critic, b, 123)
    assert np.abs(from_target - from_online).max() > 0.1  # the networks did diverge
    torch.manual_seed(123)
    np.testing.assert_allclose(learner.critic_targets(b).numpy(), from_target, atol=1e-5)
    # and the update's critic loss is the online Q's error against those targets
    with torch.no_grad():
        q = learner.critic(b.obs[:-1], b.actions).numpy()
    w = (b.mask / b.mask.sum()).numpy()
    torch.manual_seed(123)
    info = learner.update(b)
    assert info["critic_loss"] == pytest.approx(float(0.5 * ((q - from_target) ** 2 * w).sum()), rel=1e-5)


def test_policy_loss_is_svg0_with_a_kl_to_the_target_policy():
    learner, b = _learner(), _batch()
    with torch.no_grad():  # move the policy away from its target so the KL term is non-zero
        for p in learner.policy.parameters():
            p.add_(0.05)
    obs = b.obs[:-1]
    torch.manual_seed(7)
    learner.critic_targets(b)  # consumes the same random numbers as update() does first
    with torch.no_grad():
        mean = learner.policy.mean(obs)
        action = mean + 0.1 * torch.randn_like(mean)
        q_pi = learner.target_critic(obs, action)
        kl = ((mean - learner.target_policy.mean(obs)) ** 2).sum(-1) / (2 * 0.01)
        w = b.mask / b.mask.sum()
        expected = float(((-q_pi + 0.5 * kl) * w).sum())
    torch.manual_seed(7)
    info = learner.update(b)
    assert info["policy_loss"] == pytest.approx(expected, rel=1e-5)
    assert info["kl"] > 0


def test_kickstarting_adds_the_teachers_kl_and_pulls_the_policy_to_them():
    """kickstart_cost KL(pi || teacher) joins the policy loss at the teacher's states, and
    updates with it bring the policy's mean there to the teacher's actions."""
    b = _batch()
    g = torch.Generator().manual_seed(3)
    states = torch.randn(64, 6, generator=g)
    teacher = (states, 0.5 * torch.tanh(states[:, :3]))  # a teacher the small policy can match
    plain = _learner()
    torch.manual_seed(7)
    without = plain.update(b)["policy_loss"]
    torch.manual_seed(0)
    taught = SVG0Retrace(GaussianPolicy(6, 3, [16], 0.1), QNetwork(6, 3, [16]), {**CFG, "kickstart_cost": 1.0})
    frozen = [p.clone() for p in taught.policy.parameters()]
    taught.update(b, train_policy=False, teacher=teacher)  # a critic warming up: the teachers move nothing
    assert all(torch.equal(a, p) for a, p in zip(frozen, taught.policy.parameters()))
    taught.load_state_dict(_learner().state_dict())  # as before that step
    with torch.no_grad():
        teacher_kl = float((((taught.policy.mean(teacher[0]) - teacher[1]) ** 2).sum(-1) / (2 * 0.01)).mean())
    torch.manual_seed(7)
    info = taught.update(b, teacher=teacher)
    assert info["teacher_kl"] == pytest.approx(teacher_kl, rel=1e-5)
    assert info["policy_loss"] == pytest.approx(without + 1.0 * teacher_kl, rel=1e-4)
    for _ in range(200):
        last = taught.update(b, teacher=teacher)["teacher_kl"]
    for _ in range(200):
        plain.update(b)
    with torch.no_grad():
        untaught = float((((plain.policy.mean(teacher[0]) - teacher[1]) ** 2).sum(-1) / (2 * 0.01)).mean())
    assert last < 0.1 * teacher_kl and last < 0.1 * untaught


def test_targets_refresh_every_period_and_learning_reduces_critic_loss():
    learner, b = _learner(), _batch()
    learner.target_update_period = 10**9  # fixed targets: the critic regresses onto them
    first = learner.update(b)["critic_loss"]
    for _ in range(300):
        last = learner.update(b)["critic_loss"]
    assert last < 0.5 * first
    learner.target_update_period = 3
    learner.steps = 2
    learner.update(b)  # step 3: a multiple of target_update_period
    for p, t in zip(learner.critic.parameters(), learner.target_critic.parameters()):
        torch.testing.assert_close(p, t)


def test_resuming_keeps_adams_moments_but_takes_the_configured_learning_rates():
    learner = _learner()
    learner.update(_batch())
    state = learner.state_dict()
    resumed = SVG0Retrace(GaussianPolicy(6, 3, [16], 0.1), QNetwork(6, 3, [16]),
                          {**CFG, "policy_lr": 3e-4, "critic_lr": 2e-4})
    resumed.load_state_dict(state)
    assert [g["lr"] for g in resumed.policy_opt.param_groups] == [3e-4]
    assert [g["lr"] for g in resumed.critic_opt.param_groups] == [2e-4]
    saved = state["policy_opt"]["state"][0]["exp_avg"]
    torch.testing.assert_close(resumed.policy_opt.state_dict()["state"][0]["exp_avg"], saved)


def test_critic_only_updates_leave_the_policy_alone():
    learner, b = _learner(), _batch()
    policy, critic = ([p.detach().clone() for p in m.parameters()] for m in (learner.policy, learner.critic))
    learner.update(b, train_policy=False)
    assert all(torch.equal(a, p) for a, p in zip(policy, learner.policy.parameters()))
    assert not all(torch.equal(a, p) for a, p in zip(critic, learner.critic.parameters()))
    learner.update(b)
    assert not all(torch.equal(a, p) for a, p in zip(policy, learner.policy.parameters()))


def test_warm_start_acts_as_the_expert_whatever_the_new_inputs():
    """A steerable policy started from the run expert: the rate input starts ignored."""
    torch.manual_seed(0)
    expert = GaussianPolicy(6, 3, [16, 16], 0.1)
    expert.normalizer.set(np.arange(6.0), np.full(6, 2.0))
    expert_np = NumpyPolicy.from_torch(expert)
    policy = GaussianPolicy(8, 3, [16, 16], 0.1)
    load_warm_start(policy, expert_np, np.full(8, 5.0), np.full(8, 3.0))
    x = np.random.default_rng(2).normal(size=(10, 8)).astype(np.float32) * 4
    np.testing.assert_allclose(policy.mean(torch.from_numpy(x)).detach().numpy(), expert_np(x[:, :6]), atol=1e-6)
    np.testing.assert_allclose(policy.normalizer.mean.numpy(), [0, 1, 2, 3, 4, 5, 5, 5])  # the new inputs' own
    np.testing.assert_allclose(policy.normalizer.std.numpy(), [2] * 6 + [3, 3])
    with pytest.raises(ValueError, match="lowlevel.hidden"):
        load_warm_start(GaussianPolicy(8, 3, [32, 16], 0.1), expert_np, np.zeros(8), np.ones(8))
    with pytest.raises(ValueError, match="lowlevel.hidden"):  # fewer inputs than the expert's
        load_warm_start(GaussianPolicy(5, 3, [16, 16], 0.1), expert_np, np.zeros(5), np.ones(5))


def test_policy_reads_only_its_inputs_of_a_wider_critic_state():
    torch.manual_seed(0)
    policy = GaussianPolicy(6, 3, [16], 0.1)
    state = torch.randn(5, 9)
    changed = state.clone()
    changed[:, 6:] += 3.0  # the critic's extra columns
    assert torch.equal(policy.mean(state), policy.mean(state[:, :6]))
    assert torch.equal(policy.mean(state), policy.mean(changed))
    # a learner whose critic sees the wider state updates both networks
    learner = SVG0Retrace(policy, QNetwork(9, 3, [16]), CFG)
    before = [p.clone() for p in policy.parameters()]
    learner.update(_batch(obs=9))
    assert any(not torch.equal(a, b) for a, b in zip(before, policy.parameters()))


def test_pretraining_reduces_the_action_error():
    rng = np.random.default_rng(0)
    obs = rng.normal(size=(200, 6)).astype(np.float32)
    actions = np.tanh(obs[:, :3] * 0.5).astype(np.float32)
    torch.manual_seed(0)
    policy = GaussianPolicy(6, 3, [32, 32], 0.1)
    before, after = pretrain(policy, obs, actions, steps=300, lr=3e-3, batch=64, rng=rng)
    assert after < 0.2 * before


def test_numpy_actor_equals_torch_policy():
    torch.manual_seed(0)
    policy = GaussianPolicy(6, 3, [16, 16], 0.1)
    policy.normalizer.set(np.arange(6.0), np.full(6, 2.0))
    x = np.random.default_rng(1).normal(size=6).astype(np.float32)
    np.testing.assert_allclose(NumpyPolicy.from_torch(policy)(x), policy.mean(torch.from_numpy(x)).detach().numpy(),
                               atol=1e-6)


def test_fixing_a_policys_last_inputs_folds_them_exactly_into_its_first_bias():
    torch.manual_seed(0)
    policy = GaussianPolicy(9, 3, [16, 16], 0.1)
    policy.normalizer.set(np.arange(9.0), np.linspace(0.5, 3.0, 9))
    full = NumpyPolicy.from_torch(policy)
    code = np.array([0.0, 1.0, 0.0], np.float32)
    held = full.with_fixed_inputs(code)
    x = np.random.default_rng(1).normal(size=(4, 6)).astype(np.float32)
    np.testing.assert_allclose(held(x), full(np.concatenate([x, np.tile(code, (4, 1))], 1)), atol=1e-6)
    np.testing.assert_allclose(held(x[0]), full(np.concatenate([x[0], code])), atol=1e-6)  # the 1-D path
    assert held.weights[0].shape == (6, 16)
    assert not np.allclose(held(x), full.with_fixed_inputs(np.eye(3, dtype=np.float32)[0])(x))  # the code matters


def test_a_switching_library_gives_one_expert_per_behaviour_with_its_code_held():
    from hvc.lowlevel.library import shipped_library

    switching = ExpertLibrary.load(shipped_library("switching"))
    experts = switching.behaviour_experts()
    assert [e.entry for e in experts] == switching.meta["switching_entries"]
    assert [e.reference for e in experts] == switching.behaviours
    x = np.random.default_rng(0).normal(size=(3, experts[0].policy.weights[0].shape[0])).astype(np.float32)
    for b, expert in enumerate(experts):  # proprioception and phase, then behaviour b's 1-of-k code
        code = np.tile(np.eye(len(experts), dtype=np.float32)[b], (3, 1))
        np.testing.assert_allclose(expert.act(x), switching.experts[0].act(np.concatenate([x, code], 1)), atol=1e-5)
    clip_experts = ExpertLibrary.load(shipped_library())
    assert clip_experts.behaviour_experts() is clip_experts.experts


def _library():
    torch.manual_seed(0)
    n = 5
    ref = Reference("CMU_000_01", 0.03, False, *(np.random.default_rng(i).normal(size=s) for i, s in enumerate(
        [(n, 56), (n, 56), (n, 3), (n, 4), (n, 3), (n, 3), (n, 4, 3)])), np.linspace(0, 1, n))
    policy = NumpyPolicy.from_torch(GaussianPolicy(8, 56, [16], 0.1))
    return ExpertLibrary([Expert({"id": "CMU_000_01", "behaviour": "stand"}, policy, ref, {"eval_reward": 0.5})],
                         {"clip_set": "test"})


def test_library_round_trip_without_pickle(tmp_path):
    lib = _library()
    path = lib.save(tmp_path / "lib.npz")
    loaded = ExpertLibrary.load(path)
    x = np.random.default_rng(0).normal(size=8).astype(np.float32)
    np.testing.assert_allclose(loaded.experts[0].act(x), lib.experts[0].act(x), atol=1e-6)
    np.testing.assert_allclose(loaded.experts[0].reference.end_effectors, lib.experts[0].reference.end_effectors,
                               atol=1e-6)
    assert loaded.clip_ids == ["CMU_000_01"] and loaded.experts[0].scores == {"eval_reward": 0.5}
    assert loaded.behaviours == [] and "behaviours" not in loaded.meta
    # a switching library carries its behaviours' references (offline use)
    lib.behaviours = [lib.experts[0].reference.segment(0, 3), lib.experts[0].reference]
    loaded = ExpertLibrary.load(lib.save(tmp_path / "switching.npz"))
    assert [b.num_steps for b in loaded.behaviours] == [3, 5]
    np.testing.assert_allclose(loaded.behaviours[1].joints, lib.behaviours[1].joints, atol=1e-6)
    with np.load(path, allow_pickle=False) as data:  # plain arrays: no pickle needed anywhere
        assert json.loads(str(data["meta"]))["version"] == 1


def test_a_cut_library_keeps_each_experts_env_steps(tmp_path):
    one = _library().experts[0]
    two = Expert({**one.entry, "id": "CMU_000_02", "behaviour": "run"}, one.policy, one.reference)
    lib = ExpertLibrary([one, two], {"provenance": {"env_steps": [100, 200]}})
    cut = ExpertLibrary.load(lib.subset([1]).save(tmp_path / "run_only.npz"))
    assert cut.clip_ids == ["CMU_000_02"] and cut.meta["provenance"]["env_steps"] == [200]
    with pytest.raises(ValueError, match="2 entries for 1 experts"):  # cut by hand: the steps would pair wrongly
        ExpertLibrary([two], lib.meta).save(tmp_path / "bad.npz")


def test_library_from_another_version_fails_clearly(tmp_path):
    path = _library().save(tmp_path / "lib.npz")
    with np.load(path) as data:
        arrays = dict(data)
    meta = json.loads(str(arrays["meta"]))
    meta["version"] = 99
    arrays["meta"] = np.array(json.dumps(meta))
    np.savez(tmp_path / "old.npz", **arrays)
    with pytest.raises(LibraryVersionError, match="format version 99"):
        ExpertLibrary.load(tmp_path / "old.npz")


@pytest.mark.skipif(not __import__("hvc.mocap.source", fromlist=["x"]).SHARED_CLIPS.is_dir(),
                    reason="offline CMU clips not found")
@pytest.mark.parametrize("privileged", [False, True])
def test_expert_training_resumes_from_its_checkpoint(tmp_path, privileged):
    import pandas as pd
    from omegaconf import OmegaConf

    from hvc.config import compose
    from hvc.lowlevel.train import train_expert
    from hvc.runtime.env_config import env_dicts

    cfg = compose(["stage=lowlevel", "task=tracking", "clip=left_turn", "lowlevel.bc_steps=20",
                   "lowlevel.bc_rollouts=2", "lowlevel.min_replay_unrolls=5", "lowlevel.eval_episodes=1", "lowlevel.log_every=100",
                   "lowlevel.batch_size=4", f"lowlevel.critic_sees_reference={str(privileged).lower()}"])
    task, body, render = env_dicts(cfg)
    ll = OmegaConf.to_container(cfg.lowlevel)
    train_expert(task, body, render, ll, tmp_path, total_steps=200)
    first = torch.load(tmp_path / "checkpoint.pt", weights_only=True)  # no pickle needed
    assert 200 <= first["counters"]["env_steps"] < 210 and first["learner"]["steps"] > 0
    policy_inputs = first["learner"]["policy"]["normalizer.mean"].shape[0]
    critic_inputs = first["learner"]["critic"]["normalizer.mean"].shape[0]
    assert critic_inputs == policy_inputs + (7 if privileged else 0)  # the extras reach the critic only
    assert first["replay"]["obs"].shape[-1] == critic_inputs
    result = train_expert(task, body, render, ll, tmp_path, total_steps=400)
    second = torch.load(tmp_path / "checkpoint.pt", weights_only=True)
    assert 400 <= second["counters"]["env_steps"] < 410
    assert second["learner"]["steps"] > first["learner"]["steps"]
    metrics = pd.read_csv(tmp_path / "metrics.csv")
    assert (metrics.key == "bc_mse_after").sum() == 1          # pre-training ran once
    assert (metrics.key == "eval_reward").sum() == 3           # after pre-training, at 200 (kept), at 400
    assert metrics.env_steps.max() >= 400 and 0 <= result["eval_completion"] <= 1


@pytest.mark.skipif(not __import__("hvc.mocap.source", fromlist=["x"]).SHARED_CLIPS.is_dir(),
                    reason="offline CMU clips not found")
def test_a_packed_expert_run_continues_elsewhere_with_its_replay_refilled(tmp_path):
    """hvc.io.pack: the checkpoint travels without its replay; unpacked in another dir, the
    expert continues from its counters and weights, refills its replay, and learns on."""
    import tarfile

    import pandas as pd
    from omegaconf import OmegaConf

    from hvc.config import compose
    from hvc.io.pack import pack_run
    from hvc.lowlevel.train import train_expert
    from hvc.runtime.env_config import env_dicts

    cfg = compose(["stage=lowlevel", "task=tracking", "clip=left_turn", "lowlevel.bc_steps=20",
                   "lowlevel.bc_rollouts=2", "lowlevel.min_replay_unrolls=5", "lowlevel.eval_episodes=1",
                   "lowlevel.log_every=100", "lowlevel.batch_size=4"])
    task, body, render = env_dicts(cfg)
    ll = OmegaConf.to_container(cfg.lowlevel)
    expert = tmp_path / "run" / "experts" / "0_left_turn"
    train_expert(task, body, render, ll, expert, total_steps=200)
    filled = int(torch.load(expert / "checkpoint.pt", weights_only=True)["replay"]["size"])
    (tmp_path / "run" / ".lock").write_text("1")
    packed = pack_run(tmp_path / "run", tmp_path / "run.tar.gz")
    assert packed["checkpoints_without_replay"] == 1
    with tarfile.open(tmp_path / "run.tar.gz") as tar:
        assert not [n for n in tar.getnames() if n.endswith(".lock")]
        tar.extractall(tmp_path / "moved", filter="data")
    moved = tmp_path / "moved" / "run" / "experts" / "0_left_turn"
    before = torch.load(moved / "checkpoint.pt", weights_only=True)
    assert "replay" not in before and before["counters"]["env_steps"] >= 200
    train_expert(task, body, render, ll, moved, total_steps=400)
    after = torch.load(moved / "checkpoint.pt", weights_only=True)
    assert 400 <= after["counters"]["env_steps"] < 410 and after["learner"]["steps"] > before["learner"]["steps"]
    # the replay restarted empty and refilled from the second 200 steps only (kept, it would hold
    # both: about twice; falls pad unrolls, so the second part's count varies a little)
    assert 0 < int(after["replay"]["size"]) < 1.5 * filled
    metrics = pd.read_csv(moved / "metrics.csv")
    assert (metrics.key == "bc_mse_after").sum() == 1  # no pre-training again: the weights went on


@pytest.mark.skipif(not __import__("hvc.mocap.source", fromlist=["x"]).SHARED_CLIPS.is_dir(),
                    reason="offline CMU clips not found")
def test_final_evaluation_scores_by_contact_whatever_termination_trained(tmp_path):
    import pandas as pd
    from omegaconf import OmegaConf

    from hvc.config import compose
    from hvc.lowlevel.train import train_expert
    from hvc.runtime.env_config import env_dicts

    cfg = compose(["stage=lowlevel", "task=tracking", "clip=stand", "task.termination_error=1e-9",
                   "lowlevel.bc_steps=20", "lowlevel.bc_rollouts=2", "lowlevel.min_replay_unrolls=5",
                   "lowlevel.eval_episodes=3", "lowlevel.log_every=50", "lowlevel.batch_size=4"])
    task, body, render = env_dicts(cfg)
    result = train_expert(task, body, render, OmegaConf.to_container(cfg.lowlevel), tmp_path, total_steps=60)
    training = pd.read_csv(tmp_path / "metrics.csv").query("key == 'episode_return'")
    assert (training.value < 1.0).all()        # training episodes strayed and failed at their first step
    assert result["eval_steps"] > 5             # the evaluation let the stand expert run on


def test_a_nan_loss_leaves_the_expert_and_its_critic_unchanged():
    from hvc.errors import NonFiniteLoss

    learner, b = _learner(), _batch()
    before = {k: v.clone() for k, v in learner.state_dict()["critic"].items()}
    b.rewards[2, 1] = float("inf")
    with pytest.raises(NonFiniteLoss):
        learner.update(b)
    assert all(torch.equal(before[k], v) for k, v in learner.critic.state_dict().items())


def test_the_actor_samples_its_gaussian_and_reports_that_samples_log_density():
    """act(mean): mean + sigma * noise from the actor's generator (float32, as the env gets it),
    and log mu, the Gaussian log density of that very sample, which Retrace's traces divide by."""
    learner = _learner()
    sigma = learner.policy.sigma
    mean = np.array([0.3, -1.2, 2.0], np.float32)
    for seed in range(5):
        action, log_mu = learner.act(mean, np.random.default_rng(seed))
        noise = np.random.default_rng(seed).standard_normal(3).astype(np.float32)
        np.testing.assert_allclose(action, mean + sigma * noise, rtol=1e-6)
        assert action.dtype == np.float32
        density = torch.distributions.Normal(torch.from_numpy(mean).double(), float(sigma)).log_prob(
            torch.from_numpy(action).double()).sum().item()
        assert log_mu == pytest.approx(density, rel=1e-5)


def test_a_bad_policy_loss_alone_stops_the_update_before_the_critic_moves(monkeypatch):
    """The critic steps first; a non-finite policy loss must stop both, naming the two losses."""
    import hvc.algorithms.svg0_retrace as svg0
    from hvc.errors import NonFiniteLoss

    learner, b = _learner(), _batch()
    before = {k: v.clone() for k, v in learner.critic.state_dict().items()}
    monkeypatch.setattr(svg0, "svg0_policy_loss", lambda *args: torch.tensor(float("nan"), requires_grad=True))
    with pytest.raises(NonFiniteLoss, match=r"^non-finite loss: critic [0-9.e-]+, policy nan$"):
        learner.update(b)
    assert all(torch.equal(before[k], v) for k, v in learner.critic.state_dict().items())


def test_the_low_level_refreshes_its_targets_every_period_updates():
    learner = _learner()  # target_update_period=3
    same = lambda: all(torch.equal(a, b) for net, target in ((learner.policy, learner.target_policy),  # noqa: E731
                                                            (learner.critic, learner.target_critic))
                       for a, b in zip(net.state_dict().values(), target.state_dict().values()))
    history = []
    for seed in range(6):
        learner.update(_batch(seed=seed))
        history.append(same())
    assert history == [False, False, True, False, False, True]


@pytest.mark.parametrize("valid_steps", ["many", "one"])
def test_the_low_level_update_reports_the_weighted_kl_and_q_and_its_critic_loss(valid_steps):
    """Metrics named as the trainer logs them, each the mask-weighted mean over the batch's
    valid steps before the networks move; with a single valid step its weight is 1, so the
    critic loss is that step's half squared error alone."""
    from hvc.algorithms.svg0_retrace import kl_fixed_sigma

    learner, b = _learner(), _batch()
    if valid_steps == "one":
        b.mask.zero_()
        b.mask[1, 2] = 1.0
    with torch.no_grad():
        for p in learner.policy.parameters():  # online and target policies apart: a KL > 0
            p.add_(0.3 * torch.randn_like(p))
        weight = b.mask / b.mask.sum()
        q = learner.critic(b.obs[:-1], b.actions)
        kl = kl_fixed_sigma(learner.policy.mean(b.obs[:-1]), learner.target_policy.mean(b.obs[:-1]), 0.1)
    torch.manual_seed(5)
    targets = learner.critic_targets(b)
    torch.manual_seed(5)
    info = learner.update(b)
    assert set(info) == {"critic_loss", "policy_loss", "kl", "q"}
    assert info["q"] == pytest.approx(float((q * weight).sum()), rel=1e-5)
    assert info["kl"] == pytest.approx(float((kl * weight).sum()), rel=1e-5) and info["kl"] > 0
    assert info["critic_loss"] == pytest.approx(float(0.5 * ((q - targets) ** 2 * weight).sum()), rel=1e-5)
    if valid_steps == "one":
        assert info["critic_loss"] == pytest.approx(0.5 * float(q[1, 2] - targets[1, 2]) ** 2, rel=1e-5)
