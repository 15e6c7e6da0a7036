"""Final performance: each run's mean return per episode over the last part of its training,
then, per arm, the interquartile mean over runs with a stratified bootstrap confidence
interval (rliable, Agarwal et al. 2021: the estimate that stays sound with few seeds)."""
from __future__ import annotations

import warnings
from typing import Sequence

import numpy as np
import pandas as pd

from hvc.analysis.curves import check_groups
from hvc.analysis.returns import mean_episode_length, mean_return


def final_scores(frame: pd.DataFrame, last: float = 0.1) -> pd.DataFrame:
    """Per run: its options, status, env steps reached, and `score`: the mean return per
    episode over episodes ending in the last `last` fraction of its env steps; `random`: the
    random policy's return it logged (NaN if none)."""
    rows = []
    for run, m in frame.groupby("run", sort=True):
        head = m.iloc[0]
        steps = m.env_steps.max()
        score = mean_return(m, lo=(1 - last) * steps) if steps > 0 else np.nan
        random = m[m.key == "random_return"].value
        rows.append({**head.drop(["env_steps", "learner_steps", "wall_time", "key", "value"]).to_dict(),
                     "env_steps": steps, "score": score, "random": random.iloc[0] if len(random) else np.nan})
    scores = pd.DataFrame(rows)
    scores.attrs = dict(frame.attrs)
    return scores


def window_scores(frame: pd.DataFrame, windows: int, by: Sequence[str] = (), of: str = "return") -> pd.DataFrame:
    """Per run (its `by` options, seed and status): the mean return per episode (`of="length"`:
    the mean episode length, hvc.analysis.returns.mean_episode_length) in each of
    `windows` equal spans of env steps, the spans splitting the longest run's env steps, so
    that every run is read on the same grid, and over its whole run (`whole`): when an arm took
    off, where final scores only say where it ended. A span a run stopped short of is NaN; 1%
    of the grid short counts as reached (runs of one budget stop a few env steps apart)."""
    if windows < 1:
        raise ValueError(f"windows must be at least 1, got {windows}")
    measures = {"return": mean_return, "length": mean_episode_length}
    if of not in measures:
        raise ValueError(f"window_scores of={of!r}: allowed {', '.join(measures)}")
    measure = measures[of]
    by = list(by)
    check_groups(frame, by)
    budget = frame.env_steps.max()
    edges = [budget * i / windows for i in range(windows + 1)]
    rows = []
    for run, m in frame.groupby("run", sort=True):
        head = m.iloc[0]
        reached = m.env_steps.max()
        row = {k: head[k] for k in by + ["seed", "status"] if k in head.index}
        for lo, hi in zip(edges, edges[1:]):
            row[f"<={_steps_label(hi)}"] = measure(m, lo, hi) if reached >= hi - 0.01 * budget else np.nan
        row["whole"] = measure(m)
        rows.append(row)
    return pd.DataFrame(rows).sort_values([k for k in by + ["seed"] if k in rows[0]], kind="stable",
                                          ignore_index=True) if rows else pd.DataFrame()


def _steps_label(steps: float) -> str:
    """200000 -> 200k, 1500000 -> 1.5M."""
    if steps >= 1e6:
        return f"{steps / 1e6:.3g}M"
    return f"{steps / 1e3:.3g}k" if steps >= 1e3 else f"{steps:.3g}"


def iqm_table(scores: pd.DataFrame, by: Sequence[str] = (), statuses: Sequence[str] = ("finished",),
              reps: int = 2000, seed: int = 0) -> pd.DataFrame:
    """Per arm of `by`: IQM of the scores of runs whose status is in `statuses`, its 95%
    bootstrap CI, how many runs it rests on and how many were left out by status (so that a
    running or failed job shows, rather than counting as zero)."""
    from rliable import library as rly, metrics

    by = list(by)
    check_groups(scores, by)
    rows = []
    for group, runs in (scores.groupby(by, sort=True, dropna=False) if by else [((), scores)]):
        group = group if isinstance(group, tuple) else (group,)
        used = runs[runs.status.isin(statuses) & runs.score.notna()]
        row = dict(zip(by, group))
        row.update({"n_runs": len(used), **{f"n_{s}": int((runs.status == s).sum())
                                            for s in ("finished", "running", "stopped", "failed")},
                    "env_steps": used.env_steps.median() if len(used) else np.nan,
                    "random": runs.random.mean()})
        if len(used):
            # rliable 1.2's StratifiedBootstrap draws its resamples from numpy's global RNG and
            # ignores random_state, so each arm seeds that RNG itself (restored after): the same
            # scores give the same CI on every run, whatever other arms the table holds
            global_state = np.random.get_state()
            np.random.seed(seed)
            try:
                with warnings.catch_warnings():  # rliable hands arch its random_state the old way
                    warnings.simplefilter("ignore", FutureWarning)
                    point, interval = rly.get_interval_estimates(
                        {"arm": used.score.to_numpy()[:, None]}, lambda s: np.array([metrics.aggregate_iqm(s)]),
                        reps=reps, random_state=np.random.RandomState(seed))
            finally:
                np.random.set_state(global_state)
            row.update(iqm=float(point["arm"][0]), ci_low=float(interval["arm"][0, 0]),
                       ci_high=float(interval["arm"][1, 0]))
        else:
            row.update(iqm=np.nan, ci_low=np.nan, ci_high=np.nan)
        rows.append(row)
    return pd.DataFrame(rows)
