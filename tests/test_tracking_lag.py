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
