"""Final performance: each run's mean return per episode over the last part of its training,
then, per arm, the interquartile mean over runs with a stratified bootstrap confidence
interval (rliable, Agarwal et al. 2021: the estimate that stays sound with few seeds)."""
from __future__ import annotations

import warnings
from typing import Sequence

import numpy as np
import pandas as pd

from hvc.analysis.curves import check_groups
from hvc.analysis.returns import mean_return


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
