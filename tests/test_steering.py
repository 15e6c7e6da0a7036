"""Steered references: the heading turns at the commanded rate, consistently."""
import numpy as np
import pytest

from hvc.mocap.clips import root_heading
from hvc.mocap.source import SHARED_CLIPS
from hvc.mocap.steering import steer_cycle

pytestmark = pytest.mark.skipif(not SHARED_CLIPS.is_dir(), reason=f"offline CMU clips not found at {SHARED_CLIPS}")


@pytest.fixture(scope="module")
def cycle():
    from hvc.config import compose
    from hvc.mocap.reference import build_reference
    from hvc.mocap.clip_sets import select_entry
    from hvc.mocap.source import find_mocap_file

    entry = select_entry(compose([]).clips, "run").as_dict()
    entry["steps"] = None
    looped = build_reference(entry, str(find_mocap_file(None, "2019")), cycle_repeats=1)
    return looped


def test_each_cycle_turns_at_its_rate(cycle):
    rates = [0.0, 1.0, -1.5]
    ref, per_step = steer_cycle(cycle, rates)
    L, dt = cycle.num_steps, cycle.dt
    heading = root_heading(ref.quaternion)
    assert len(per_step) == 3 * L and np.all(per_step[L:2 * L] == 1.0)
    turned = [heading[(k + 1) * L - 1] - heading[k * L] for k in range(3)]
    # rate 0 runs straight (the cycle's own drift removed); others turn rate * cycle time
    np.testing.assert_allclose(turned, [r * (L - 1) * dt for r in rates], atol=0.12)


def test_path_velocity_and_gyro_are_consistent(cycle):
    ref, _ = steer_cycle(cycle, [1.2, 1.2])
    fd = np.diff(ref.position[:, :2], axis=0) / ref.dt
    np.testing.assert_allclose(fd[1:-1], ref.velocity[1:-2, :2], atol=0.6)  # same path, finite differences
    # the turning rate shows up as extra yaw rate of the root in the world frame
    base, _ = steer_cycle(cycle, [0.0, 0.0])
    w = lambda r: np.array([_world_z(q, a) for q, a in zip(r.quaternion, r.angular_velocity)])  # noqa: E731
    np.testing.assert_allclose(w(ref) - w(base), 1.2, atol=1e-6)


def _world_z(q, angular_local):
    w, x, y, z = q
    row = np.array([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)])
    return row @ angular_local


def test_steerable_tracking_task_draws_rates_and_shows_them():
    from conftest import plain_cfg
    from hvc.config import compose
    from hvc.envs.fast_env import FastEnv
    from hvc.mocap.clip_sets import select_entry
    from hvc.mocap.source import find_mocap_file

    cfg = compose(["stage=lowlevel", "task=tracking", "clips=steerable"])
    task, body, render = plain_cfg("stage=lowlevel", "task=tracking", "clips=steerable")
    task.update(clip=select_entry(cfg.clips, None).as_dict(), mocap_file=str(find_mocap_file(None, "2019")))
    env = FastEnv.build(task, body, render, seed=0)
    logic = env.layout.logic
    seen = set()
    for _ in range(5):
        obs = env.reset()
        assert obs["task"].shape == (2,) and obs["task"][1] == pytest.approx(logic.rates[logic.t], rel=1e-6)
        assert -1.5 <= obs["task"][1] <= 1.5
        seen.add(round(float(obs["task"][1]), 6))
        logic.set_reference_state(env.data, logic.t)  # the reference itself tracks perfectly
        import mujoco
        mujoco.mj_forward(env.model, env.data)
        reward, _ = logic.reward_fn(logic.body_features(env.data), logic.reference_features(logic.t))
        assert reward == pytest.approx(1.0, abs=1e-6)
    assert len(seen) == 5  # a new draw every episode
    env.close()


def test_turn_from_turns_and_moves_only_the_rest_of_the_reference(cycle):
    from hvc.mocap.steering import turn_from

    ref, _ = steer_cycle(cycle, [0.5, 0.5])
    before = {k: getattr(ref, k).copy() for k in ("quaternion", "velocity", "position", "angular_velocity")}
    t, L = 10, cycle.num_steps
    turn_from(ref, t, 0.7, np.array([5.0, -2.0]))
    for k, v in before.items():
        np.testing.assert_array_equal(getattr(ref, k)[:t], v[:t])  # the past is kept
    np.testing.assert_array_equal(ref.angular_velocity, before["angular_velocity"])  # root frame
    np.testing.assert_allclose(root_heading(ref.quaternion[t:]) - root_heading(before["quaternion"][t:]), 0.7,
                               atol=1e-9)
    np.testing.assert_allclose(ref.position[t, :2], [5.0, -2.0])
    turn = np.array([[np.cos(0.7), -np.sin(0.7)], [np.sin(0.7), np.cos(0.7)]])  # counter-clockwise
    np.testing.assert_allclose(ref.position[t:, :2] - ref.position[t, :2],
                               (before["position"][t:, :2] - before["position"][t, :2]) @ turn.T, atol=1e-9)
    np.testing.assert_allclose(ref.velocity[t:, :2], before["velocity"][t:, :2] @ turn.T, atol=1e-9)
    np.testing.assert_allclose(ref.velocity[t:, 2], before["velocity"][t:, 2])
    assert L > t


def _straight_under_a_left_turn(*overrides: str, **task_updates):
    """The steerable tracking env from the cycle's first step, its reference turning left at
    1.5 rad/s, and a function driving the body straight open loop for up to n steps (stopping at
    a failure when asked)."""
    from conftest import plain_cfg
    from hvc.config import compose
    from hvc.envs.fast_env import FastEnv
    from hvc.mocap.clip_sets import select_entry
    from hvc.mocap.source import find_mocap_file

    cfg = compose(["stage=lowlevel", "task=tracking", "clips=steerable"])
    task, body, render = plain_cfg("stage=lowlevel", "task=tracking", "clips=steerable", *overrides)
    task.update(clip=select_entry(cfg.clips, None).as_dict(), mocap_file=str(find_mocap_file(None, "2019")),
                random_start=False, **task_updates)
    env = FastEnv.build(task, body, render, seed=0)
    logic = env.layout.logic
    logic.held_rate = 1.5
    env.reset()
    L = logic.cycle.num_steps
    straight, _ = steer_cycle(logic.cycle, [0.0])

    def drive(n: int, stop_on_failure: bool = False) -> None:
        for t in range(n):
            env.step(np.clip(logic.pose_to_actuation(straight.joints[min(t + 1, L - 1)]), -1, 1))
            if stop_on_failure and logic.failure:
                return

    return env, logic, drive


def test_each_steered_cycle_starts_from_the_body_heading():
    """Whatever the body did in a cycle, the next cycle's reference starts where it faces."""
    from hvc.envs.tracking_reward import quat_log_norm
    from hvc.rotations import quat_conj, quat_mul

    for reanchor in (True, False):
        env, logic, drive = _straight_under_a_left_turn(f"task.reanchor={str(reanchor).lower()}")
        L = logic.cycle.num_steps
        drive(L)
        body_heading = float(root_heading(env.data.qpos[logic.root_qpos + 3:logic.root_qpos + 7][None])[0])
        ref_heading = float(root_heading(logic.reference.quaternion[L][None])[0])
        body_q = env.data.qpos[logic.root_qpos + 3:logic.root_qpos + 7]
        assert logic.t == L and logic.last_terms["ori"] == pytest.approx(  # this step's reward used it
            quat_log_norm(quat_mul(body_q, quat_conj(logic.reference.quaternion[L]))), abs=1e-9)
        gap = abs((body_heading - ref_heading + np.pi) % (2 * np.pi) - np.pi)
        assert (gap < 1e-6) if reanchor else (gap > 0.5), (reanchor, gap)
        env.close()


def test_lean_tilts_the_root_into_the_turn_by_the_centripetal_angle(cycle):
    from hvc.mocap.steering import lean_angle
    from hvc.rotations import quat_conj, quat_mul, quat_to_mat

    rates = [1.0, -1.0]
    upright, _ = steer_cycle(cycle, rates)
    leaned, _ = steer_cycle(cycle, rates, lean=True, lean_ramp=6)
    speed = float(np.linalg.norm(np.mean(cycle.velocity[:, :2], axis=0)))
    L = cycle.num_steps
    # rolling about the direction of travel barely moves the heading
    np.testing.assert_allclose(root_heading(leaned.quaternion), root_heading(upright.quaternion), atol=0.05)

    def roll(t):  # how far the world rotation from the upright to the leaned root tips the vertical to the left
        up = quat_to_mat(quat_mul(leaned.quaternion[t], quat_conj(upright.quaternion[t])))[:, 2]
        travel = upright.velocity[t, :2] / np.linalg.norm(upright.velocity[t, :2])
        left = np.array([-travel[1], travel[0], 0.0])
        return float(np.arcsin(up @ left))

    for k, rate in enumerate(rates):
        t = k * L + L // 2  # past the ramp
        assert np.sign(roll(t)) == np.sign(rate)  # a left turn (rate > 0) leans left, towards the centre
        assert roll(t) == pytest.approx(lean_angle(speed, rate), abs=0.05)
        assert leaned.position[t, 2] < upright.position[t, 2]
    assert roll(L) > 0 > roll(L + 6)  # the second cycle ramps from the first's lean


def test_heading_termination_fails_a_body_that_does_not_turn():
    from hvc.envs.tracking import heading_error

    failed = {}
    for threshold in (None, 0.3):
        env, logic, drive = _straight_under_a_left_turn(heading_termination=threshold)
        drive(logic.cycle.num_steps - 1, stop_on_failure=True)
        failed[threshold] = (logic.t, logic.contact_failure(env.data),
                             heading_error(logic.body_now.quaternion, logic.reference_now.quaternion))
        env.close()
    step, contact, _ = failed[None]
    # without it, open-loop play stays up for a while (it falls eventually, by contact)
    assert step >= 10
    # with it, the heading lag ends the episode first: 0.3 rad at 1.5 rad/s is about 0.2 s (7 steps),
    # give or take the gait's own sway, and no body part has touched the ground
    step_h, contact_h, error_h = failed[0.3]
    assert 3 <= step_h < step and not contact_h and error_h < -0.3, failed


@pytest.mark.parametrize("repeat", [0.0, 0.5, 1.0])
def test_turn_rate_repeat_holds_rates_across_cycles(repeat):
    from hvc.envs.steerable_tracking import SteerableTrackingLogic

    logic = SteerableTrackingLogic.__new__(SteerableTrackingLogic)  # only the rate draw, no env
    logic.turn_rates, logic.cycles, logic.repeat = (-1.5, 1.5), 8, repeat
    rng = np.random.default_rng(0)
    draws = np.array([logic._random_rates(rng) for _ in range(400)])
    assert np.all((draws >= -1.5) & (draws <= 1.5))
    kept = np.mean(draws[:, 1:] == draws[:, :-1])
    assert kept == pytest.approx(repeat, abs=0.03)  # uniform draws never repeat exactly by chance
    assert np.std(draws[:, 0]) == pytest.approx(3 / np.sqrt(12), abs=0.1)  # the first cycle is uniform


def test_steering_response_holds_each_rate_from_distinct_starts_in_the_first_cycle():
    """The mean action from one start would replay one episode per rate (falls only 0 or 1)."""
    from hvc.lowlevel.evaluation import steering_response

    env, logic, _ = _straight_under_a_left_turn()
    logic.held_rate = None
    settings = (logic.cycles, logic.random_start, logic.start_window)
    starts, lengths = [], []

    def act(obs, episode_logic):
        if episode_logic.t == episode_logic.start:  # an episode's first step
            starts.append(episode_logic.start)
            lengths.append(episode_logic.reference.num_steps)
        return np.zeros(env.action_size, np.float32)

    rows = steering_response(env, act, [0.5], episodes_per_rate=4, cycles=2)
    env.close()
    L = logic.cycle.num_steps
    assert len(starts) == 4 and len(set(starts)) > 1 and all(0 <= s < L for s in starts)
    assert set(lengths) == {3 * L}  # a cycle to start in, then the 2 held ones
    assert rows[0]["commanded_rate"] == 0.5 and 0.0 <= rows[0]["fall_rate"] <= 1.0
    assert (logic.cycles, logic.random_start, logic.start_window, logic.held_rate) == (*settings, None)
