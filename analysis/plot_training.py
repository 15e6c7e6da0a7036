"""Learning curves of single high-level runs (one line each, from run dirs or metrics files):
episode return against the transitions the learner processed (the paper's x-axis) and
against env steps, with the random policy's return. For means over seeds, plot_sweep.py.

    python analysis/plot_training.py out.png outputs/<run dir or metrics.csv[.gz]> [...]
"""
from __future__ import annotations

import argparse
from pathlib import Path

import matplotlib.pyplot as plt
import pandas as pd

from hvc.analysis.returns import episode_returns
from hvc.analysis.runs import METRICS_FILES, last_timeline, read_metrics


def plot(out: Path, run_dirs: list[Path], points: int = 60) -> Path:
    draw(run_dirs, points).savefig(out, dpi=110)
    return out


def draw(run_dirs: list[Path], points: int = 60):
    """Each run's return per episode, averaged over about 1/`points` of its rows (weighted by
    the episodes in each row), so that long runs read as curves rather than spikes."""
    metrics = {run: last_timeline(pd.read_csv(run)) if run.is_file() else read_metrics(run) for run in run_dirs}
    for run, m in metrics.items():  # every run read before a figure opens: an error leaves none open
        if m.empty:
            raise SystemExit(f"no metrics in {run}: give a metrics file or a run dir holding one of {METRICS_FILES}")
    fig, axes = plt.subplots(1, 2, figsize=(11, 4))
    for run, m in metrics.items():
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
    return fig


def main(argv: list[str] | None = None) -> Path:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("out", type=Path, help="the figure")
    parser.add_argument("runs", type=Path, nargs="+", help="run dirs or metrics.csv[.gz] files, one line each")
    args = parser.parse_args(argv)
    return plot(args.out, args.runs)


if __name__ == "__main__":
    print(main())
