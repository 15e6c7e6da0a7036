"""Returns per episode from metrics rows. Training logs, every `log_every` env steps, the
mean return of the episodes that ended since the previous log (`episode_return`) and the
running episode count (`episodes`); a mean over rows would weigh each row alike, so these
weigh each episode once."""
from __future__ import annotations

import pandas as pd

from hvc.analysis.runs import last_timeline, log_events


def episode_returns(metrics: pd.DataFrame) -> pd.DataFrame:
    """Per log row of one run: env_steps, learner_steps, the mean return of the episodes that
    ended since the previous row (`value`) and how many they were (`n`)."""
    m = last_timeline(metrics[metrics.key.isin(["episodes", "episode_return"])].reset_index(drop=True))
    if m.empty:
        return pd.DataFrame(columns=["env_steps", "learner_steps", "value", "n"])
    row = log_events(m)
    rows = m.pivot_table(index=row, columns="key", values="value", sort=True)
    rows[["env_steps", "learner_steps"]] = m.groupby(row)[["env_steps", "learner_steps"]].first()
    rows["n"] = rows["episodes"].ffill().diff().fillna(rows["episodes"])
    rows = rows.dropna(subset=["episode_return"])
    rows = rows[rows.n > 0]
    return rows[["env_steps", "learner_steps", "episode_return", "n"]].rename(
        columns={"episode_return": "value"}).reset_index(drop=True)


def mean_return(metrics: pd.DataFrame, lo: float = 0, hi: float = float("inf")) -> float:
    """The mean return per episode over episodes ending in (lo, hi] env steps."""
    r = episode_returns(metrics)
    r = r[(r.env_steps > lo) & (r.env_steps <= hi)]
    return float((r.value * r.n).sum() / r.n.sum()) if r.n.sum() else float("nan")


def mean_episode_length(metrics: pd.DataFrame, lo: float = 0, hi: float = float("inf")) -> float:
    """Env steps per episode ended in (lo, hi] env steps: the mean episode length in control
    steps (env steps count every env's steps, episodes every env's ends), which for a walker
    whose episodes end in a fall long before the time limit is how long it stays up."""
    r = episode_returns(metrics)
    before, inside = r[r.env_steps <= lo], r[(r.env_steps > lo) & (r.env_steps <= hi)]
    if inside.empty:
        return float("nan")
    start = before.env_steps.iloc[-1] if len(before) else 0.0
    return float((inside.env_steps.iloc[-1] - start) / inside.n.sum())
