"""Libraries (or structured policies) side by side from their `stage=evaluate` runs: per
library, each clip's tracking score and the random-switch survival, as a markdown table.

    hvc-run -m stage=evaluate episodes=100 library=shipped,outputs/skills/<run>/experts_go_to_target.npz
    python analysis/compare_libraries.py outputs/sweeps/<date>/<time>
    python analysis/compare_libraries.py <evaluate run dirs...> --by library --score completion
"""
from __future__ import annotations

import argparse
from pathlib import Path

from hvc.analysis import load_runs
from hvc.analysis.evaluations import evaluation_table, markdown


def main(argv: list[str] | None = None) -> str:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("dirs", nargs="+", type=Path, help="evaluate run dirs, or sweep dirs holding them")
    parser.add_argument("--by", default=None,
                        help="comma-separated options naming each row (default: the options that differ between "
                             "the runs, else the run dir)")
    parser.add_argument("--score", default="reward",
                        help="the per-clip score: reward, completion, fall_rate, openloop_reward, energy_ori, ...")
    args = parser.parse_args(argv)
    try:
        frame = load_runs(args.dirs)
        by = [k for k in args.by.split(",") if k] if args.by is not None else _readable_factors(frame)
        table = evaluation_table(frame, by=by, score=args.score)
    except (FileNotFoundError, ValueError) as error:
        parser.error(str(error))
    text = markdown(table)
    print(text)
    return text


def _readable_factors(frame) -> list[str]:
    """The options that differ between the runs, but for whole config sections (such as
    `clips.entries`), which would print as long blobs: each row is told apart by the run dir
    then."""
    return [k for k in frame.attrs["factors"] if k not in frame.attrs["sections"]]


if __name__ == "__main__":
    main()
