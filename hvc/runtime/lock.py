"""One writer per run dir: an exclusive `flock` on `<run dir>/.lock`, holding the writer's pid.

The OS drops a flock when its process ends, however it ends, so a killed run never leaves a
stale lock. Processes forked by the writer (env and expert workers) share the lock, so the
dir stays in use while a worker whose launcher died still saves its checkpoint.
"""
from __future__ import annotations

import fcntl
import os
from contextlib import contextmanager
from pathlib import Path
from typing import Iterator

from hvc.errors import RunDirInUse

LOCK_FILE = ".lock"


def holder(run_dir: Path) -> str | None:
    """Who writes to `run_dir` ("pid 1234"), None when no process does."""
    path = Path(run_dir) / LOCK_FILE
    if not path.is_file():
        return None
    with open(path) as f:
        try:
            fcntl.flock(f, fcntl.LOCK_SH | fcntl.LOCK_NB)
        except BlockingIOError:
            return _who(f.read())
    return None


@contextmanager
def locked(run_dir: Path) -> Iterator[None]:
    """Holds the run dir's lock for the block; raises RunDirInUse, naming the holder's pid,
    when another process holds it."""
    run_dir = Path(run_dir)
    f = open(run_dir / LOCK_FILE, "a+")
    try:
        try:
            fcntl.flock(f, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            f.seek(0)
            raise RunDirInUse(f"{run_dir} is in use by another hvc-run ({_who(f.read())}); one process writes "
                              f"to a run dir at a time: wait for it to end or stop it") from None
        f.truncate(0)
        f.write(f"{os.getpid()}\n")
        f.flush()
        yield
    finally:
        f.close()  # releases the lock


def _who(text: str) -> str:
    return f"pid {text.strip()}" if text.strip().isdigit() else "a process that has not written its pid yet"
