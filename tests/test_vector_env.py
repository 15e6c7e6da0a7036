import numpy as np
import pytest

from conftest import plain_cfg
from hvc.envs.vector_env import VectorEnv, WorkerError


def test_vector_env_steps_autoresets_and_closes():
    task, body, render = plain_cfg("task=go_to_target")
    rng = np.random.default_rng(0)
    with VectorEnv(task, body, render, num_envs=2, seed=5) as env:
        obs = env.reset()
        assert obs["proprio"].shape == (2, env.observation_sizes["proprio"])
        finished = []
        for _ in range(60):  # random actions fall within ~20 steps, so episodes end and restart
            obs, rewards, discounts, dones, infos = env.step(env.random_actions(rng))
            finished += [info for info in infos if info]
            assert rewards.shape == (2,) and dones.dtype == bool
        procs = list(env._procs)
    assert finished and all(info["episode_length"] > 0 for info in finished)
    assert not any(p.is_alive() for p in procs)


def test_worker_failure_names_the_worker_and_task():
    task, body, render = plain_cfg("task=gaps", "task.layout_pool=1")
    env = VectorEnv(task, body, render, num_envs=2, seed=0)
    env.reset()
    env._conns[1].send(("crash", "simulated failure"))
    with pytest.raises(WorkerError, match=r"(?s)worker 1 \(task=gaps\).*simulated failure"):
        env._receive(1)
    assert env.closed


def test_worker_death_is_an_error_not_a_hang():
    task, body, render = plain_cfg("task=go_to_target")
    env = VectorEnv(task, body, render, num_envs=1, seed=0)
    env._procs[0].kill()
    with pytest.raises(WorkerError, match=r"worker 0 \(task=go_to_target\)"):
        env.step(np.zeros((1, env.action_size)))
