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


def test_training_runs_with_ray_actors_write_what_a_local_one_does(tmp_path):
    """Acting in the actors and acting centrally: the same metrics, env steps and learner steps
    (learning from the first unroll on: actors deliver one unroll at a time, the local backend
    one per env, so a larger minimum would be reached at different counts)."""
    ball = ["stage=train", "body=rolling_ball", "controller=end_to_end", "num_envs=2", "total_steps=200",
            "hl.random_episodes=1", "hl.min_replay_unrolls=1", "algorithm.batch_size=2", "task.time_limit=1.0"]
    runs = {"local": [], "actors": ["actors=ray", "ray.num_cpus=2", "ray.acting=actors"],
            "central": ["actors=ray", "ray.num_cpus=2", "ray.acting=central"]}
    for name, extra in runs.items():
        result = subprocess.run([sys.executable, "-m", "hvc.cli", *ball, *extra, f"hydra.run.dir={name}"],
                                capture_output=True, text=True, cwd=tmp_path, timeout=600)
        assert result.returncode == 0, result.stderr[-3000:]
    local = pd.read_csv(tmp_path / "local" / "metrics.csv")
    for name in ("actors", "central"):
        remote = pd.read_csv(tmp_path / name / "metrics.csv")
        assert set(remote.key) == set(local.key) and {"episode_return", "critic_loss"} <= set(remote.key)
        assert remote.env_steps.max() == local.env_steps.max() == 200
        assert remote.learner_steps.max() == local.learner_steps.max() > 0
        returns = remote[remote.key == "episode_return"].value
        assert len(returns) and np.isfinite(returns).all()


def _ball_acting(extra=()):
    from hvc.runtime.hl_train import build_agent
    from hvc.runtime.ray_acting import RayActing

    cfg = compose(["body=rolling_ball", "controller=end_to_end", "num_envs=2", "actors=ray", "ray.num_cpus=2",
                   "task.time_limit=1.0", *extra])
    acting = RayActing(cfg, 0, None)
    spec, agent, learner = build_agent(cfg, acting)
    return cfg, acting.attach(agent), spec, agent, learner


def test_actors_act_with_the_weights_broadcast_every_few_unrolls(local_ray):
    """Weights reach the actors only at a broadcast, every ray.broadcast_every unrolls; an
    actor already resubmitted finishes its unroll with the weights it was sent. The unrolls
    fit the learner's replay and feed its input normaliser.

    New weights are set after the 2nd unroll and broadcast after the 4th: the first 4 unrolls
    and the two already under way then (one per actor, whichever delivers first) act with the
    old ones, so exactly 6 of the 12 do, the first 5 among them; all later ones the new."""
    import torch

    from hvc.algorithms.replay import UnrollReplay
    from hvc.runtime.hl_train import unroll_fields

    cfg, acting, spec, agent, learner = _ball_acting(["ray.broadcast_every=4"])
    n = int(cfg.task.agent.unroll)

    def set_mean(sign):  # the Gaussian's mean at one bound, its sigma at the floor
        with torch.no_grad():
            agent.policy_out.weight.zero_()
            agent.policy_out.bias[:spec.action_size] = 10.0 * sign
            agent.policy_out.bias[spec.action_size:] = -20.0

    replay = UnrollReplay(16, unroll_fields(spec, n, query=learner.keeps_query))
    try:
        set_mean(+1)
        acting.publish(0)
        signs, count = [], float(agent.normalizer.count)
        for k in range(12):
            collected = acting.collect()
            assert collected.env_steps == n and len(collected.unrolls) == 1
            replay.add(**collected.unrolls[0])
            signs.append(int(np.sign(collected.unrolls[0]["action"].mean())))
            if k == 1:
                set_mean(-1)  # not broadcast until 4 unrolls have come in
            acting.publish(0)
        assert signs[:5] == [1] * 5 and signs.count(1) == 6 and signs[-1] == -1, signs
        assert float(agent.normalizer.count) == count + 12 * n
        assert replay.size == 12
    finally:
        acting.close()


def test_an_acting_actor_lost_mid_run_is_an_error_naming_the_task(local_ray):
    from hvc.envs.vector_env import WorkerError

    _, acting, *_ = _ball_acting()
    acting.publish(0)
    acting.collect()
    ray.kill(acting._actors[0])
    with pytest.raises(WorkerError, match="task=go_to_target"):
        for _ in range(10):
            acting.collect()
    assert acting.closed


def test_a_bad_backend_fails_in_one_line():
    from hvc.config import ConfigError, validate

    with pytest.raises(ConfigError, match="actors=slurm is not a backend; allowed: local, ray"):
        validate(compose(["actors=slurm"]))
    with pytest.raises(ConfigError, match="ray.acting=remote is not a way to act; allowed: actors, central"):
        validate(compose(["ray.acting=remote"]))
    with pytest.raises(ConfigError, match="ray.broadcast_every=0 must be a positive integer"):
        validate(compose(["ray.broadcast_every=0"]))
