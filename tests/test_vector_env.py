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


@pytest.mark.parametrize("controller", [None, "fragments"])
def test_envs_stepped_in_the_main_process_match_worker_envs(controller):
    """Seeds follow the env index wherever it runs: the same actions give the same steps,
    controller infos included."""
    from omegaconf import OmegaConf

    from hvc.config import compose
    from hvc.controllers.factory import Drive
    from hvc.skills import resolve_skills

    task, body, render = plain_cfg("task=go_to_target")
    cfg = compose(["controller=fragments"])
    ctrl = OmegaConf.to_container(cfg.controller, resolve=True) if controller else None
    skills = resolve_skills(cfg) if controller else None
    runs = []
    for in_process in (0, 2):
        rng = np.random.default_rng(1)
        with VectorEnv(task, body, render, num_envs=3, seed=7, drive=Drive(ctrl, skills) if ctrl else None,
                       in_process=in_process) as env:
            assert len(env._procs) == 3 - in_process
            obs, steps = env.reset(), []
            for _ in range(150):  # random fragment choices: episodes end in falls within this (the median is 60-85)
                obs, rewards, discounts, dones, infos = env.step(env.random_actions(rng))
                steps.append((obs["proprio"].copy(), rewards, dones, infos))
        runs.append(steps)
    for (o0, r0, d0, i0), (o1, r1, d1, i1) in zip(*runs):
        np.testing.assert_array_equal(o0, o1)
        np.testing.assert_array_equal(r0, r1)
        np.testing.assert_array_equal(d0, d1)
        assert i0 == i1
    assert any(any(d) for _, _, d, _ in runs[0])  # episodes ended and reset on both sides
    if controller:
        assert all("new_action" in info and "hl_action" in info for step in runs[1] for info in step[3])


def test_an_in_process_env_failure_names_the_env_and_closes_the_workers(monkeypatch):
    task, body, render = plain_cfg("task=go_to_target")
    env = VectorEnv(task, body, render, num_envs=2, seed=0, in_process=1)
    env.reset()

    def broken(action):
        raise FloatingPointError("simulated physics blow-up")

    monkeypatch.setattr(env._hosts[0], "step", broken)
    with pytest.raises(WorkerError, match=r"env 1 \(task=go_to_target, in the main process\).*blow-up"):
        env.step(np.zeros((2, env.action_size)))
    assert env.closed and not env._procs[0].is_alive()


def test_worker_failure_names_the_worker_and_task():
    task, body, render = plain_cfg("task=gaps", "task.layout_pool=1")
    env = VectorEnv(task, body, render, num_envs=2, seed=0)
    env.reset()
    env._send(1, "crash", "simulated failure")
    with pytest.raises(WorkerError, match=r"(?s)worker 1 \(task=gaps\).*simulated failure"):
        env._receive(1)
    assert env.closed


def test_worker_death_is_an_error_not_a_hang():
    task, body, render = plain_cfg("task=go_to_target")
    env = VectorEnv(task, body, render, num_envs=1, seed=0)
    env._procs[0].kill()
    with pytest.raises(WorkerError, match=r"worker 0 \(task=go_to_target\)"):
        env.step(np.zeros((1, env.action_size)))
