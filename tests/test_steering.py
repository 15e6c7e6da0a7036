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
    from hvc.lowlevel.tracking import build_reference
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
