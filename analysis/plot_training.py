"""Learning curves of high-level runs: episode return against the transitions the learner
processed (the paper's x-axis) and against env steps, with the random policy's return.

    python analysis/plot_training.py out.png outputs/<run dir> [outputs/<run dir> ...]
"""
from __future__ import annotations

import sys
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import pandas as pd  # noqa: E402


def plot(out: Path, run_dirs: list[Path], points: int = 60) -> Path:
    """Each run's returns as a running mean over about 1/`points` of its rows, so that long
    runs (thousands of log rows, one episode each) read as curves rather than spikes."""
    fig, axes = plt.subplots(1, 2, figsize=(11, 4))
    for run in run_dirs:
        m = pd.read_csv(run / "metrics.csv")
        returns = m[m.key == "episode_return"]
        label = run.name
        window = max(10, len(returns) // points)
        for ax, x in zip(axes, ("learner_steps", "env_steps")):
            line, = ax.plot(returns[x], returns.value.rolling(window, min_periods=1).mean(), label=label)
            random = m[m.key == "random_return"].value
            if len(random):
                ax.axhline(float(random.iloc[0]), color=line.get_color(), ls="--", lw=1)
    for ax, x in zip(axes, ("transitions processed by the learner", "env steps")):
        ax.set_xlabel(x)
        ax.set_ylabel("episode return (dashed: random policy)")
        ax.grid(alpha=0.3)
    axes[0].legend()
    fig.tight_layout()
    fig.savefig(out, dpi=110)
    return out


if __name__ == "__main__":
    print(plot(Path(sys.argv[1]), [Path(a) for a in sys.argv[2:]]))
