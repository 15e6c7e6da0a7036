"""Copy what a figure needs of run dirs into the repository, compressed: metrics.csv.gz
(every return row; other keys such as losses thinned to one row per THIN env steps), the
resolved config and options, summary, skills, commands and evaluation report; no checkpoints,
TensorBoard or videos. A `stage=lowlevel` run gives each expert's metrics_<clip>.csv.gz and
result_<clip>.json, and its library once it has finished. Re-exporting a run that goes on
replaces its copy, so a figure's data can be committed as its runs progress and still be drawn
from a fresh clone.

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
KEPT = ("config_resolved.yaml", "overrides.yaml", "summary.json", "skills.json", "commands.log", "failed.json",
        "evaluation.txt")


def run_dirs(paths: list[Path]) -> list[Path]:
    """The run dirs at or under `paths`: dirs holding metrics.csv, and `stage=lowlevel` runs (their
    metrics are per expert, under experts/)."""
    found = set()
    for path in paths:
        for metrics in Path(path).rglob("metrics.csv"):
            lowlevel = metrics.parent.parent.name == "experts"  # <run>/experts/<index>_<clip>/metrics.csv
            found.add(metrics.parents[2] if lowlevel else metrics.parent)
    return sorted(found)


def _write_gzip(path: Path, data: bytes) -> None:
    with open(path, "wb") as raw, gzip.GzipFile(fileobj=raw, mode="wb", mtime=0) as dst:  # same data, same bytes
        dst.write(data)


def _export_experts(run: Path, target: Path) -> None:
    """Each expert's metrics and evaluation, named by its clip (the dir name without its index);
    the library only once the run has finished, so a partial copy never carries a stale one."""
    for expert in sorted((run / "experts").iterdir()):
        if not (expert / "metrics.csv").is_file():
            continue
        name = expert.name.split("_", 1)[1]
        _write_gzip(target / f"metrics_{name}.csv.gz", (expert / "metrics.csv").read_bytes())
        if (expert / "result.json").is_file():
            shutil.copy2(expert / "result.json", target / f"result_{name}.json")
        else:
            (target / f"result_{name}.json").unlink(missing_ok=True)
    for library in run.glob("experts_*.npz"):
        if (run / "summary.json").is_file():
            shutil.copy2(library, target / library.name)
        else:
            (target / library.name).unlink(missing_ok=True)


def export(dest: Path, paths: list[Path]) -> list[Path]:
    out = []
    for run in run_dirs(paths):
        target = Path(dest) / run.name
        target.mkdir(parents=True, exist_ok=True)
        if (run / "experts").is_dir():
            _export_experts(run, target)
        else:
            metrics = pd.read_csv(run / "metrics.csv")
            metrics = metrics[metrics.key.isin(RETURN_KEYS) | (metrics.env_steps % THIN == 0)]
            _write_gzip(target / "metrics.csv.gz", metrics.to_csv(index=False).encode())
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
