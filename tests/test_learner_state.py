"""A learner restored from its checkpoint state continues exactly as if it had not stopped:
weights, target copies, optimiser moments and the update count (the target refresh
schedule) come back, while the learning rate is the configured one (issue 21: resume)."""
import json

import numpy as np
import pytest
import torch

from hvc.agents.network import AgentSpec, HighLevelAgent
from hvc.algorithms.svg0_retrace import RecurrentSVG0Retrace
from hvc.algorithms.vtrace import VTraceLearner
from hvc.algorithms.wolpertinger import WolpertingerLearner
from hvc.config import compose
from hvc.io.checkpoint import random_states, restore_random_states
from hvc.schema import SVG0RetraceConfig, VTraceConfig, WolpertingerConfig

T, B = 4, 3


def _batch(discrete: bool, seed: int = 0) -> dict:
    g = torch.Generator().manual_seed(seed)
    action = (torch.randint(0, 4, (T, B), generator=g) if discrete else torch.rand(T, B, 2, generator=g) * 2 - 1)
    prev = torch.zeros(T + 1, B, dtype=torch.long) if discrete else torch.zeros(T + 1, B, 2)
    return {"proprio": torch.randn(T + 1, B, 3, generator=g), "task": torch.zeros(T + 1, B, 0),
            "prev_reward": torch.zeros(T + 1, B), "prev_action": prev, "first": torch.zeros(T + 1, B),
            "action": action, "query": torch.rand(T, B, 2, generator=g) * 2 - 1,
            "log_mu": -torch.rand(T, B, generator=g), "reward": torch.rand(T, B, generator=g),
            "discount": torch.ones(T, B), "new_action": torch.ones(T, B), "state": torch.zeros(B, 4, 128)}


class _Keys:
    keys = np.random.default_rng(0).normal(size=(6, 2)).astype(np.float32)

    def nearest(self, query):
        return np.arange(len(self.keys))


def _learner(kind: str, seed: int, learning_rate: float = 1e-2):
    torch.manual_seed(seed)
    discrete = kind == "vtrace"
    agent = HighLevelAgent(AgentSpec(3, 0, 4 if discrete else 2, discrete, 16, (16, 1),
                                     critic_takes_action=not discrete))
    if kind == "vtrace":
        return VTraceLearner(agent, 0.9, VTraceConfig(learning_rate=learning_rate))
    if kind == "svg0":
        return RecurrentSVG0Retrace(agent, 0.9, -1.0, 1.0, (0.1, 1.0),
                                    SVG0RetraceConfig(learning_rate=learning_rate, target_update_period=5))
    return WolpertingerLearner(agent, 0.9, -3.0, 3.0, (0.1, 1.0), _Keys(), 1.0,
                               WolpertingerConfig(learning_rate=learning_rate, target_update_period=5), seed=seed)


def _tensors(module: torch.nn.Module) -> list[torch.Tensor]:
    return [t.clone() for t in module.state_dict().values()]


@pytest.mark.parametrize("kind", ["vtrace", "svg0", "wolpertinger"])
def test_a_restored_learner_continues_as_the_uninterrupted_one(kind, tmp_path):
    batch = _batch(kind == "vtrace")
    original = _learner(kind, seed=0)
    for _ in range(3):
        original.update(batch)
    path = tmp_path / "learner.pt"
    torch.save(original.state_dict(), path)
    restored = _learner(kind, seed=1)  # other initial weights: everything must come from the state
    restored.load_state_dict(torch.load(path, weights_only=True))
    assert restored.steps == original.steps == 3
    for step in range(3):  # steps 4-6 cross the target refresh at step 5
        torch.manual_seed(10 + step)
        a = original.update(batch)
        torch.manual_seed(10 + step)
        b = restored.update(batch)
        assert a == pytest.approx(b, rel=1e-6, abs=1e-7), step
    for x, y in zip(_tensors(original.agent), _tensors(restored.agent)):
        torch.testing.assert_close(x, y)
    if kind != "vtrace":
        for x, y in zip(_tensors(original.target), _tensors(restored.target)):
            torch.testing.assert_close(x, y)


def test_a_fresh_optimiser_would_not_continue_the_same(tmp_path):
    """The test above can fail: without the optimiser's moments the next update differs."""
    batch = _batch(True)
    original = _learner("vtrace", seed=0)
    for _ in range(3):
        original.update(batch)
    state = original.state_dict()
    restored = _learner("vtrace", seed=1)
    restored.agent.load_state_dict(state["agent"])  # the weights alone
    torch.manual_seed(0)
    a = original.update(batch)
    torch.manual_seed(0)
    b = restored.update(batch)
    assert a["loss"] == pytest.approx(b["loss"])  # same weights, same loss ...
    assert any(not torch.equal(x, y) for x, y in zip(_tensors(original.agent), _tensors(restored.agent)))


@pytest.mark.parametrize("kind", ["vtrace", "svg0"])
def test_a_restored_learner_keeps_the_configured_learning_rate(kind):
    original = _learner(kind, seed=0, learning_rate=1e-2)
    original.update(_batch(kind == "vtrace"))
    restored = _learner(kind, seed=0, learning_rate=3e-4)  # resumed with algorithm.learning_rate=3e-4
    restored.load_state_dict(original.state_dict())
    assert [g["lr"] for g in restored.optimizer.param_groups] == [3e-4]
    assert restored.optimizer.state_dict()["state"]  # ... with the saved moments


def test_wolpertinger_resumes_its_selection_stream():
    """The Boltzmann choice among the nearest keys draws from the learner's own generator."""
    original = _learner("wolpertinger", seed=0)
    policy_out, h = torch.zeros(B, 4), torch.zeros(B, 16)
    original.act(policy_out, h)
    state = json.loads(json.dumps(original.state_dict()["selection_rng"]))
    restored = _learner("wolpertinger", seed=7)
    restored.load_state_dict({**original.state_dict(), "selection_rng": state})
    torch.manual_seed(3)
    a = original.act(policy_out, h).send
    torch.manual_seed(3)
    b = restored.act(policy_out, h).send
    np.testing.assert_array_equal(a, b)


def test_random_states_restore_every_stream():
    rng, other = np.random.default_rng(0), np.random.default_rng(1)
    rng.random(5), torch.rand(3)
    saved = random_states({"rng": rng, "env_rng": other})
    expected = rng.random(4), other.random(4), torch.rand(4)
    restored_rng, restored_other = np.random.default_rng(9), np.random.default_rng(9)
    torch.manual_seed(9)
    restore_random_states(saved, {"rng": restored_rng, "env_rng": restored_other})
    np.testing.assert_array_equal(restored_rng.random(4), expected[0])
    np.testing.assert_array_equal(restored_other.random(4), expected[1])
    torch.testing.assert_close(torch.rand(4), expected[2])


def test_load_checkpoint_refuses_agents_from_before_input_normalisation(tmp_path, caplog):
    from hvc.errors import HvcUserError
    from hvc.runtime.hl_train import load_checkpoint

    agent = _learner("vtrace", seed=0).agent.state_dict()
    torch.save({"agent": agent, "counters": {"env_steps": 5}}, tmp_path / "good.pt")
    assert load_checkpoint(tmp_path / "good.pt")["counters"] == {"env_steps": 5}
    torch.save({"agent": {k: v for k, v in agent.items() if not k.startswith("normalizer.")}}, tmp_path / "old.pt")
    with pytest.raises(HvcUserError, match="older hvc"):
        load_checkpoint(tmp_path / "old.pt")
    torch.save({"agent": {k: v for k, v in agent.items() if k != "normalizer.var_floor"}}, tmp_path / "floor.pt")
    with caplog.at_level("WARNING"):
        load_checkpoint(tmp_path / "good.pt")
        assert not caplog.records  # a checkpoint with its floor loads quietly
        load_checkpoint(tmp_path / "floor.pt")
    assert len(caplog.records) == 1
    assert caplog.records[0].getMessage() == (
        f"{tmp_path / 'floor.pt'} does not record its input normaliser's variance floor; assuming 0.01 "
        f"(hvc since 2026-12-01 20:17; 1e-6 before)")


def test_a_cuda_run_saves_and_restores_its_device_stream_and_a_cpu_run_leaves_it(monkeypatch):
    """The CUDA stream's plumbing, without a GPU: torch.cuda's get/set are stand-ins here."""
    calls = []
    monkeypatch.setattr(torch.cuda, "get_rng_state",
                        lambda device: calls.append(("get", device)) or torch.tensor([7], dtype=torch.uint8))
    monkeypatch.setattr(torch.cuda, "set_rng_state", lambda state, device: calls.append(("set", state.tolist(), device)))
    rng, gpu = np.random.default_rng(0), torch.device("cuda:1")
    saved = random_states({"rng": rng}, gpu)
    assert saved["cuda_rng"].tolist() == [7] and calls == [("get", gpu)]
    restore_random_states(saved, {"rng": rng}, gpu)
    assert calls[-1] == ("set", [7], gpu)
    calls.clear()
    on_cpu = random_states({"rng": rng}, torch.device("cpu"))
    assert "cuda_rng" not in on_cpu
    restore_random_states({**on_cpu, "cuda_rng": torch.tensor([1])}, {"rng": rng}, torch.device("cpu"))
    restore_random_states(on_cpu, {"rng": rng}, gpu)  # a CPU run's checkpoint resumed on a GPU: no stream to set
    assert calls == []


@pytest.mark.parametrize("kind", ["vtrace", "svg0", "wolpertinger"])
def test_a_checkpoint_from_before_learner_steps_takes_the_update_count(kind):
    """Checkpoints written before the learners saved their own step count (the Fig. 6 runs):
    the count of updates stands for it, so target refreshes keep their schedule."""
    state = _learner(kind, seed=0).state_dict()
    del state["learner_steps"]
    restored = _learner(kind, seed=1)
    restored.load_state_dict({**state, "counters": {"updates": 7, "env_steps": 70, "episodes": 1}})
    assert restored.steps == 7
    fresh = _learner(kind, seed=1)
    fresh.load_state_dict(state)  # no counters either: from zero
    assert fresh.steps == 0


def test_the_learners_take_their_hyperparameters_from_the_typed_config():
    """One declaration (hvc/schema.py) feeds config and learner: an override reaches the learner,
    and what the YAML leaves out is the schema's default, not a second default in code."""
    from hvc.agents.network import AgentSpec, HighLevelAgent
    from hvc.algorithms.svg0_retrace import RecurrentSVG0Retrace
    from hvc.algorithms.vtrace import VTraceLearner
    from hvc.envs.spaces import ActionSpace
    from hvc.schema import SVG0RetraceConfig

    continuous = HighLevelAgent(AgentSpec(3, 0, 1, False, 16, (16, 1), critic_takes_action=True))
    cfg = compose(["controller=steerable", "algorithm.entropy_cost=0.5", "controller.sigma_clip=[0.2,0.7]"])
    learner = RecurrentSVG0Retrace.from_config(continuous, cfg, ActionSpace(discrete=False, size=1, low=-1, high=1))
    assert (learner.entropy_cost, learner.sigma_clip, (learner.low, learner.high)) == (0.5, (0.2, 0.7), (-1.5, 1.5))
    assert learner.period == SVG0RetraceConfig.target_update_period and learner.gamma == cfg.task.agent.gamma
    discrete = HighLevelAgent(AgentSpec(3, 0, 4, True, 16, (16, 1)))
    vtrace = VTraceLearner.from_config(discrete, compose(["algorithm.rho_clip=2", "algorithm.learning_rate=3e-3"]))
    assert vtrace.hp.rho_clip == 2.0 and vtrace.optimizer.param_groups[0]["lr"] == 3e-3
