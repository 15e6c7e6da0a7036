"""Learning curves of a `stage=lowlevel` run: per clip, tracking reward and completion vs env steps.

    python analysis/plot_lowlevel.py outputs/<run dir> [out.png]
    python analysis/plot_lowlevel.py --steering outputs/<stage=evaluate run dir of a steerable library> [out.png]
    python analysis/plot_lowlevel.py --compare out.png CLIP LABEL=<run dir> LABEL=<run dir> ...

Reads each expert's metrics.csv (long format) and draws the on-policy (noisy) per-step
reward and episode completion during RL, with the deterministic evaluation before RL
(after pre-training) and at the end as markers.
"""
from __future__ import annotations

import argparse
from pathlib import Path

import matplotlib.pyplot as plt
import pandas as pd
from matplotlib.ticker import EngFormatter

from hvc.analysis.runs import read_metrics


def load(run_dir: Path) -> dict[str, pd.DataFrame]:
    curves = {}
    for metrics in sorted((run_dir / "experts").glob("*/metrics.csv")):
        frame = read_metrics(metrics.parent)  # a resumed expert's superseded rows dropped
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
    return _save_curves(fig, axes, out)


def _save_curves(fig, axes, out: Path) -> Path:
    for ax in axes:
        ax.set_xlabel("env steps")
        ax.xaxis.set_major_formatter(EngFormatter(sep=""))  # 500k, 1M: full integers overlap
        ax.grid(alpha=0.3)
    axes[0].legend()
    fig.tight_layout()
    fig.savefig(out, dpi=110)
    return out


def plot_compare(out: Path, clip: str, runs: dict[str, Path]) -> Path:
    """One clip's curves from several runs (e.g. settings resumed from one checkpoint)."""
    fig, axes = plt.subplots(1, 2, figsize=(11, 4))
    for label, run_dir in runs.items():
        curves = load(run_dir)
        matches = [name for name in curves if name.endswith(f"_{clip}") or f"_{clip}_" in name]
        if len(matches) != 1:
            raise SystemExit(f"{run_dir}: {len(matches)} experts match clip {clip!r}: {matches or list(curves)}")
        table = curves[matches[0]]
        for ax, key in zip(axes, ("step_reward", "completion")):
            ax.plot(table.index, table[key].rolling(5, min_periods=1).mean(), label=label)
    axes[0].set_title(f"{clip}: tracking reward per step (with noise)")
    axes[1].set_title(f"{clip}: completion of the remaining clip")
    return _save_curves(fig, axes, out)


def plot_steering(eval_dir: Path, out: Path) -> Path:
    """Commanded vs achieved turning rate (and completion) of a steerable policy, from the
    `achieved_rate/<clip>/<rate>` and `completion/<clip>/<rate>` rows of stage=evaluate."""
    m = pd.read_csv(eval_dir / "metrics.csv")
    rows = m[m.key.str.startswith(("achieved_rate/", "completion/"))].copy()
    if rows.empty:
        raise SystemExit(f"{eval_dir}/metrics.csv has no steering rows: evaluate a steerable library")
    parts = rows.key.str.split("/", expand=True)
    rows["measure"], rows["commanded"] = parts[0], parts[2].astype(float)
    table = rows.pivot_table(index="commanded", columns="measure", values="value")
    fig, (rate_ax, done_ax) = plt.subplots(1, 2, figsize=(10, 4))
    limit = float(abs(table.index.to_numpy()).max())
    rate_ax.plot([-limit, limit], [-limit, limit], "k--", lw=1, label="commanded")
    rate_ax.plot(table.index, table["achieved_rate"], "o-", label="achieved")
    rate_ax.set_xlabel("commanded turning rate (rad/s)")
    rate_ax.set_ylabel("achieved (slope of the heading, rad/s)")
    rate_ax.legend()
    done_ax.bar(table.index, table["completion"], width=0.3)
    done_ax.set_xlabel("commanded turning rate (rad/s)")
    done_ax.set_ylabel("completion of 8 gait cycles")
    for ax in (rate_ax, done_ax):
        ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(out, dpi=110)
    return out


def main(argv: list[str] | None = None) -> Path:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], usage="%(prog)s [--steering] RUN_DIR [out.png] | --compare out.png CLIP LABEL=<run dir> ...")
    mode = parser.add_mutually_exclusive_group()
    mode.add_argument("--steering", action="store_true", help="the turning rates of a steerable library's evaluation")
    mode.add_argument("--compare", action="store_true", help="one clip's curves from several runs, one line each")
    parser.add_argument("args", nargs="+", help="the run dir [out.png]; with --compare: out.png CLIP LABEL=<run dir> ...")
    args = parser.parse_args(argv)
    if args.compare:
        if len(args.args) < 3 or not all("=" in a for a in args.args[2:]):
            parser.error("--compare needs out.png CLIP LABEL=<run dir> [LABEL=<run dir> ...]")
        runs = dict(a.split("=", 1) for a in args.args[2:])
        return plot_compare(Path(args.args[0]), args.args[1], {label: Path(d) for label, d in runs.items()})
    if len(args.args) > 2:
        parser.error(f"one run dir and at most one out.png, got {len(args.args)} arguments")
    run = Path(args.args[0])
    out = Path(args.args[1]) if len(args.args) > 1 else run / ("steering.png" if args.steering else "learning_curves.png")
    return plot_steering(run, out) if args.steering else plot(run, out)


if __name__ == "__main__":
    print(main())
