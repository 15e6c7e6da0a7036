"""Envs in Ray actors (`actors=ray`) on a local Ray cluster: the same envs as worker processes."""
import subprocess
import sys

import numpy as np
import pandas as pd
import pytest

ray = pytest.importorskip("ray")

from hvc.config import compose  # noqa: E402


@pytest.fixture(scope="module")
def local_ray():
    from hvc.envs.ray_actors import connect

    connect(num_cpus=2)
    yield
    ray.shutdown()


@pytest.mark.parametrize("overrides", [["body=rolling_ball", "controller=end_to_end"],
                                       ["controller=fragments", "task.init_from_clips=false"]])
def test_ray_actors_step_the_same_envs_as_worker_processes(local_ray, overrides):
    from hvc.runtime.env_config import vector_env

    local = compose(["num_envs=2", "in_process_envs=1", *overrides])
    remote = compose(["num_envs=2", "actors=ray", *overrides])
    from hvc.skills import skills_for_job

    skills = skills_for_job(remote)
    if skills is not None:  # experts that acted here hold scratch buffers, which Ray ships read-only
        policy = skills.library.experts[0].policy
        policy(np.zeros(policy.mean_obs.shape, np.float32))
    a, b = vector_env(local, seed=5), vector_env(remote, seed=5)
    try:
        assert type(b).__name__ == "RayVectorEnv" and b.action_space == a.action_space
        obs_a, obs_b = a.reset(), b.reset()
        rng = np.random.default_rng(0)
        for _ in range(12):
            actions = a.random_actions(rng)
            for key in obs_a:
                np.testing.assert_array_equal(obs_a[key], obs_b[key])
            (obs_a, *rest_a), (obs_b, *rest_b) = a.step(actions), b.step(actions)
            for x, y in zip(rest_a[:3], rest_b[:3]):  # rewards, discounts, dones
                np.testing.assert_array_equal(x, y)
            np.testing.assert_array_equal([i.get("hl_action", -1) for i in rest_a[3]],
                                          [i.get("hl_action", -1) for i in rest_b[3]])  # nan == nan here
    finally:
        a.close()
        b.close()


@pytest.mark.parametrize("compiled", [True, False])
def test_an_actor_failing_mid_run_is_an_error_naming_the_task(local_ray, compiled):
    """Through the compiled graph and through plain actor calls alike: a WorkerError, no hang,
    and the envs closed."""
    from hvc.envs.ray_actors import RayVectorEnv
    from hvc.envs.vector_env import WorkerError
    from hvc.runtime.env_config import env_dicts

    task, body, render = env_dicts(compose(["body=rolling_ball", "controller=end_to_end"]))
    envs = RayVectorEnv(task, body, render, 2, seed=0, compiled=compiled)
    envs.reset()
    envs.step(envs.random_actions(np.random.default_rng(0)))
    with pytest.raises(WorkerError, match=r"(?s)task=go_to_target.*simulated failure"):
        envs._call([("step", np.zeros(envs.action_size)), ("crash", "simulated failure")])
    assert envs.closed


def test_a_training_run_with_ray_actors_writes_what_a_local_one_does(tmp_path):
    ball = ["stage=train", "body=rolling_ball", "controller=end_to_end", "num_envs=2", "total_steps=200",
            "hl.random_episodes=1", "hl.min_replay_unrolls=2", "algorithm.batch_size=2", "task.time_limit=1.0"]
    for name, extra in (("local", []), ("ray", ["actors=ray", "ray.num_cpus=2"])):
        result = subprocess.run([sys.executable, "-m", "hvc.cli", *ball, *extra, f"hydra.run.dir={name}"],
                                capture_output=True, text=True, cwd=tmp_path, timeout=600)
        assert result.returncode == 0, result.stderr[-3000:]
    local, remote = (pd.read_csv(tmp_path / n / "metrics.csv") for n in ("local", "ray"))
    assert set(remote.key) == set(local.key) and {"episode_return", "critic_loss"} <= set(remote.key)
    assert remote.env_steps.max() == local.env_steps.max() == 200
    assert remote.learner_steps.max() == local.learner_steps.max() > 0


def test_a_bad_backend_fails_in_one_line():
    from hvc.config import ConfigError, validate

    with pytest.raises(ConfigError, match="actors=slurm is not a backend; allowed: local, ray"):
        validate(compose(["actors=slurm"]))
