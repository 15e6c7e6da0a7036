"""Long-format metrics: one row per logged value, flushed as it is written.

Columns `env_steps, learner_steps, wall_time, key, value`, so `pandas.read_csv` gives a
frame that pivots or filters by key, and a killed run keeps every row it logged.
"""
from __future__ import annotations

import csv
import time
from pathlib import Path
from typing import Mapping

COLUMNS = ("env_steps", "learner_steps", "wall_time", "key", "value")


class MetricsLogger:
    """Appends rows to `path`; with `tensorboard=True` also writes the same scalars as
    TensorBoard events into `<dir>/tb/` (x-axis: env steps)."""

    def __init__(self, path: str | Path, tensorboard: bool = False):
        self.path = Path(path)
        self._tb = None
        if tensorboard:
            from torch.utils.tensorboard import SummaryWriter

            self._tb = SummaryWriter(str(self.path.parent / "tb"))
        new = not self.path.exists() or self.path.stat().st_size == 0
        self._file = open(self.path, "a", newline="")  # append: resumed runs continue the file
        self._writer = csv.writer(self._file)
        if new:
            self._writer.writerow(COLUMNS)
            self._file.flush()
        self._start = time.perf_counter()

    def log(self, env_steps: int, values: Mapping[str, float], learner_steps: int = 0) -> None:
        wall = round(time.perf_counter() - self._start, 3)
        for key, value in values.items():
            self._writer.writerow((int(env_steps), int(learner_steps), wall, key, float(value)))
            if self._tb is not None:
                self._tb.add_scalar(key, float(value), int(env_steps))
        self._file.flush()

    def close(self) -> None:
        self._file.close()
        if self._tb is not None:
            self._tb.close()

    def __enter__(self) -> "MetricsLogger":
        return self

    def __exit__(self, *exc) -> None:
        self.close()
