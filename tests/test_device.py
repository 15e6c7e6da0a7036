"""`device=`: the high-level learner on a GPU where there is one, the same losses as on the CPU."""
import copy

import numpy as np
import pytest
import torch

from hvc.config import ConfigError
from hvc.runtime.device import torch_device


def test_device_names_resolve_or_fail_in_one_line():
    assert torch_device("cpu") == torch.device("cpu")
    assert torch_device("auto").type == ("cuda" if torch.cuda.is_available() else "cpu")
    with pytest.raises(ConfigError, match="device=gpu is not a device; allowed: auto, cpu, cuda, cuda:N"):
        torch_device("gpu")
    if not torch.cuda.is_available():
        with pytest.raises(ConfigError, match="device=cuda:1: .* sees no CUDA device"):
            torch_device("cuda:1")


def _host_noise(monkeypatch):
    """Gaussian noise drawn on the CPU whatever the device, so both devices see the same samples."""
    import torch.distributions.normal as normal

    draw = normal._standard_normal
    monkeypatch.setattr(normal, "_standard_normal",
                        lambda shape, dtype, device: draw(shape, dtype=dtype, device="cpu").to(device))
    monkeypatch.setattr(normal.Normal, "sample", lambda self, shape=torch.Size(): self.rsample(shape).detach())


def _learner_losses(device: str, steps: int = 3) -> list[dict[str, float]]:
    """A few SVG(0) + Retrace updates of the high-level agent on one fixed batch."""

    from hvc.agents.network import AgentSpec, HighLevelAgent
    from hvc.algorithms.svg0_retrace import RecurrentSVG0Retrace
    from hvc.schema import SVG0RetraceConfig

    torch.manual_seed(0)
    spec = AgentSpec(proprio_size=5, task_size=3, action_size=2, discrete=False, lstm_size=16, value_mlp=(16, 1),
                     vision=False, critic_takes_action=True)
    agent = HighLevelAgent(spec).to(device)
    learner = RecurrentSVG0Retrace(agent, 0.99, -1.0, 1.0, (0.1, 1.0), SVG0RetraceConfig(
        learning_rate=1e-3, entropy_cost=1e-4, target_update_period=2, value_samples=2, kl_cost=0.0))
    rng = np.random.default_rng(0)
    T, B, H = 5, 4, max(spec.lstm_size, spec.policy_lstm)
    batch = {"proprio": rng.normal(size=(T + 1, B, 5)), "task": rng.normal(size=(T + 1, B, 3)),
             "prev_reward": rng.normal(size=(T + 1, B)), "prev_action": rng.uniform(-1, 1, (T + 1, B, 2)),
             "first": np.zeros((T + 1, B)), "action": rng.uniform(-1, 1, (T, B, 2)), "log_mu": rng.normal(size=(T, B)),
             "reward": rng.normal(size=(T, B)), "discount": np.full((T, B), 0.99), "new_action": np.ones((T, B)),
             "state": np.zeros((B, 4, H))}
    batch = {k: torch.tensor(v, dtype=torch.float32, device=device) for k, v in batch.items()}
    out = []
    for _ in range(steps):
        torch.manual_seed(1)  # the same noise for the samples inside the update on both devices
        out.append(learner.update(copy.copy(batch)))
    return out


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_learner_steps_on_the_gpu_give_the_cpu_losses(monkeypatch):
    _host_noise(monkeypatch)
    cpu, gpu = _learner_losses("cpu"), _learner_losses("cuda")
    for a, b in zip(cpu, gpu):
        for key in a:
            assert b[key] == pytest.approx(a[key], rel=1e-3, abs=1e-4), key


def test_the_learner_steps_of_the_gpu_test_run_on_the_cpu(monkeypatch):
    """The CUDA test's own reference path, so that it cannot rot where no GPU is."""
    _host_noise(monkeypatch)
    losses = _learner_losses("cpu")
    assert len(losses) == 3 and all(np.isfinite(v) for step in losses for v in step.values())
    assert losses[0]["critic_loss"] != losses[2]["critic_loss"]  # the agent learned between them


def test_a_training_run_records_the_device_it_resolved(tmp_path):
    import subprocess
    import sys

    import yaml

    ball = ["stage=train", "body=rolling_ball", "controller=end_to_end", "num_envs=1", "total_steps=20",
            "hl.random_episodes=0", "hl.min_replay_unrolls=2", "algorithm.batch_size=2"]
    run = lambda *a: subprocess.run([sys.executable, "-m", "hvc.cli", *ball, *a], capture_output=True, text=True,  # noqa: E731
                                    cwd=tmp_path, timeout=600)
    assert run("hydra.run.dir=auto").returncode == 0
    resolved = yaml.safe_load((tmp_path / "auto" / "config_resolved.yaml").read_text())
    assert resolved["device"] == ("cuda" if torch.cuda.is_available() else "cpu")
    if not torch.cuda.is_available():
        result = run("device=cuda", "hydra.run.dir=gpu")
        assert result.returncode == 2 and not (tmp_path / "gpu").exists()
        [line] = [line for line in result.stderr.splitlines() if line.strip() and "absl" not in line]
        assert line.startswith("hvc-run: error: device=cuda: ") and "sees no CUDA device" in line
