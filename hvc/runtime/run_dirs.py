"""Finding the run to continue (`resume=true`: the newest earlier run of the same job) and
the options it ran with, so that `resume=<run dir>` alone continues it as it was.

Runs live in `outputs/runs/<date>/<time>_<task>_<controller>` (conf/config.yaml); a run is
"the same job" when its resolved config has the same stage, task, controller, clip set,
body, algorithm and seed, and it can be continued when it left a checkpoint (`checkpoint.pt`,
or `experts/` for the low level) and no process writes to it now.
"""
from __future__ import annotations

import logging
import shutil
from pathlib import Path

import yaml

from hvc.config import GROUPS, ConfigError
from hvc.errors import RunDirInUse
from hvc.provenance import COMMANDS_FILE
from hvc.runtime.lock import LOCK_FILE, holder
from hvc.runtime.sweep_report import FAILED_FILE

log = logging.getLogger(__name__)

RUNS_ROOT = Path("outputs") / "runs"


JOB_KEYS = ("stage", "task", "controller", "clips", "body", "algorithm")


def _job(config: dict) -> tuple:
    named = tuple((config.get(k) or {}).get("name") if isinstance(config.get(k), dict) else config.get(k)
                  for k in JOB_KEYS)
    return (*named, config.get("seed"))


def latest_run_dir(config: dict, current: Path, root: Path = RUNS_ROOT) -> Path:
    """The newest run dir under `root` (other than `current`, which Hydra has just made) of
    the same job as `config` (a resolved config as a dict) that can be continued."""
    want = _job(config)
    candidates = sorted(root.glob("*/*"), key=lambda p: (p.parent.name, p.name), reverse=True)
    for run in candidates:
        if run.resolve() == current.resolve() or not (run / "config_resolved.yaml").is_file():
            continue
        if not ((run / "checkpoint.pt").is_file() or (run / "experts").is_dir()):
            continue
        if _job(yaml.safe_load((run / "config_resolved.yaml").read_text()) or {}) == want:
            writer = holder(run)
            if writer is None:
                return run
            log.info("resume=true: skipping %s, in use by %s", run, writer)
    job = " ".join(f"{k}={v}" for k, v in zip((*JOB_KEYS, "seed"), want))
    raise ConfigError(f"resume=true found no earlier run with a checkpoint of {job} under {root}/; "
                      f"pass resume=<run dir>")


OVERRIDES_FILE = "overrides.yaml"


def _key(override: str) -> str:
    return override.partition("=")[0].lstrip("+~")


def saved_overrides(run_dir: Path) -> list[str]:
    """The options a run goes on with: our own record (its first start's, updated by each
    resume), else Hydra's `.hydra/overrides.yaml` (runs made before the record existed)."""
    for path in (run_dir / OVERRIDES_FILE, run_dir / ".hydra" / "overrides.yaml"):
        if path.is_file():
            return [str(o) for o in (yaml.safe_load(path.read_text()) or [])]
    return []


def merge_overrides(saved: list[str], new: list[str]) -> list[str]:
    """A resume's options: the run's saved ones (but its `resume=`), then the new command's,
    which win where both set the same key (e.g. a larger total_steps). A new group choice
    drops the saved options inside that group (task=gaps: no task.turn_rate_repeat of
    task=tracking), and a key the run added with `+` keeps being added (`++`)."""
    given = {_key(o) for o in new}
    regrouped = tuple(f"{g}." for g in given & set(GROUPS))
    kept = [o for o in saved if _key(o) not in given and _key(o) != "resume" and not _key(o).startswith(regrouped)]
    added = {_key(o) for o in saved if o.startswith("+")}
    return kept + [f"++{o}" if _key(o) in added and not o.startswith(("+", "~")) else o for o in new]


def save_overrides(run_dir: Path, overrides: list[str]) -> None:
    (run_dir / OVERRIDES_FILE).write_text(yaml.safe_dump([o for o in overrides if _key(o) != "resume"]))


BRANCHING = ".branching"  # where branch_run copies before moving in
# What hvc-run writes into a run dir before the stage's own work (besides Hydra's .hydra/ and
# the job's log): a dir holding no more is a stub of a command that failed before any work.
BOOKKEEPING = {".hydra", LOCK_FILE, OVERRIDES_FILE, "config_resolved.yaml", COMMANDS_FILE, BRANCHING}
# The source's records of its own ending and the episodes it recorded stay with it (and .tmp, .mp4 files).
NOT_BRANCHED = {"summary.json", FAILED_FILE, "episodes"}


def remove_stub(run_dir: Path, log_file: str) -> bool:
    """Removes `run_dir` when it holds nothing but bookkeeping and `log_file` (and its date dir
    under RUNS_ROOT, when that is left empty); True if it did."""
    if not run_dir.is_dir() or any(p.name not in BOOKKEEPING | {log_file} for p in run_dir.iterdir()):
        return False
    shutil.rmtree(run_dir)
    if run_dir.parent.parent.resolve() == RUNS_ROOT.resolve() and not any(run_dir.parent.iterdir()):
        run_dir.parent.rmdir()
    return True


def branch_run(source: Path, target: Path, log_file: str) -> None:
    """`branch_from=<source>`: copies the source run's state (checkpoints, with an expert's
    critic and replay, metrics, its command history) into the new run dir `target`, which then
    goes on from there as a resume would; the source is left as it is, so one run can be
    continued several ways (cut-ins or not) and each branch's curves start at step 0. The copy
    is made aside and moved in whole, so a failed one leaves nothing but bookkeeping."""
    if not ((source / "checkpoint.pt").is_file() or (source / "experts").is_dir()):
        raise ConfigError(f"branch_from={source} has no checkpoint to go on from (checkpoint.pt or experts/): "
                          f"only stage=train and stage=lowlevel runs branch")
    writer = holder(source)
    if writer is not None:
        raise RunDirInUse(f"branch_from={source} is in use by another hvc-run ({writer}); branch from it once it "
                          f"has stopped, or it would go on from whatever step it had reached")
    aside = target / BRANCHING
    shutil.rmtree(aside, ignore_errors=True)  # an earlier attempt's, killed while copying
    held = sorted(p.name for p in target.iterdir() if p.name not in BOOKKEEPING | {log_file})
    if held:
        raise ConfigError(f"branch_from={source}: {target} already holds a run ({', '.join(held)}); "
                          f"continue it with resume={target}")
    aside.mkdir()
    try:
        for item in sorted(source.iterdir()):
            if item.name in NOT_BRANCHED or item.name == log_file or item.suffix in (".tmp", ".mp4") \
                    or (item.name in BOOKKEEPING and item.name != COMMANDS_FILE):
                continue
            if item.is_dir():
                shutil.copytree(item, aside / item.name, ignore=shutil.ignore_patterns("*.tmp"))
            else:
                shutil.copy2(item, aside / item.name)
        for item in aside.iterdir():
            item.rename(target / item.name)
    finally:
        shutil.rmtree(aside, ignore_errors=True)

