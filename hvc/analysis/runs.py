"""Run dirs (a sweep dir, an exported figure dir, or single runs) into one tidy DataFrame:
one row per metrics row, with the run, its status and its options as columns.

A run's options are the `key=value` options it ran with (overrides.yaml), plus the core
choices its resolved config holds whether or not they were given (controller, task, clips,
body, seed, fragment_len), so that runs of different sweeps line up. The options any run gave
are read, for every run, from its resolved config (`default` where null): an arm that kept the
default is an arm of the comparison, not a gap, and `1e-3` given equals `0.001` kept.
"""
from __future__ import annotations

import fcntl
import json
from pathlib import Path
from typing import Iterable

import pandas as pd
import yaml

METRICS_FILES = ("metrics.csv", "metrics.csv.gz")
# From the resolved config: the choices a figure is drawn over, given or not.
CORE = {"controller": ("controller", "name"), "task": ("task", "name"), "clips": ("clips", "name"),
        "body": ("body", "name"), "seed": ("seed",), "fragment_len": ("fragment_len",)}
# Options that say how a run was executed, not what was run: never a factor of a figure.
# (a key, or any key under it: `ray` covers `ray.address`)
EXECUTION = {"stage", "num_envs", "in_process_envs", "torch_threads", "resume", "total_steps", "budget",
             "log_every", "video", "video_steps", "record_episodes", "device", "actors", "ray", "mocap_file",
             "progress_seconds", "hl.checkpoint_seconds", "lowlevel.workers", "lowlevel.log_every",
             "lowlevel.checkpoint_seconds"}
STATUSES = ("finished", "running", "stopped", "failed")


def find_runs(paths: Iterable[str | Path]) -> list[Path]:
    """The run dirs at or under `paths`: dirs holding metrics or a failure record, outside
    the experts/ dirs of low-level runs."""
    found: set[Path] = set()
    for path in map(Path, paths):
        if not path.exists():
            raise FileNotFoundError(f"no run or sweep dir at {path}")
        for name in (*METRICS_FILES, "failed.json"):
            found |= {p.parent for p in ([path / name] if (path / name).is_file() else path.rglob(name))}
    return sorted(p for p in found if "experts" not in p.parts)


def run_status(run: Path) -> str:
    """finished (summary.json), failed (failed.json), running (another process holds the run
    dir's lock) or stopped (ended without finishing: killed, out of time; resumable)."""
    if (run / "summary.json").is_file():
        return "finished"
    if (run / "failed.json").is_file():
        return "failed"
    lock = run / ".lock"
    if lock.is_file():
        with open(lock) as f:
            try:
                fcntl.flock(f, fcntl.LOCK_SH | fcntl.LOCK_NB)
            except BlockingIOError:
                return "running"
    return "stopped"


def run_options(run: Path) -> dict:
    """The options a run ran with (see the module docstring); values parsed as YAML."""
    options = {}
    config = run / "config_resolved.yaml"
    if config.is_file():
        cfg = yaml.safe_load(config.read_text()) or {}
        for key, where in CORE.items():
            node = _lookup(cfg, where)
            if node is not _ABSENT and node is not None:
                options[key] = node
    overrides = run / "overrides.yaml"
    given = yaml.safe_load(overrides.read_text()) if overrides.is_file() else []
    for option in given or []:
        key, _, value = option.lstrip("+~").partition("=")
        if not key.startswith("hydra.") and key not in ("controller", "task", "clips", "body"):
            options[key] = yaml.safe_load(value) if value else None
    return options


def read_metrics(run: Path) -> pd.DataFrame:
    """The run's metrics rows, without the rows a resume superseded (see `last_timeline`)."""
    for name in METRICS_FILES:
        if (run / name).is_file():
            return last_timeline(pd.read_csv(run / name))
    return pd.DataFrame(columns=["env_steps", "learner_steps", "wall_time", "key", "value"])


def last_timeline(metrics: pd.DataFrame) -> pd.DataFrame:
    """A run resumed from a checkpoint logs again from the checkpoint's step: the rows it
    superseded (logged at or after a step some later row went back to) are dropped, so each
    episode counts once and env steps increase. Rows at one step belong together (a
    stage=evaluate run logs every clip at step 0; a final evaluation shares the last training
    row's step) until a key repeats or the wall time goes back: a resume logging that step again."""
    if metrics.empty:
        return metrics
    event = log_events(metrics)
    steps = metrics.groupby(event).env_steps.first().astype(float)
    later_min = steps[::-1].cummin()[::-1].shift(-1, fill_value=float("inf"))
    keep = steps.index[steps < later_min]
    return metrics[event.isin(keep)].reset_index(drop=True)


def log_events(metrics: pd.DataFrame) -> pd.Series:
    """Per row, the number of the logging event it belongs to: a new one when the env or
    learner step changes, the wall time goes back, or a key repeats at the same step."""
    steps_changed = metrics[["env_steps", "learner_steps"]].diff().abs().sum(axis=1) != 0
    by_step = (steps_changed | (metrics.wall_time.diff() < 0)).cumsum()
    repeat = metrics.groupby([by_step, metrics.key], dropna=False).cumcount()  # 1: a key's second time there
    within = repeat.groupby(by_step).cummax()
    return (by_step.diff().ne(0) | within.diff().ne(0)).cumsum()


def load_runs(paths: Iterable[str | Path], keys: Iterable[str] | None = None) -> pd.DataFrame:
    """One tidy frame of the runs at or under `paths`: columns `run`, `status`, one per option
    (NaN where a run lacks it), then env_steps, learner_steps, wall_time, key, value (`keys`:
    only those metrics). A run without metrics rows (failed before any) keeps one row with
    NaN metrics, so it shows in the frame. `frame.attrs["factors"]` lists the options whose
    values differ between the runs (the swept keys), execution options left out; and
    `frame.attrs["sections"]` those whose values are whole config sections or lists (such as
    `clips.entries`), each one JSON string."""
    frames, options = [], {}
    for run in find_runs(paths):
        metrics = read_metrics(run)
        if keys is not None:
            metrics = metrics[metrics.key.isin(list(keys))]
        if metrics.empty:
            metrics = pd.DataFrame({"key": [None]})
        options[str(run)] = run_options(run)
        metrics.insert(0, "status", run_status(run))
        metrics.insert(0, "run", str(run))
        frames.append(metrics)
    if not frames:
        raise FileNotFoundError(f"no runs under {', '.join(map(str, paths))}")
    sections = _fill_defaults(options)
    table = pd.DataFrame.from_dict(options, orient="index")
    frame = pd.concat(frames, ignore_index=True)
    frame = frame.join(table, on="run")
    columns = ["run", "status", *table.columns, "env_steps", "learner_steps", "wall_time", "key", "value"]
    frame = frame[[c for c in columns if c in frame.columns]]
    frame.attrs["factors"] = [c for c in table.columns
                              if not is_execution(c) and table[c].dropna().astype(str).nunique() > 1]
    frame.attrs["sections"] = sorted(sections)
    return frame


def is_execution(key: str) -> bool:
    return any(key == e or key.startswith(e + ".") for e in EXECUTION)


def _fill_defaults(options: dict[str, dict]) -> set[str]:
    """The options some runs gave, for every run, as its resolved config holds them (Hydra's
    parse, the same for a given and a default value): `default` where null, `absent` where
    neither the config nor the run has it (a `~key` deletion, a `+key` another run added); a
    section or list as one string. A run without a resolved config (failed before writing one)
    keeps what it gave. Returns the keys that held such a section or list in some run."""
    keys = {k for given in options.values() for k in given if not is_execution(k)} - set(CORE)
    sections = set()
    for run, given in options.items():
        config = Path(run) / "config_resolved.yaml"
        if not config.is_file():
            blobs = {k: v for k, v in given.items() if _is_section(v)}
            given.update({k: _factor_value(v) for k, v in blobs.items()})
            sections |= blobs.keys()
            continue
        cfg = yaml.safe_load(config.read_text()) or {}
        for key in keys:
            node = _lookup(cfg, key.split("."))
            if node is _ABSENT and given.get(key) is not None:  # given, but not a config key (a hand-made run)
                node = given[key]
            if _is_section(node):
                sections.add(key)
            given[key] = _factor_value(node)
    return sections


_ABSENT = object()


def _lookup(cfg: dict, parts) -> object:
    """The value at a key path of a loaded config, or _ABSENT."""
    node = cfg
    for part in parts:
        node = node.get(part, _ABSENT) if isinstance(node, dict) else _ABSENT
    return node


def _is_section(value) -> bool:
    """A value `_factor_value` turns into a JSON string: a list, or a section without a name."""
    return isinstance(value, list) or (isinstance(value, dict) and not isinstance(value.get("name"), str))


def _factor_value(value):
    """A config value as one hashable factor level."""
    if value is _ABSENT:
        return "absent"
    if value is None:
        return "default"
    if isinstance(value, dict):
        return value["name"] if isinstance(value.get("name"), str) else json.dumps(value, sort_keys=True)
    if isinstance(value, list):
        return json.dumps(value, sort_keys=True)
    return value
