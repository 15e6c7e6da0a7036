"""Every controller on every high-level task trains end to end for a tiny budget: actors,
controller, replay, the controller's learner, metrics and the checkpoint."""
import numpy as np
import pytest
import torch

from conftest import ENV_TASKS
from hvc.agents.mlp import GaussianPolicy, NumpyPolicy
from hvc.config import compose, resolve_parallelism
from hvc.lowlevel.library import Expert, ExpertLibrary
from hvc.mocap.reference import Reference

PROPRIO = 136  # the paper's proprioception of the CMU humanoid
CONTROLLERS = ("fragments", "query", "steerable", "switching", "end_to_end")


def _reference(clip_id: str, n: int, seed: int, cycle: int | None = None) -> Reference:
    rng = np.random.default_rng(seed)
    phase = np.tile(np.arange(cycle) / cycle, n // cycle) if cycle else np.linspace(0, 1, n)
    return Reference(clip_id, 0.03, cycle is not None, rng.normal(size=(n, 56)) * 0.1, rng.normal(size=(n, 56)),
                     rng.normal(size=(n, 3)), np.tile([1.0, 0, 0, 0], (n, 1)), rng.normal(size=(n, 3)),
                     rng.normal(size=(n, 3)), rng.normal(size=(n, 4, 3)), phase)


def _policy(obs_size: int, seed: int) -> NumpyPolicy:
    torch.manual_seed(seed)
    return NumpyPolicy.from_torch(GaussianPolicy(obs_size, 56, [16], 0.1))


@pytest.fixture(scope="module")
def libraries(tmp_path_factory):
    """Random-weight libraries of the right shapes for each controller."""
    out = tmp_path_factory.mktemp("libs")
    experts = [Expert({"id": f"CMU_00{i}_01", "behaviour": f"b{i}", "start": 0, "end": n},
                      _policy(PROPRIO + 1, i), _reference(f"CMU_00{i}_01", n, i)) for i, n in enumerate((9, 6))]
    clips = ExpertLibrary(experts, {}).save(out / "clips.npz")
    steer = Expert({"id": "CMU_009_06", "behaviour": "run_steered", "steer": True}, _policy(PROPRIO + 2, 5),
                   _reference("CMU_009_06", 12, 5, cycle=4))
    steerable = ExpertLibrary([steer], {}).save(out / "steerable.npz")
    behaviours = [_reference(f"CMU_01{k}_01", 8, 10 + k, cycle=4) for k in range(3)]
    switch = Expert({"id": "switching", "behaviour": "switching"}, _policy(PROPRIO + 1 + 3, 9), behaviours[0])
    switching = ExpertLibrary([switch], {"switching_entries": [{"id": b.clip_id} for b in behaviours]},
                              behaviours).save(out / "switching.npz")
    return {"fragments": clips, "query": clips, "steerable": steerable, "switching": switching, "end_to_end": None}


@pytest.mark.parametrize("task", ENV_TASKS)
@pytest.mark.parametrize("controller", CONTROLLERS)
def test_controller_trains_on_task(task, controller, libraries, tmp_path):
    from hvc.runtime.hl_train import run_hl_training

    library = libraries[controller]
    cfg = compose([f"task={task}", f"controller={controller}", "num_envs=1", "task.layout_pool=1",
                   "task.init_from_clips=false", "hl.random_episodes=0", "hl.min_replay_unrolls=1",
                   "algorithm.batch_size=2", "algorithm.updates_per_unroll=1", "log_every=1",
                   *([f"library={library}"] if library else [])])
    resolve_parallelism(cfg)
    cfg.total_steps = 2 * int(cfg.task.agent.unroll)
    summary = run_hl_training(cfg, tmp_path)
    assert summary["env_steps"] == cfg.total_steps and summary["learner_steps"] > 0
    state = torch.load(tmp_path / "checkpoint.pt", weights_only=True)
    assert state["counters"]["updates"] > 0
    assert all(torch.isfinite(v).all() for v in state["agent"].values() if v.is_floating_point())


@pytest.mark.parametrize("controller", CONTROLLERS)
def test_each_controllers_action_reaches_the_body(controller, libraries):
    """From the same start, two different high-level actions move the body differently and the
    same action moves it the same way: the choice, not noise, is what the body follows."""
    from hvc.runtime.env_config import vector_env

    library = libraries[controller]
    cfg = compose(["task=go_to_target", f"controller={controller}", "num_envs=1", "in_process_envs=1",
                   "task.init_from_clips=false", *([f"library={library}"] if library else [])])

    def body_after(action, steps=6):
        envs = vector_env(cfg, seed=3)
        try:
            envs.reset()
            for _ in range(steps):
                obs, *_ = envs.step([action])
            return obs["proprio"][0]
        finally:
            envs.close()

    space = vector_env(cfg, seed=3)
    space.close()
    space = space.action_space
    a, b = ((0, 1) if space.discrete else
            (np.full(space.size, space.low, np.float32), np.full(space.size, space.high, np.float32)))
    np.testing.assert_array_equal(body_after(a), body_after(a))
    assert np.abs(body_after(a) - body_after(b)).max() > 1e-3
