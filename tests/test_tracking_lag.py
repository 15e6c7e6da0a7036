"""The lagged-tracker yardstick: the reference k steps late, scored by the paper's reward."""
import math
import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "analysis"))
from tracking_lag import main  # noqa: E402

pytestmark = pytest.mark.skipif(not __import__("hvc.mocap.source", fromlist=["x"]).SHARED_CLIPS.is_dir(),
                                reason="offline CMU clips not found")


@pytest.fixture(scope="module")
def go_to_target():
    return main(["go_to_target", "--lags", "0", "1", "2"])


def test_no_lag_is_perfect_tracking(go_to_target):
    exact = go_to_target[go_to_target.lag == 0]
    assert len(exact) == 4
    assert exact.reward.tolist() == pytest.approx([1.0] * 4)
    assert exact[["qpos", "qvel", "ori", "ee", "vel", "gyro"]].abs().max().max() == pytest.approx(0.0, abs=1e-9)


def test_each_step_of_lag_costs_reward_and_fast_clips_pay_most(go_to_target):
    by = go_to_target.pivot_table(index="behaviour", columns="lag", values="reward")
    assert set(by.index) == {"stand", "run", "left_turn", "right_turn"}
    assert (by[0] > by[1]).all() and (by[1] > by[2]).all()
    # the stand barely moves: one step late is nearly perfect; the run's joint velocities change fast
    assert by.loc["stand", 1] > 0.9 > by.loc["run", 1]
    # the energy terms carry their weights: the reward is exp(-beta * sum / w_total) per step, so
    # exp(-mean sum / 3) bounds the mean reward from below (Jensen)
    row = go_to_target[(go_to_target.behaviour == "run") & (go_to_target.lag == 1)].iloc[0]
    total = row[["qpos", "qvel", "ori", "ee", "vel", "gyro"]].sum()
    assert row.reward >= math.exp(-10 * total / 30) - 1e-9


def test_a_lag_past_the_clip_or_an_unknown_set_is_one_line(capsys):
    with pytest.raises(SystemExit):
        main(["go_to_target", "--lags", "500"])
    assert "lag=500 must be in [0, " in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main(["gapz"])
    assert "unknown clips 'gapz'; allowed: " in capsys.readouterr().err


def test_joints_past_the_walker_ranges_cap_the_reward():
    import numpy as np
    from tracking_lag import range_ceiling, references

    reward, refs, _ = references("go_to_target")
    ref = refs[0][1]
    names = [f"j{i}" for i in range(ref.joints.shape[1])]
    free = np.tile([-np.inf, np.inf], (ref.joints.shape[1], 1))
    assert range_ceiling(ref, free, names, reward) == {"out_of_range": 0.0, "largest_excess": 0.0,
                                                       "worst_joint": "j0", "qpos_floor": 0.0, "reward_ceiling": 1.0}
    # joint 7 held 0.2 rad below everything the reference asks of it: every step is 0.2 rad past
    tight = free.copy()
    tight[7, 1] = ref.joints[:, 7].min() - 0.2
    capped = range_ceiling(ref, tight, names, reward)
    assert capped["worst_joint"] == "j7" and capped["out_of_range"] == pytest.approx(1 / ref.joints.shape[1])
    floor = reward.weights["qpos"] * (ref.joints[:, 7] - tight[7, 1]).mean() / ref.joints.shape[1]
    assert capped["qpos_floor"] == pytest.approx(floor) and floor > 5 * 0.2 / 56 - 1e-9
    assert capped["largest_excess"] == pytest.approx((ref.joints[:, 7] - tight[7, 1]).max())
    assert capped["reward_ceiling"] < 1.0


def test_the_ranges_table_reads_the_walker_limits():
    table = main(["go_to_target", "--ranges"])
    assert list(table.behaviour) == ["stand", "run", "left_turn", "right_turn"]
    assert ((table.reward_ceiling > 0) & (table.reward_ceiling <= 1)).all()
    # the retargeted clips do bend some joints past the walker's hinges (thumbs, wrists, toes)
    assert (table.out_of_range > 0).all() and (table.largest_excess < 3.2).all()
