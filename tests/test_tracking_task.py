"""task=tracking on real CMU clips: reward wiring, termination, resets, looped cycles."""
import mujoco
import numpy as np
import pytest

from conftest import plain_cfg
from hvc.mocap.source import SHARED_CLIPS

pytestmark = pytest.mark.skipif(not SHARED_CLIPS.is_dir(), reason=f"offline CMU clips not found at {SHARED_CLIPS}")


def _env(clip="run", *extra):
    from hvc.envs.fast_env import FastEnv
    from hvc.mocap.clip_sets import select_entry
    from hvc.mocap.source import find_mocap_file
    from hvc.config import compose

    cfg = compose(["stage=lowlevel", "task=tracking", *extra])
    task, body, render = plain_cfg("stage=lowlevel", "task=tracking", *extra)
    task.update(clip=select_entry(cfg.clips, clip).as_dict(), mocap_file=str(find_mocap_file(None, "2019")))
    return FastEnv.build(task, body, render, seed=0)


@pytest.fixture(scope="module")
def run_env():
    env = _env("run")
    yield env
    env.close()


def test_reference_state_tracks_itself_perfectly(run_env):
    """Body features read from the simulator equal the stored reference features."""
    logic = run_env.layout.logic
    for t in (0, 17, 60, logic.reference.num_steps - 1):
        logic.set_reference_state(run_env.data, t)
        mujoco.mj_forward(run_env.model, run_env.data)
        reward, terms = logic.reward_fn(logic.body_features(run_env.data), logic.reference_features(t))
        assert reward == pytest.approx(1.0, abs=1e-6), terms
        # and a pose from another time scores clearly lower
        wrong, _ = logic.reward_fn(logic.body_features(run_env.data), logic.reference_features((t + 7) % 100))
        assert wrong < 0.7


def test_open_loop_tracks_early_then_falls(run_env):
    from hvc.lowlevel.evaluation import open_loop_action, run_episode

    logic = run_env.layout.logic
    first_rewards, random_rewards, falls, completions = [], [], 0, []
    rng = np.random.default_rng(0)
    for _ in range(20):
        run_env.reset()
        target = logic.reference.joints[logic.t + 1]
        _, reward, _, _ = run_env.step(np.clip(logic.pose_to_actuation(target), -1, 1))
        first_rewards.append(reward)
        run_env.reset()
        random_rewards.append(run_env.step(rng.uniform(-1, 1, run_env.action_size))[1])
        stats = run_episode(run_env, open_loop_action)
        falls += stats.fell
        completions.append(stats.completion)
    # right after a reference start, playing the next pose tracks well (about 0.55: joint
    # velocities lag under position control) and far better than random actions
    assert np.mean(first_rewards) > 0.45 and np.mean(first_rewards) > 2 * np.mean(random_rewards)
    assert falls > 0                             # ... and open loop falls: the termination fires
    assert 0 < np.mean(completions) < 1


def test_episode_energies_are_the_weighted_terms_behind_the_reward(run_env):
    from hvc.lowlevel.evaluation import open_loop_action, run_episode

    logic = run_env.layout.logic
    seen = []

    def act(obs, logic):  # sees the terms of the step before (the first call: the last episode's)
        seen.append(dict(logic.last_terms))
        return open_loop_action(obs, logic)

    stats = run_episode(run_env, act)
    per_step = seen[1:] + [dict(logic.last_terms)]
    assert len(per_step) == stats.steps
    weights = logic.reward_fn.weights
    for term in weights:
        assert stats.energy[term] == pytest.approx(np.mean([weights[term] * s[term] for s in per_step]))
    # r = exp(-beta E / w_total) is convex in E: the mean reward bounds the reward of the mean energy
    total = sum(stats.energy.values())
    assert 0 < np.exp(-logic.reward_fn.beta * total / logic.reward_fn.w_total) <= stats.mean_reward + 1e-9


def test_critic_features_are_the_rotation_and_velocity_to_the_reference(run_env):
    from hvc.rotations import quat_mul, quat_to_mat, yaw_quat

    logic = run_env.layout.logic
    t = 30
    logic.t = t
    logic.set_reference_state(run_env.data, t)
    mujoco.mj_forward(run_env.model, run_env.data)
    features = logic.critic_features(run_env.data)
    assert features.shape == (logic.critic_feature_size,)
    np.testing.assert_allclose(features[:4], [1, 0, 0, 0], atol=1e-6)  # on the reference: no rotation
    body = run_env.data.qpos[logic.root_qpos + 3:logic.root_qpos + 7].copy()
    np.testing.assert_allclose(features[4:], quat_to_mat(body).T @ logic.reference.velocity[t], atol=1e-5)
    # the body turned 0.4 rad to the left of the reference: the reference is 0.4 rad to its right
    run_env.data.qpos[logic.root_qpos + 3:logic.root_qpos + 7] = quat_mul(yaw_quat(0.4), body)
    features = logic.critic_features(run_env.data)
    assert 2 * np.arccos(features[0]) == pytest.approx(0.4, abs=1e-5)
    world_axis = quat_to_mat(run_env.data.qpos[logic.root_qpos + 3:logic.root_qpos + 7]) @ features[1:4]
    assert world_axis[2] / np.linalg.norm(world_axis) == pytest.approx(-1.0, abs=1e-5)


def test_time_input_and_random_starts(run_env):
    logic = run_env.layout.logic
    starts = set()
    for _ in range(10):
        obs = run_env.reset()
        starts.add(logic.t)
        assert obs["task"][0] == pytest.approx(logic.reference.phase[logic.t])
        assert obs["proprio"].shape == (run_env.layout.proprio.size,)
    assert len(starts) > 5
    assert logic.reference.cyclic and logic.reference.phase.max() < 1.0  # sawtooth


def test_torso_on_the_ground_fails_but_hands_may_touch():
    env = _env("stand")
    logic, model, data = env.layout.logic, env.model, env.data
    env.reset()
    root = logic.root_qpos
    data.qpos[root + 2] = 0.12                       # lay the pelvis on the floor
    _, _, discount, done = env.step(np.clip(logic.pose_to_actuation(logic.reference.joints[logic.t]), -1, 1))
    assert done and logic.failure and discount == 0.0
    # hands and feet may touch the ground; every other body part may not
    body_of = {mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_BODY, model.geom_bodyid[g]).split("/")[-1]: g
               for g in range(model.ngeom) if model.geom_bodyid[g] > 0}
    for name in ("lhand", "rfingers", "lthumb", "lfoot", "rtoes"):
        assert not logic.contact_failure.nonfoot[body_of[name]], name
    for name in ("root", "head", "lhumerus", "rtibia", "lwrist"):
        assert logic.contact_failure.nonfoot[body_of[name]], name
    env.close()


def test_episode_ends_at_the_clip_end_without_failure():
    env = _env("left_turn", "task.random_start=false")
    logic = env.layout.logic
    env.reset()
    steps = 0
    done = False
    while not done:
        # hold the body on the reference (kinematic replay) so only the clip's end can stop it
        logic.set_reference_state(env.data, logic.t)
        mujoco.mj_forward(env.model, env.data)
        _, _, discount, done = env.step(np.clip(logic.pose_to_actuation(logic.reference.joints[logic.t + 1]), -1, 1))
        steps += 1
    assert steps == logic.reference.num_steps - 1 and discount == 1.0 and logic.completion == 1.0
    env.close()


def test_looped_cycle_is_continuous_at_the_seam(run_env):
    ref = run_env.layout.logic.reference
    length = int(np.argmax(ref.phase[1:] < ref.phase[:-1])) + 1  # first wrap of the sawtooth
    steps = np.abs(np.diff(ref.joints, axis=0)).mean(axis=1)
    assert steps[length - 1] < 3 * np.median(steps)            # no jump at the seam
    jumps = np.linalg.norm(np.diff(ref.position, axis=0), axis=1)
    assert jumps[length - 1] < 3 * np.median(jumps)            # the next cycle starts where the last ended


def test_pose_error_ignores_position_and_heading_but_not_tilt(run_env):
    """The deviation termination looks only at what the egocentric policy can observe."""
    from hvc.envs.tracking import pose_error
    from hvc.rotations import quat_mul, yaw_quat

    logic, data, model = run_env.layout.logic, run_env.data, run_env.model
    t, root = 30, logic.root_qpos
    ref = logic.reference_features(t)

    def error_after(position_shift=(0.0, 0.0, 0.0), turn=None):
        logic.set_reference_state(data, t)
        data.qpos[root:root + 3] += position_shift
        if turn is not None:
            data.qpos[root + 3:root + 7] = quat_mul(turn, data.qpos[root + 3:root + 7])
        mujoco.mj_forward(model, data)
        return pose_error(logic.body_features(data), ref)

    assert error_after() == pytest.approx(0.0, abs=1e-9)
    assert error_after((1.5, -2.0, 0.0), yaw_quat(0.9)) == pytest.approx(0.0, abs=1e-9)
    tilt = np.array([np.cos(0.15), np.sin(0.15), 0.0, 0.0])   # 0.3 rad about world x
    assert error_after(turn=tilt) > 0.03
    logic.set_reference_state(data, t)
    data.qpos[logic.joint_qpos] += 0.2
    mujoco.mj_forward(model, data)
    assert pose_error(logic.body_features(data), ref) > 0.5 * 0.2     # the joint half alone


def test_straying_from_the_reference_fails_only_with_a_termination_error():
    def steps_until_done(*extra):
        env = _env("run", "task.random_start=false", *extra)
        env.reset()
        steps, done = 0, False
        while not done:
            _, _, discount, done = env.step(np.zeros(env.action_size))  # hold the mid-range pose
            steps += 1
        failed = env.layout.logic.failure
        env.close()
        return steps, failed, discount

    free_steps, _, _ = steps_until_done()
    strict_steps, failed, discount = steps_until_done("task.termination_error=0.1")
    assert failed and discount == 0.0 and strict_steps < free_steps
    with pytest.raises(ValueError, match="termination_error"):
        _env("run", "task.termination_error=0")
