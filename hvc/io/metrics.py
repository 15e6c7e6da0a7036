"""Long-format metrics: one row per logged value, flushed as it is written.

Columns `env_steps, learner_steps, wall_time, key, value`, so `pandas.read_csv` gives a
frame that pivots or filters by key, and a killed run keeps every row it logged.

A training run that goes on from a checkpoint first cuts the file back to what the
checkpoint had seen (`continue_metrics`): the rows a killed run logged after its last
checkpoint would otherwise appear twice, and its env steps would go back.
"""
from __future__ import annotations

import csv
import io
import time
from pathlib import Path
from typing import Mapping

from hvc.io.checkpoint import write_atomically

COLUMNS = ("env_steps", "learner_steps", "wall_time", "key", "value")


class MetricsLogger:
    """Appends rows to `path`; with `tensorboard=True` also writes the same scalars as
    TensorBoard events into `<dir>/tb/` (x-axis: env steps), hiding events from `purge_step`
    on. `wall_time` counts from `wall_offset` (a resumed run's time so far)."""

    def __init__(self, path: str | Path, tensorboard: bool = False, wall_offset: float = 0.0,
                 purge_step: int | None = None):
        self.path = Path(path)
        self._tb = None
        if tensorboard:
            from torch.utils.tensorboard import SummaryWriter

            self._tb = SummaryWriter(str(self.path.parent / "tb"), purge_step=purge_step)
        self.rows = _count_rows(self.path)
        self._file = open(self.path, "a", newline="")  # append: resumed runs continue the file
        self._writer = csv.writer(self._file)
        if self.rows is None:
            self._writer.writerow(COLUMNS)
            self._file.flush()
            self.rows = 0
        self._start, self._offset = time.perf_counter(), float(wall_offset)

    def wall_time(self) -> float:
        return round(self._offset + time.perf_counter() - self._start, 3)

    def log(self, env_steps: int, values: Mapping[str, float], learner_steps: int = 0) -> None:
        wall = self.wall_time()
        for key, value in values.items():
            self._writer.writerow((int(env_steps), int(learner_steps), wall, key, float(value)))
            if self._tb is not None:
                self._tb.add_scalar(key, float(value), int(env_steps))
        self._file.flush()
        self.rows += len(values)

    def mark(self) -> dict[str, float]:
        """What a checkpoint stores to continue this file: its rows so far and the wall time.
        TensorBoard's queue is flushed, so its events reach the checkpoint's step too."""
        if self._tb is not None:
            self._tb.flush()
        return {"rows": self.rows, "wall_time": self.wall_time()}

    def close(self) -> None:
        self._file.close()
        if self._tb is not None:
            self._tb.close()

    def __enter__(self) -> "MetricsLogger":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def _count_rows(path: Path) -> int | None:
    """Data rows in the file; None when there is no file or not even a header."""
    if not path.exists() or path.stat().st_size == 0:
        return None
    with open(path, newline="") as f:
        return sum(1 for _ in f) - 1


def cut_rows(path: Path, env_steps: int, rows: int | None = None) -> tuple[int, float]:
    """Keeps the rows at or before `env_steps` (and only the first `rows`, when known: rows
    logged at that step after the checkpoint, such as a final evaluation, go too), rewriting
    the file atomically; a partial last row of a killed run is dropped with them. Returns
    (rows dropped, wall time of the last row kept)."""
    if not path.exists():
        return 0, 0.0
    with open(path, newline="") as f:
        lines = list(csv.reader(f))
    body = lines[1:] if lines and tuple(lines[0]) == COLUMNS else lines
    kept = []
    for row in body:
        if (rows is not None and len(kept) >= rows) or len(row) != len(COLUMNS) or not _at_most(row[0], env_steps):
            continue
        kept.append(row)
    dropped = len(body) - len(kept)
    if dropped or body is lines:
        out = io.StringIO(newline="")
        csv.writer(out).writerows([COLUMNS, *kept])
        write_atomically(path, out.getvalue().encode())
    return dropped, float(kept[-1][2]) if kept else 0.0


def _at_most(value: str, env_steps: int) -> bool:
    try:
        return int(value) <= env_steps
    except ValueError:
        return False


def continue_metrics(path: Path, checkpoint: Mapping | None, tensorboard: bool = False) -> tuple[MetricsLogger, int]:
    """The metrics logger of a training run starting from `checkpoint` (a loaded one, with
    `counters.env_steps` and, since it was written by this version, `metrics` = MetricsLogger.mark();
    None: from scratch). Rows logged after the checkpoint are dropped first (every row, from
    scratch: a run killed before its first checkpoint), so no row appears twice and env steps
    never go back; wall time goes on from the checkpoint's. Returns (logger, rows dropped)."""
    env_steps = int(checkpoint["counters"]["env_steps"]) if checkpoint is not None else -1
    mark = checkpoint.get("metrics", {}) if checkpoint is not None else {}
    dropped, last_wall = cut_rows(Path(path), env_steps, mark.get("rows"))
    logger = MetricsLogger(path, tensorboard, wall_offset=mark.get("wall_time", last_wall),
                           purge_step=env_steps + 1)
    return logger, dropped
