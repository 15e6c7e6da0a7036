"""A sweep goes on past a failed job and ends with a summary of the jobs that failed.

A job that fails writes `failed.json` into its own dir and returns (hvc.cli), so every
launcher goes on with the next job; this Hydra callback (`hydra.callbacks` in
conf/config.yaml) runs in the launching process when the sweep ends and reads those files,
whichever launcher ran the jobs and wherever they ran, as long as they share the sweep dir.
"""
from __future__ import annotations

import json
import shutil
import sys
import time
from pathlib import Path
from typing import Any

from hydra.experimental.callback import Callback
from omegaconf import DictConfig

FAILED_FILE = "failed.json"


def record_failure(job_dir: Path, overrides: list[str], error: str, kind: str, log_file: Path) -> None:
    """`kind`: "error" (the user's, told in one line) or "crash" (its traceback is in `log_file`)."""
    (job_dir / FAILED_FILE).write_text(json.dumps({"overrides": overrides, "kind": kind, "error": error,
                                                   "log": str(log_file)}, indent=2))


def forget_failure(job_dir: Path) -> None:
    """A job run again in the same dir starts without the failure of its last attempt."""
    (job_dir / FAILED_FILE).unlink(missing_ok=True)


class SweepReport(Callback):
    # The last sweep of this process: its dir, and how many of its jobs failed (hvc-run exits non-zero on it).
    sweep_dir: Path | None = None
    failed = 0

    def on_multirun_start(self, config: DictConfig, **kwargs: Any) -> None:
        self.started = time.time()
        SweepReport.sweep_dir, SweepReport.failed = Path(str(config.hydra.sweep.dir)), 0

    def on_multirun_end(self, config: DictConfig, **kwargs: Any) -> None:
        sweep_dir = Path(str(config.hydra.sweep.dir))
        since = getattr(self, "started", 0.0) - 1.0  # a reused sweep dir may hold an older sweep's jobs
        jobs = [p.parent for p in sweep_dir.rglob(".hydra") if p.stat().st_mtime >= since]
        failures = sorted((p for p in sweep_dir.rglob(FAILED_FILE) if p.stat().st_mtime >= since),
                          key=lambda p: p.parent.name)
        SweepReport.failed = len(failures)
        if not failures:
            return
        print(f"hvc-run: sweep {sweep_dir}: {len(failures)} of {len(jobs)} jobs failed:", file=sys.stderr)
        for path in failures:
            failure = json.loads(path.read_text())
            where = f" (traceback in {failure['log']})" if failure["kind"] == "crash" else ""
            print(f"hvc-run:   {path.parent.relative_to(sweep_dir)}: {failure['error']}{where}", file=sys.stderr)


def remove_stub_sweep() -> None:
    """The dir of a sweep that failed before its first job (a typo in a key), if it holds
    nothing but Hydra's multirun.yaml."""
    sweep_dir = SweepReport.sweep_dir
    if sweep_dir and sweep_dir.is_dir() and {p.name for p in sweep_dir.iterdir()} <= {"multirun.yaml"}:
        shutil.rmtree(sweep_dir)
