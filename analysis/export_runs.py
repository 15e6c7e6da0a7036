"""Copy what a figure needs of run dirs into the repository, compressed: metrics.csv.gz
(every return row; other keys such as losses thinned to one row per THIN env steps), the
resolved config and options, summary, skills and commands; no checkpoints, TensorBoard or
videos. Re-exporting a run that goes on replaces its copy, so a figure's data can be
committed as its runs progress and still be drawn from a fresh clone.

    python analysis/export_runs.py docs/results/<figure>/runs <run or sweep dirs...>
"""
from __future__ import annotations

import argparse
import gzip
import shutil
from pathlib import Path

import pandas as pd

THIN = 1000
RETURN_KEYS = ("episode_return", "episodes", "random_return")
KEPT = ("config_resolved.yaml", "overrides.yaml", "summary.json", "skills.json", "commands.log", "failed.json")


def run_dirs(paths: list[Path]) -> list[Path]:
    """The run dirs at or under `paths` (dirs holding metrics.csv)."""
    found = []
    for path in paths:
        found += [p.parent for p in sorted(Path(path).rglob("metrics.csv")) if "experts" not in p.parts]
    return found


def export(dest: Path, paths: list[Path]) -> list[Path]:
    out = []
    for run in run_dirs(paths):
        target = Path(dest) / run.name
        target.mkdir(parents=True, exist_ok=True)
        metrics = pd.read_csv(run / "metrics.csv")
        metrics = metrics[metrics.key.isin(RETURN_KEYS) | (metrics.env_steps % THIN == 0)]
        with open(target / "metrics.csv.gz", "wb") as raw, \
                gzip.GzipFile(fileobj=raw, mode="wb", mtime=0) as dst:  # mtime 0: same data, same bytes
            dst.write(metrics.to_csv(index=False).encode())
        for name in KEPT:
            if (run / name).is_file():
                shutil.copy2(run / name, target / name)
            else:
                (target / name).unlink(missing_ok=True)  # e.g. summary.json of a run that went on
        out.append(target)
    return out


def main(argv: list[str] | None = None) -> list[Path]:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("target", type=Path, help="where the copies go, e.g. docs/results/<figure>/runs")
    parser.add_argument("dirs", type=Path, nargs="+", help="run dirs, or sweep dirs holding them")
    args = parser.parse_args(argv)
    return export(args.target, args.dirs)


if __name__ == "__main__":
    for target in main():
        print(target)
