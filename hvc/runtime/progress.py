"""Progress of a training loop that a user sees wherever the output goes.

In a terminal, a tqdm bar (on stderr) whose `ret=` is the mean return of the recent
episodes. Where output goes to a file (nohup, SLURM, CI) a bar prints nothing useful, so a
log line every `seconds` says how far the run is, how fast it goes and when it will end.
Either way a closing line says how the run ended: finished, stopped or failed.
"""
from __future__ import annotations

import logging
import sys
import time
from contextlib import contextmanager
from typing import Iterator

from tqdm import tqdm

log = logging.getLogger(__name__)

RECENT_EPISODES = 100  # the episodes whose mean return progress shows


def _duration(seconds: float) -> str:
    seconds = int(seconds)
    hours, rest = divmod(seconds, 3600)
    return f"{hours}h{rest // 60:02d}m" if hours else f"{rest // 60}m{rest % 60:02d}s"


class Progress:
    """Env steps of one training loop towards `total`, from `done` (a resumed run's)."""

    def __init__(self, name: str, total: int, done: int = 0, seconds: float = 30.0, position: int | None = None):
        self.name, self.total, self.seconds = name, int(total), float(seconds)
        self.steps = self.start_steps = int(done)
        self.recent_return: float | None = None
        self.learner_steps: int | None = None
        self.start = self.last_line = time.monotonic()
        self.bar = (tqdm(total=self.total, initial=self.steps, desc=name, unit="step", position=position,
                         mininterval=2.0) if sys.stderr.isatty() else None)
        self.lines = not (sys.stdout.isatty() and sys.stderr.isatty())  # a stream that a bar does not reach

    def restart(self) -> None:
        """The clock starts now: a clip that waited for a free worker counts its speed, eta and
        elapsed time from when its worker started, not from when the stage did."""
        self.start, self.start_steps = time.monotonic(), self.steps

    def update(self, steps: int, recent_return: float | None = None, learner_steps: int | None = None) -> None:
        """`steps`: the env steps done so far; the others when known (kept until the next)."""
        if recent_return is not None and recent_return != self.recent_return and self.bar is not None:
            self.bar.set_postfix(ret=f"{recent_return:.2f}", refresh=False)
        self.recent_return = self.recent_return if recent_return is None else float(recent_return)
        self.learner_steps = self.learner_steps if learner_steps is None else int(learner_steps)
        if steps < self.steps:  # a clip worker restarted from a checkpoint older than its last report
            self.start, self.start_steps = time.monotonic(), int(steps)
            if self.bar is not None:
                self.bar.reset(total=self.total)
                self.bar.update(steps)
        elif self.bar is not None:
            self.bar.update(steps - self.steps)
        self.steps = int(steps)
        now = time.monotonic()
        if self.lines and now - self.last_line >= self.seconds:
            self.last_line = now
            log.info("%s: %s", self.name, self.status())

    def status(self) -> str:
        elapsed = time.monotonic() - self.start
        rate = (self.steps - self.start_steps) / elapsed if elapsed > 0 else 0.0
        parts = [f"env_steps={self.steps}/{self.total}", f"steps_per_second={rate:.0f}"]
        if self.recent_return is not None:
            parts.append(f"mean_return_last_{RECENT_EPISODES}={self.recent_return:.2f}")
        if self.learner_steps is not None:
            parts.append(f"learner_steps={self.learner_steps}")
        if self.steps < self.total:
            parts.append(f"eta={_duration((self.total - self.steps) / rate)}" if rate > 0 else "eta=?")
        return " ".join(parts)

    def close(self, outcome: str) -> None:
        """The closing line, in a terminal too: `outcome` is how the run ended."""
        if self.bar is not None:
            self.bar.close()
            self.bar = None
        log.info("%s %s: %s elapsed=%s", self.name, outcome, self.status(), _duration(time.monotonic() - self.start))

    @contextmanager
    def closing(self) -> Iterator["Progress"]:
        """Closes with `finished`, `stopped` (Ctrl-C, `kill`) or `failed (<error>)`; the error
        itself is reported by whoever catches it."""
        outcome = "failed"
        try:
            yield self
            outcome = "finished"
        except (KeyboardInterrupt, SystemExit):
            outcome = "stopped"
            raise
        except Exception as error:
            outcome = f"failed ({type(error).__name__})"
            raise
        finally:
            self.close(outcome)
