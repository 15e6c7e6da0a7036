"""Draw a sweep: learning curves (mean over seeds +- standard error) per arm, one panel per
facet, and print each arm's final IQM with its bootstrap CI and how many runs finished
(`--last 1` scores each run over all of it instead of its last 10%; `--windows 5` also prints
each run's mean return and mean episode length per fifth of the env steps: when each seed took
off, how long its episodes lasted).

    python analysis/plot_sweep.py <sweep dir or run dirs...> --by fragment_len -o fig.png
    python analysis/plot_sweep.py outputs/sweeps/core_tasks/<time> --by controller --facet task -o fig6.png
"""
from __future__ import annotations

import argparse
import os
from pathlib import Path


from hvc.analysis import curves, final_scores, iqm_table, load_runs, window_scores
from hvc.analysis.plots import plot_curves
from hvc.analysis.runs import STATUSES


def main(argv: list[str] | None = None) -> Path:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("dirs", nargs="+", type=Path, help="sweep dirs, exported figure dirs or run dirs")
    parser.add_argument("--by", default="", help="comma-separated keys, one line per arm (e.g. controller)")
    parser.add_argument("--facet", default=None, help="one panel per value of this key (e.g. task)")
    parser.add_argument("--x", default="learner_steps", choices=["learner_steps", "env_steps"])
    parser.add_argument("--points", type=int, default=100, help="grid points per curve")
    parser.add_argument("--partial", action="store_true",
                        help="draw curve points that only some seeds reached (n_seeds marks them)")
    parser.add_argument("--last", type=float, default=0.1,
                        help="share of each run's env steps its score averages over (1: the whole run, how fast it learned)")
    parser.add_argument("--windows", type=int, default=0,
                        help="also print each run's mean return and episode length per this many equal spans of env steps")
    parser.add_argument("--title", default=None, help="the figure's title (default: the dirs' common folder)")
    parser.add_argument("-o", "--out", type=Path, default=Path("sweep.png"))
    args = parser.parse_args(argv)
    if not 0 < args.last <= 1:
        parser.error(f"--last must be in (0, 1], got {args.last}")
    if args.windows < 0:
        parser.error(f"--windows must be 0 (none) or more, got {args.windows}")
    by = [k for k in args.by.split(",") if k]
    keys = by + ([args.facet] if args.facet else [])
    frame = load_runs(args.dirs, keys=["episodes", "episode_return", "random_return"])
    missing = [k for k in keys if k not in frame.columns]
    if missing:
        parser.error(f"no option {', '.join(missing)} in these runs; they have: {', '.join(frame.attrs['factors'])}")
    try:
        lines = curves(frame, keys, x=args.x, points=args.points, complete=not args.partial)
        scores = final_scores(frame, last=args.last)
        table = iqm_table(scores, keys, statuses=STATUSES[:3] if args.partial else ("finished",))
        spans = [(of, window_scores(frame, args.windows, keys, of)) for of in ("return", "length")] if args.windows else []
    except ValueError as error:
        parser.error(str(error))
    fig = plot_curves(lines, by, args.facet, x=args.x, scores=scores, title=args.title or _title(args.dirs))
    args.out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(args.out, dpi=110)
    print(table.to_string(index=False, float_format=lambda v: f"{v:.3g}"))
    for of, per_span in spans:
        print(f"mean episode {of} per span of env steps:")
        print(per_span.to_string(index=False, float_format=lambda v: f"{v:.3g}"))
    print(args.out)
    return args.out


def _title(dirs: list[Path]) -> str:
    """One dir as given; several as their common folder and how many (a list of them would
    run off the figure)."""
    if len(dirs) == 1:
        return str(dirs[0])
    try:
        common = os.path.relpath(os.path.commonpath([d.resolve() for d in dirs]))
    except ValueError:  # dirs on different drives (Windows): no common folder
        return f"{len(dirs)} dirs"
    return f"{common} ({len(dirs)} dirs)"


if __name__ == "__main__":
    main()
