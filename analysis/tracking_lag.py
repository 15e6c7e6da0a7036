"""What a tracking reward means: the reward a kinematically perfect tracker scores when it runs
a few control steps behind its reference, per clip of a set.

    python analysis/tracking_lag.py [clip set, default go_to_target] [--lags 1 2 3]

The body is the reference itself k steps late (every feature the reward compares), scored by
the paper's reward against the reference now. Fast clips lose most per step of lag (their joint
velocities change fastest), so the same expert reward is a closer track on a run than on a
stand; `stage=evaluate` gives the experts' own rewards to read against these.
"""
from __future__ import annotations

import argparse
from typing import Sequence

import numpy as np
import pandas as pd

from hvc.envs.tracking import reference_features
from hvc.envs.tracking_reward import TERMS, TrackingReward
from hvc.mocap.reference import Reference, build_reference


def lagged_reward(ref: Reference, reward: TrackingReward, lag: int) -> dict[str, float]:
    """Mean reward, and each weighted energy term, of the reference `lag` steps late against itself."""
    if not 0 <= lag < ref.num_steps:
        raise ValueError(f"lag={lag} must be in [0, {ref.num_steps}) for a reference of {ref.num_steps} steps")
    rewards, terms = [], []
    for t in range(lag, ref.num_steps):
        r, e = reward(reference_features(ref, t - lag), reference_features(ref, t))
        rewards.append(r)
        terms.append([reward.weights[k] * e[k] for k in TERMS])
    return {"reward": float(np.mean(rewards)), **dict(zip(TERMS, np.mean(terms, axis=0).tolist()))}


def table(clip_set: str, lags: Sequence[int]) -> pd.DataFrame:
    """One row per clip and lag: the mean reward and weighted energy terms."""
    from hvc.config import compose
    from hvc.mocap.clip_sets import entries_of, resolve
    from hvc.runtime.mocap_stages import mocap_file_of

    cfg = compose(["stage=lowlevel", "task=tracking", f"clips={clip_set}"])
    mocap_file = str(mocap_file_of(cfg))
    reward = TrackingReward(cfg.reward)
    rows = []
    for entry in resolve(entries_of(cfg.clips), mocap_file):
        ref = build_reference(entry.as_dict(), mocap_file, int(cfg.task.cycle_repeats), int(cfg.task.cycle_blend))
        for lag in lags:
            rows.append({"behaviour": entry.behaviour, "clip": entry.id, "lag": lag,
                         **lagged_reward(ref, reward, lag)})
    return pd.DataFrame(rows)


def main(argv: list[str] | None = None) -> pd.DataFrame:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("clip_set", nargs="?", default="go_to_target", help="a conf/clips/ option")
    parser.add_argument("--lags", type=int, nargs="+", default=[1, 2, 3], help="control steps late")
    args = parser.parse_args(argv)
    from hvc.config import ConfigError

    try:
        return table(args.clip_set, args.lags)
    except (ConfigError, ValueError) as err:
        parser.error(str(err))


if __name__ == "__main__":
    print(main().round(3).to_string(index=False))
