"""Learning curves of high-level runs: episode return against the transitions the learner
processed (the paper's x-axis) and against env steps, with the random policy's return.

    python analysis/plot_training.py out.png outputs/<run dir or metrics.csv[.gz]> [...]
"""
from __future__ import annotations

import sys
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import pandas as pd  # noqa: E402


def episode_returns(metrics: pd.DataFrame) -> pd.DataFrame:
    """Per log row: env_steps, learner_steps, the mean return of the episodes that ended since
    the previous row and how many they were (`n`). A resumed run logs again from its last
    checkpoint: the rows it superseded are dropped, so each episode counts once."""
    m = metrics[metrics.key.isin(["episodes", "episode_return"])].reset_index(drop=True)
    row = (m[["env_steps", "learner_steps", "wall_time"]].diff().abs().sum(axis=1) != 0).cumsum()
    rows = m.pivot_table(index=row, columns="key", values="value", sort=True)
    rows[["env_steps", "learner_steps"]] = m.groupby(row)[["env_steps", "learner_steps"]].first()
    later_min = rows.env_steps.astype(float)[::-1].cummin()[::-1].shift(-1, fill_value=float("inf"))
    rows = rows[rows.env_steps < later_min]  # keep only the last timeline after each resume
    rows["n"] = rows["episodes"].ffill().diff().fillna(rows["episodes"])
    rows = rows.dropna(subset=["episode_return"])
    return rows[["env_steps", "learner_steps", "episode_return", "n"]].rename(columns={"episode_return": "value"})


def mean_return(metrics: pd.DataFrame, lo: float = 0, hi: float = float("inf")) -> float:
    """The mean return per episode over episodes ending in [lo, hi) env steps. A plain mean of
    the rows would favour long episodes: they end in rows of their own."""
    r = episode_returns(metrics)
    r = r[(r.env_steps >= lo) & (r.env_steps < hi)]
    return float((r.value * r.n).sum() / r.n.sum())


def plot(out: Path, run_dirs: list[Path], points: int = 60) -> Path:
    """Each run's return per episode, averaged over about 1/`points` of its rows (weighted by
    the episodes in each row), so that long runs read as curves rather than spikes."""
    fig, axes = plt.subplots(1, 2, figsize=(11, 4))
    for run in run_dirs:
        m = pd.read_csv(run if run.suffix in (".csv", ".gz") else run / "metrics.csv")
        returns = episode_returns(m)
        label = run.name.removesuffix(".gz").removesuffix(".csv")
        window = max(10, len(returns) // points)
        total = (returns.value * returns.n).rolling(window, min_periods=1).sum()
        smooth = total / returns.n.rolling(window, min_periods=1).sum()
        for ax, x in zip(axes, ("learner_steps", "env_steps")):
            line, = ax.plot(returns[x], smooth, label=label)
            random = m[m.key == "random_return"].value
            if len(random):
                ax.axhline(float(random.iloc[0]), color=line.get_color(), ls="--", lw=1)
    for ax, x in zip(axes, ("transitions processed by the learner", "env steps")):
        ax.set_xlabel(x)
        ax.set_ylabel("return per episode (dashed: random policy)")
        ax.grid(alpha=0.3)
    axes[0].legend()
    fig.tight_layout()
    fig.savefig(out, dpi=110)
    return out


if __name__ == "__main__":
    if len(sys.argv) < 3:
        raise SystemExit(__doc__)
    print(plot(Path(sys.argv[1]), [Path(a) for a in sys.argv[2:]]))
