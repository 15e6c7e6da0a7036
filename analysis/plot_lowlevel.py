"""Learning curves of a `stage=lowlevel` run: per clip, tracking reward and completion vs env steps.

    python analysis/plot_lowlevel.py outputs/<run dir> [out.png]

Reads each expert's metrics.csv (long format) and draws the on-policy (noisy) per-step
reward and episode completion during RL, with the deterministic evaluation before RL
(after pre-training) and at the end as markers.
"""
from __future__ import annotations

import sys
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import pandas as pd  # noqa: E402


def load(run_dir: Path) -> dict[str, pd.DataFrame]:
    curves = {}
    for metrics in sorted((run_dir / "experts").glob("*/metrics.csv")):
        frame = pd.read_csv(metrics)
        curves[metrics.parent.name] = frame.pivot_table(index="env_steps", columns="key", values="value", aggfunc="last")
    return curves


def plot(run_dir: Path, out: Path) -> Path:
    curves = load(run_dir)
    fig, axes = plt.subplots(1, 2, figsize=(11, 4))
    for name, table in curves.items():
        label = name.split("_", 1)[1]
        for ax, (train_key, eval_key) in zip(axes, (("step_reward", "eval_reward"), ("completion", "eval_completion"))):
            if train_key in table:
                line, = ax.plot(table.index, table[train_key].rolling(5, min_periods=1).mean(), label=label)
                evals = table[eval_key].dropna() if eval_key in table else pd.Series(dtype=float)
                ax.plot(evals.index, evals.values, "o", color=line.get_color())
    axes[0].set_title("tracking reward per step (line: with noise; dots: deterministic eval)")
    axes[1].set_title("completion of the remaining clip")
    for ax in axes:
        ax.set_xlabel("env steps")
        ax.grid(alpha=0.3)
    axes[0].legend()
    fig.tight_layout()
    fig.savefig(out, dpi=110)
    return out


if __name__ == "__main__":
    run = Path(sys.argv[1])
    print(plot(run, Path(sys.argv[2]) if len(sys.argv) > 2 else run / "learning_curves.png"))
