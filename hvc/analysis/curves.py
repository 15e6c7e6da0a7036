"""Learning curves over seeds: each run's returns per episode on a common grid, then the mean
and standard error over the runs of each arm (the paper's bands).

Runs of unequal length: a run contributes to the grid points it reached; `n_seeds` says how
many runs each point averages, and by default points that not every run of the arm reached
are left out, so a mean never silently changes its seeds along the curve.
"""
from __future__ import annotations

import warnings
from typing import Sequence

import numpy as np
import pandas as pd

from hvc.analysis.returns import episode_returns

X_AXES = ("learner_steps", "env_steps")


def run_curve(metrics: pd.DataFrame, x: str, grid: np.ndarray, window: float) -> np.ndarray:
    """One run's mean return per episode over the episodes ending in (g - window, g] of `x`,
    at each grid point g; NaN past the run's last row or where no episode ended."""
    r = episode_returns(metrics).sort_values(x)
    values = np.full(len(grid), np.nan)
    if r.empty:
        return values
    at = r[x].to_numpy(float)
    weighted = np.concatenate([[0.0], np.cumsum((r.value * r.n).to_numpy())])
    counts = np.concatenate([[0.0], np.cumsum(r.n.to_numpy())])
    hi, lo = np.searchsorted(at, grid, "right"), np.searchsorted(at, grid - window, "right")
    n = counts[hi] - counts[lo]
    reached = grid <= at[-1]
    ok = reached & (n > 0)
    values[ok] = (weighted[hi] - weighted[lo])[ok] / n[ok]
    return values


def check_groups(frame: pd.DataFrame, keys: Sequence[str]) -> None:
    """Runs averaged together must differ only in their seed: any other swept key left out of
    `keys` would average different arms (one line naming it and how to split on it)."""
    factors = [f for f in frame.attrs.get("factors", []) if f not in (*keys, "seed")]
    if factors:
        raise ValueError(f"runs differ in {', '.join(factors)} besides the seed; group by it too "
                         f"(--by / --facet {factors[0]})")


def curves(frame: pd.DataFrame, by: Sequence[str] = (), x: str = "learner_steps", points: int = 100,
           window: float = 0.05, complete: bool = True) -> pd.DataFrame:
    """Mean return per episode and its standard error over the runs of each group of `by`, at
    `points` grid points of `x` spanning the longest run of the group; each run's value at a
    point is its mean return over the trailing `window` fraction of that span. Columns: *by,
    x, mean, se, n_seeds, n_runs. Failed runs and runs without returns are left out."""
    if x not in X_AXES:
        raise ValueError(f"x={x!r}; allowed: {', '.join(X_AXES)}")
    by = list(by)
    check_groups(frame, by)
    frame = frame[(frame.status != "failed") & frame.key.isin(["episodes", "episode_return"])]
    out = []
    for group, runs in (frame.groupby(by, sort=True, dropna=False) if by else [((), frame)]):
        group = group if isinstance(group, tuple) else (group,)
        top = runs[x].max()
        if not top > 0:
            continue
        grid = np.linspace(top / points, top, points)
        per_run = np.array([run_curve(m, x, grid, max(window * top, top / points))
                            for _, m in runs.groupby("run", sort=True)])
        n = (~np.isnan(per_run)).sum(0)
        with warnings.catch_warnings():  # columns no run reached are NaN, as they should be
            warnings.simplefilter("ignore", RuntimeWarning)
            mean = np.nanmean(per_run, axis=0)
            std = np.nanstd(per_run, axis=0, ddof=1)
        curve = pd.DataFrame({x: grid, "mean": mean, "se": np.where(n > 1, std / np.sqrt(np.maximum(n, 1)), np.nan),
                              "n_seeds": n, "n_runs": len(per_run)})
        if complete:
            curve = curve[curve.n_seeds == len(per_run)]
        for key, value in zip(by, group):
            curve.insert(len(curve.columns) - 5, key, value)
        out.append(curve)
    columns = [*by, x, "mean", "se", "n_seeds", "n_runs"]
    return pd.concat(out, ignore_index=True)[columns] if out else pd.DataFrame(columns=columns)
