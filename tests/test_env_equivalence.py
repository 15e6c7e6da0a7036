"""The fast env against dm_control's composer on the same models and recorded actions."""
import numpy as np
import pytest

from conftest import ENV_TASKS, plain_cfg
from hvc.envs.builders import build_composer_env
from hvc.envs.fast_env import FastEnv, forward_without_actuation

STEPS = 80


def _paired(task_name, body_name="cmu_humanoid", seed=3, extra=()):
    task, body, render = plain_cfg(f"task={task_name}", f"body={body_name}", "controller=end_to_end", *extra)
    env = build_composer_env(task, body, seed=seed)
    first = env.reset()
    fast = FastEnv.from_composer(env, task, body, render, render=False)
    physics = env.physics
    fast.data.qpos[:] = physics.data.qpos
    fast.data.qvel[:] = physics.data.qvel
    fast.data.act[:] = physics.data.act
    fast.data.time = physics.data.time
    forward_without_actuation(fast.model, fast.data)
    logic = fast.layout.logic
    if hasattr(logic, "reward_of_type"):  # composer's colour-to-reward assignment of this episode
        logic.reward_of_type = np.asarray(env.task._target_type_rewards, float)
        logic.after_reset(fast.model, fast.data)
    return env, fast, first


def _dm_observables(env, fast):
    """What dm_control's own observables return for the composer physics' current state."""
    walker = env.task._walker
    env.physics.forward()
    return {name: np.asarray(getattr(walker.observables, name).observation_callable(env.physics)()).ravel()
            for name in fast.layout.proprio.names}


def _assert_proprio_equal(reference, proprio, slices, context):
    for name, part in slices.items():
        np.testing.assert_allclose(proprio[part], reference[name], rtol=1e-5, atol=1e-5,
                                   err_msg=f"{context}: observable {name}")


CASES = ([(t, "cmu_humanoid", "") for t in ENV_TASKS]
         + [("go_to_target", "rolling_ball", ""), ("gaps", "cmu_humanoid_2020", ""),
            ("go_to_target", "cmu_humanoid", "target_at_walker"), ("walls", "cmu_humanoid", "time_limit")])


@pytest.mark.parametrize("task_name,body_name,variant", CASES)
def test_trajectory_rewards_and_observations_match_composer(task_name, body_name, variant):
    """Random small actions until a fall; variants reach the target reward and the time limit."""
    extra = ("task.time_limit=0.3",) if variant == "time_limit" else ()
    env, fast, first = _paired(task_name, body_name, extra=extra)
    if variant == "target_at_walker":  # the sparse reward path: target 0.5 m from the walker
        target = env.physics.bind(env.task._walker.root_body).xpos[:2] + [0.5, 0.0]
        env.physics.bind(env.task._target).pos = [*target, 0.0]
        fast.model.site_pos[fast.layout.logic.site] = [*target, 0.0]
    slices = fast.layout.proprio.slices
    obs = fast.observation()
    _assert_proprio_equal({k: np.ravel(first.observation[f"walker/{k}"]) for k in slices}, obs["proprio"],
                          slices, "reset")
    rng = np.random.default_rng(7)
    spec = env.action_spec()
    # Small actions around a standing pose keep episodes going long enough to compare.
    actions = np.clip(rng.normal(0, 0.25, (STEPS, spec.shape[0])), spec.minimum, spec.maximum)
    ended = False
    for t, action in enumerate(actions):
        step = env.step(action)
        obs, reward, discount, done = fast.step(action)
        context = f"{task_name}/{body_name} step {t}"
        np.testing.assert_allclose(fast.data.qpos, env.physics.data.qpos, rtol=0, atol=1e-9, err_msg=context)
        np.testing.assert_allclose(fast.data.qvel, env.physics.data.qvel, rtol=0, atol=1e-7, err_msg=context)
        assert reward == pytest.approx(step.reward, abs=1e-9), context
        assert done == step.last(), context
        composer_failed = env.task.should_terminate_episode(env.physics) and env.physics.time() < env._time_limit
        if not (done and fast.layout.logic.failure):
            assert discount == step.discount, context
        else:  # failure: 0, where composer's maze task still reports 1 on that step (see MazeLogic)
            assert discount == 0.0 and composer_failed, context
        _assert_proprio_equal(_dm_observables(env, fast), obs["proprio"], slices, context)
        if "walker/target" in step.observation:  # go-to-target's egocentric target
            np.testing.assert_allclose(obs["task"], step.observation["walker/target"], atol=1e-5, err_msg=context)
        if done:
            ended = True
            break
    assert ended or t == STEPS - 1
    if variant == "target_at_walker":
        assert fast.episode_return > 0
    if variant == "time_limit":
        assert t == 9 and discount == 1.0 and not fast.layout.logic.failure


def test_maze_balls_pay_their_colour_once_and_end_the_episode():
    env, fast, _ = _paired("heterogeneous_forage")
    logic, model, data = fast.layout.logic, fast.model, fast.data
    n_balls = len(logic.target_geoms)
    assert n_balls == 6 and sorted(np.bincount(logic.target_type)) == [3, 3]
    total = 0.0
    for slot in range(n_balls):
        # Teleport the walker's root into each ball in turn (a contact with the ball geom).
        ball = data.xpos[model.geom_bodyid[logic.target_geoms[slot]]].copy()
        fast.data.qpos[0:3] = [ball[0], ball[1], 1.0]
        fast.data.qvel[:] = 0
        _, reward, discount, done = fast.step(np.zeros(fast.action_size))
        paid = logic.reward_of_type[logic.target_type[slot]]
        assert logic.activated[slot]
        total += reward
        assert reward == pytest.approx(0.01 + paid)
        assert model.mat_rgba[logic.target_materials[slot], 3] == 0.0  # a taken ball vanishes
        if done:
            break
    assert done and logic.activated.all() and discount == 1.0
    assert total == pytest.approx(0.01 * n_balls + 3 * 30 - 3 * 10)
