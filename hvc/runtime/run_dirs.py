"""Finding the run to continue for `resume=true`: the newest earlier run of the same job.

Runs live in `outputs/runs/<date>/<time>_<task>_<controller>` (conf/config.yaml); a run is
"the same job" when its resolved config has the same stage, task, controller, clip set,
body, algorithm and seed, and it can be continued when it left a checkpoint (`checkpoint.pt`,
or `experts/` for the low level).
"""
from __future__ import annotations

from pathlib import Path

import yaml

from hvc.config import ConfigError

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
            return run
    job = " ".join(f"{k}={v}" for k, v in zip((*JOB_KEYS, "seed"), want))
    raise ConfigError(f"resume=true found no earlier run with a checkpoint of {job} under {root}/; "
                      f"pass resume=<run dir>")
