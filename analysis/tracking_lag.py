"""What a tracking reward means: the reward a kinematically perfect tracker scores when it runs
a few control steps behind its reference, per clip of a set; with --ranges, what no tracker can
score because the reference bends joints past the walker's limits.

    python analysis/tracking_lag.py [clip set, default go_to_target] [--lags 1 2 3] [--ranges]

The body is the reference itself k steps late (every feature the reward compares), scored by
the paper's reward against the reference now. Fast clips lose most per step of lag (their joint
velocities change fastest), so the same expert reward is a closer track on a run than on a
stand; `stage=evaluate` gives the experts' own rewards to read against these.

The clips are retargeted angle by angle from the captured skeleton, not fitted to the walker, so
some reference angles (thumbs, wrists, toes most) lie outside the walker's hinge ranges: a body
within its limits keeps that much joint error at best, and starts from a pose its limits push
back at once. --ranges gives, per clip, the share of (step, joint) values out of range, the
largest excess, and the reward ceiling this alone sets (the qpos term only; the end effectors
would move too, so the true ceiling is lower).
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


def range_ceiling(ref: Reference, ranges: np.ndarray, joint_names: Sequence[str],
                  reward: TrackingReward) -> dict[str, float | str]:
    """How far the reference's joints go past `ranges` ((56, 2), the reference's joint order) and
    the mean reward of the nearest pose within them, from the qpos term alone."""
    excess = np.maximum(ref.joints - ranges[:, 1], 0.0) + np.maximum(ranges[:, 0] - ref.joints, 0.0)
    floor = reward.weights["qpos"] * excess.mean(axis=1)  # weighted qpos energy per step, at best
    worst = int(np.argmax(excess.max(axis=0)))
    return {"out_of_range": float((excess > 0).mean()), "largest_excess": float(excess.max()),
            "worst_joint": joint_names[worst], "qpos_floor": float(floor.mean()),
            "reward_ceiling": float(np.mean(np.exp(-reward.beta * floor / reward.w_total)))}


def references(clip_set: str):
    """(the paper's reward, [(entry, reference)], the walker's model version) for a clip set, as the
    tracking task builds them."""
    from hvc.config import compose
    from hvc.mocap.clip_sets import entries_of, resolve
    from hvc.runtime.mocap_stages import mocap_file_of

    cfg = compose(["stage=lowlevel", "task=tracking", f"clips={clip_set}"])
    mocap_file = str(mocap_file_of(cfg))
    refs = [(entry, build_reference(entry.as_dict(), mocap_file, int(cfg.task.cycle_repeats),
                                    int(cfg.task.cycle_blend)))
            for entry in resolve(entries_of(cfg.clips), mocap_file)]
    return TrackingReward(cfg.reward), refs, str(cfg.body.model_version)


def ranges_table(clip_set: str) -> pd.DataFrame:
    """One row per clip: its joints past the walker's hinge ranges, and the reward ceiling that sets."""
    from hvc.mocap.convert import WalkerPoser

    reward, refs, walker_version = references(clip_set)
    poser = WalkerPoser(walker_version)
    names = [name.removeprefix("walker/") for name in poser.joint_names]
    return pd.DataFrame([{"behaviour": entry.behaviour, "clip": entry.id,
                          **range_ceiling(ref, poser.joint_ranges, names, reward)} for entry, ref in refs])


def table(clip_set: str, lags: Sequence[int]) -> pd.DataFrame:
    """One row per clip and lag: the mean reward and weighted energy terms."""
    reward, refs, _ = references(clip_set)
    rows = []
    for entry, ref in refs:
        for lag in lags:
            rows.append({"behaviour": entry.behaviour, "clip": entry.id, "lag": lag,
                         **lagged_reward(ref, reward, lag)})
    return pd.DataFrame(rows)


def main(argv: list[str] | None = None) -> pd.DataFrame:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("clip_set", nargs="?", default="go_to_target", help="a conf/clips/ option")
    parser.add_argument("--lags", type=int, nargs="+", default=[1, 2, 3], help="control steps late")
    parser.add_argument("--ranges", action="store_true", help="the joints past the walker's limits instead")
    args = parser.parse_args(argv)
    from hvc.config import ConfigError

    try:
        return ranges_table(args.clip_set) if args.ranges else table(args.clip_set, args.lags)
    except (ConfigError, ValueError) as err:
        parser.error(str(err))


if __name__ == "__main__":
    print(main().round(3).to_string(index=False))
