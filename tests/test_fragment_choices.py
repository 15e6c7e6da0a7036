"""Fig. A.4C's question, "are extraneous behaviours ignored?", is read off recorded episodes:
each behaviour's share of the high level's choices against its share of the library."""
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "analysis"))
from fragment_transitions import behaviour_shares  # noqa: E402


def _record(tmp_path: Path, episodes: list[tuple[list[int], list[bool], list[float]]]) -> Path:
    # 4 fragments: 3 of "stand", 1 of "hops" (so uniform choices give 0.75 / 0.25)
    pd.DataFrame({"index": range(4), "clip": [0, 0, 0, 1], "clip_id": ["a"] * 3 + ["b"],
                  "behaviour": ["stand"] * 3 + ["hops"], "start": [0, 3, 6, 0], "length": 3}
                 ).to_csv(tmp_path / "fragments.csv", index=False)
    (tmp_path / "episodes").mkdir()
    for i, (action, new, reward) in enumerate(episodes):
        np.savez(tmp_path / "episodes" / f"episode_{i:04d}.npz", hl_action=np.array(action, float),
                 new_action=np.array(new), reward=np.array(reward))
    return tmp_path


def test_shares_count_only_new_choices_and_can_skip_episodes_rewarded_from_the_start(tmp_path):
    run = _record(tmp_path, [
        ([3, 3, 3, 0], [True, False, False, True], [0.0, 0.0, 1.0, 0.0]),   # walk: hops, then stand
        ([1, 1, 2, 2], [True, False, True, False], [1.0, 1.0, 1.0, 1.0]),   # spawned at the target: stand, stand
    ])
    shares = behaviour_shares(run)
    assert shares.loc["hops", "chosen"] == pytest.approx(1 / 4)      # 1 of 4 choices; held steps not counted
    assert shares.loc["stand", "fragments"] == pytest.approx(3 / 4)
    walks = behaviour_shares(run, skip_rewarded_at_start=True)
    assert walks.loc["hops", "chosen"] == pytest.approx(1 / 2) and walks.chosen.sum() == pytest.approx(1)


def test_a_behaviour_never_chosen_keeps_its_row(tmp_path):
    run = _record(tmp_path, [([0, 1], [True, True], [0.0, 0.0])])
    shares = behaviour_shares(run)
    assert list(shares.index) == ["stand", "hops"] and shares.loc["hops", "chosen"] == 0
