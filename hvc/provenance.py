"""Where a run's results came from: the code version and every command that touched its
run dir (a resumed run's later overrides, e.g. a changed learning rate, are part of its
history and Hydra's own record in .hydra/ keeps only the first)."""
from __future__ import annotations

import shlex
import subprocess
import time
from pathlib import Path

import hvc

COMMANDS_FILE = "commands.log"


def code_version() -> str:
    try:
        commit = subprocess.run(["git", "describe", "--always", "--dirty"], capture_output=True, text=True,
                                cwd=Path(__file__).parent, timeout=5).stdout.strip()
    except (OSError, subprocess.SubprocessError):
        commit = ""
    return f"hvc {hvc.__version__}" + (f" ({commit})" if commit else "")


def record_command(run_dir: Path, overrides: list[str]) -> None:
    """Append this job (UTC time, code version, its own overrides: in a multirun, this job's
    values rather than the sweep's) to the run dir's log, quoted so that it replays."""
    line = " ".join([time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()), f"[{code_version()}]",
                     "hvc-run", shlex.join(overrides)])
    with open(run_dir / COMMANDS_FILE, "a") as log:
        log.write(line.rstrip() + "\n")


def run_commands(run_dir: Path) -> list[str]:
    path = run_dir / COMMANDS_FILE
    return path.read_text().splitlines() if path.exists() else []
