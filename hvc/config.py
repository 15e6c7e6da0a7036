"""Config composition and validation: bad values fail before any work, in one line.

Hydra composes `conf/`; this module checks what YAML types cannot express (positive
integers, which controller runs on which body, which stage exists) and names the bad
value with the allowed ones.
"""
from __future__ import annotations

import os
import warnings

from pathlib import Path
from typing import Iterable, Sequence

from omegaconf import DictConfig, OmegaConf, open_dict

from hvc.schema import SCHEMAS, register as register_schemas

register_schemas()  # before any composition: the group files name their schemas (hvc.schema)
CONF_DIR = Path(__file__).resolve().parent.parent / "conf"
GROUPS = ("body", "task", "controller", "algorithm", "clips", "reward", "render", "lowlevel", "budget")
STAGES = ("rollout", "train", "record", "info", "convert", "playback", "openloop", "lowlevel", "evaluate")
MOCAP_STAGES = ("info", "convert", "playback", "openloop", "lowlevel", "evaluate")
# Top-level keys that must be positive integers.
POSITIVE_INTS = ("fragment_len", "total_steps", "log_every", "video_steps", "episodes")
# Task kinds with an environment on the fast path.
RUNNABLE_TASK_KINDS = ("go_to_target", "corridor", "maze", "tracking")
IMAGE_PRECISIONS = ("float32", "bfloat16")  # the image encoder's compute (hvc.agents.network.ImageEncoder)


class ConfigError(ValueError):
    """A bad config value; the message is one line naming the value and the allowed ones."""


def group_options(group: str) -> list[str]:
    return sorted(p.stem for p in (CONF_DIR / group).glob("*.yaml"))


def group_config(group: str, option: str) -> DictConfig:
    """One option file of a group, without its defaults list (for stages that need a
    second task config, e.g. playback tracks a clip whatever `task` says), typed by the schema
    its defaults list names (hvc.schema), as composition would type it."""
    cfg = OmegaConf.load(CONF_DIR / group / f"{option}.yaml")
    defaults = cfg.pop("defaults", None) or []
    for name in (d for d in defaults if isinstance(d, str) and d in SCHEMAS.get(group, {})):
        cfg = OmegaConf.merge(OmegaConf.structured(SCHEMAS[group][name]), cfg)
    return cfg


def check_group_overrides(overrides: Iterable[str]) -> None:
    """Fails on `group=unknown` before Hydra prints its multi-line error."""
    for item in overrides:
        key, sep, value = item.partition("=")
        key = key.lstrip("+~")
        if not sep or key not in GROUPS:
            continue
        for choice in value.split(","):  # multirun: body=a,b
            if choice and choice not in group_options(key):
                raise ConfigError(f"unknown {key} {choice!r}; allowed: {', '.join(group_options(key))}")


def unknown_key(key: str, overrides: Sequence[str]) -> str:
    """One line for an override of a key the config lacks, with the closest keys as a
    suggestion, from the config of the command's own group choices (keys differ by group)."""
    import difflib

    from hydra import compose as hydra_compose, initialize_config_dir

    choices = [f"{k}={v.split(',')[0]}" for k, _, v in (o.partition("=") for o in overrides) if k in GROUPS]
    try:
        with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
            cfg = hydra_compose(config_name="config", overrides=choices)
    except Exception:  # noqa: BLE001 - a suggestion is a courtesy: fall back to the defaults' keys
        with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
            cfg = hydra_compose(config_name="config")
    matches = difflib.get_close_matches(key, _dotted_keys(OmegaConf.to_container(cfg, resolve=False)), n=2)
    hint = f"did you mean {' or '.join(matches)}?" if matches else "`hvc-run --cfg job` lists the keys"
    return f"no key {key} in the config; {hint}"


def _dotted_keys(node: dict, prefix: str = "") -> list[str]:
    keys = []
    for k, v in node.items():
        keys.append(f"{prefix}{k}")
        if isinstance(v, dict):
            keys += _dotted_keys(v, f"{prefix}{k}.")
    return keys


def _integral(cfg: DictConfig, key: str) -> None:
    """A count given as an integral float (total_steps=1e6) becomes the int it is, in the config too."""
    value = cfg.get(key)
    if isinstance(value, float) and value.is_integer():
        cfg[key] = int(value)


def _positive_int(cfg: DictConfig, key: str) -> None:
    value = cfg.get(key)
    if isinstance(value, bool) or not isinstance(value, int) or value < 1:
        raise ConfigError(f"{key}={value!r} must be a positive integer (e.g. {key}=3)")


CHEAP_BODY_ENVS = 8  # num_envs=auto for a body without motion-capture skills (the rolling ball)


def _cores() -> int:
    return max(1, len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1)


CPUS_ENV = "HVC_CPUS"  # a user's own cap on the cores of each job (e.g. on a shared machine)
# conf/hydra/launcher/ presets carry the names of the plugins' own configs, so that one flag selects
# them (hydra/launcher=joblib); Hydra 1.3 merges such a file onto the plugin's schema and warns that it
# will stop doing so (it still does in 1.3; pyproject pins hydra-core<1.4): not a user's concern.
warnings.filterwarnings("ignore", message=r"\s*'hydra/launcher/(joblib|submitit_local|submitit_slurm|ray)' is "
                                          r"validated against ConfigStore schema", category=UserWarning)


def job_cores() -> int:
    """The cores this job may use (resolve_parallelism's docstring says how they are found)."""
    from hydra.core.hydra_config import HydraConfig
    from hydra.types import RunMode

    cores = _cores()
    in_sweep = HydraConfig.initialized() and HydraConfig.get().mode == RunMode.MULTIRUN
    launcher = HydraConfig.get().get("launcher") if in_sweep else None
    if launcher is not None:
        jobs = launcher.get("n_jobs")  # joblib: this many jobs side by side on this machine
        if isinstance(jobs, int) and not isinstance(jobs, bool):
            cores = max(1, cores // (jobs if jobs > 0 else max(1, cores + 1 + jobs)))  # -1: one per core
        cpus = launcher.get("cpus_per_task")  # submitit: the CPUs the job asked for
        if cpus is None:
            cpus = OmegaConf.select(launcher, "ray.remote.num_cpus", default=None)  # ray: the task's CPUs
        if isinstance(cpus, (int, float)) and not isinstance(cpus, bool) and cpus >= 1:
            cores = min(cores, int(cpus))
    limit = os.environ.get(CPUS_ENV, "").strip()
    if limit:
        if not limit.isdigit() or int(limit) < 1:
            raise ConfigError(f"{CPUS_ENV}={limit!r} must be a positive integer (the cores a job may use)")
        cores = min(cores, int(limit))
    return cores


def resolve_parallelism(cfg: DictConfig) -> None:
    """`num_envs`, `in_process_envs` and `torch_threads` set to auto become numbers, so run
    dirs record them.

    For the humanoid, and for any body on a vision task: one env per core, one of them in the
    main process (steps with the low-level experts or a camera are long enough for a worker
    to pay off). For a body without motion-capture skills (the rolling ball) on a task
    without vision: CHEAP_BODY_ENVS envs, all in the main process.
    Its step costs less than a worker's round trip, and acting is batched, so more envs cost
    little more per step and decorrelate the data (docs/results/design_measurements).

    "Cores" are this job's share of the machine, so that jobs a launcher runs side by side
    (conf/hydra/launcher/) do not oversubscribe it with envs, worker processes and torch
    threads. They start from the cores the process may run on (its affinity mask, which
    SLURM's cgroups and `taskset` narrow); in a sweep's job the launcher's own config
    (hydra.launcher) then says its share: joblib's n_jobs=k runs k jobs at once here, so each
    takes cores // k (at least 1; k <= 0 counts as joblib does, -1 = one job per core);
    submitit's cpus_per_task and the Ray launcher's ray.remote.num_cpus cap it at the CPUs the
    job asked for; and the environment variable HVC_CPUS, when set, caps it too. Explicit
    num_envs= and torch_threads= are kept as given."""
    cheap = not cfg.body.humanoid and not cfg.task.vision
    if cfg.num_envs == "auto":
        cfg.num_envs = CHEAP_BODY_ENVS if cheap else job_cores()
    if cfg.in_process_envs == "auto":
        cfg.in_process_envs = cfg.num_envs if cheap else 1
    if cfg.in_process_envs > cfg.num_envs:
        raise ConfigError(f"in_process_envs={cfg.in_process_envs} exceeds num_envs={cfg.num_envs}; "
                          f"allowed: 0 to num_envs")
    if cfg.torch_threads == "auto":
        # The learner's updates run while the worker envs wait for their next step, so on a
        # vision task the ResNet's convs can take every core (docs/results/design_measurements).
        # Without vision the ops are small (LSTMs and MLPs at batch 32).
        cfg.torch_threads = job_cores() if cfg.task.vision else 1


def expand_clip_set(clips: DictConfig) -> None:
    """A clip set's `include` (sets whose entries come first, recursively) expanded where the
    config is composed, so that the code reading clip sets (hvc.mocap.clip_sets) reads one list
    and no config file: `entries` becomes the whole set, `included` names every set it includes
    (transitively, in order), and `include` is emptied. A second call changes nothing."""
    included, entries = [], []
    for name in clips.get("include") or []:
        other = group_config("clips", name)
        expand_clip_set(other)
        included += [name, *other.get("included", [])]
        entries += list(other.entries or [])
    if included or "included" not in clips:
        with open_dict(clips):
            clips.included = included
            clips.entries = entries + list(clips.get("entries") or [])
            clips.include = []


def validate(cfg: DictConfig) -> None:
    """Raises ConfigError on the first bad value or combination. Normalises on the way: counts
    given as integral floats become ints, the clip set's includes are expanded."""
    expand_clip_set(cfg.clips)
    for key in (*POSITIVE_INTS, "num_envs", "in_process_envs", "torch_threads"):
        _integral(cfg, key)
    for key in POSITIVE_INTS:
        _positive_int(cfg, key)
    if cfg.num_envs != "auto" and (isinstance(cfg.num_envs, bool) or not isinstance(cfg.num_envs, int)
                                   or cfg.num_envs < 1):
        raise ConfigError(f"num_envs={cfg.num_envs!r} must be a positive integer or auto (as many as cores)")
    if cfg.torch_threads != "auto" and (isinstance(cfg.torch_threads, bool)
                                        or not isinstance(cfg.torch_threads, int) or cfg.torch_threads < 1):
        raise ConfigError(f"torch_threads={cfg.torch_threads!r} must be a positive integer or auto")
    if cfg.in_process_envs != "auto" and (isinstance(cfg.in_process_envs, bool)
                                          or not isinstance(cfg.in_process_envs, int) or cfg.in_process_envs < 0):
        raise ConfigError(f"in_process_envs={cfg.in_process_envs!r} must be an integer from 0 to num_envs, "
                          f"or auto")
    if cfg.image_precision not in IMAGE_PRECISIONS:
        raise ConfigError(f"image_precision={cfg.image_precision!r}; allowed: {', '.join(IMAGE_PRECISIONS)}")
    if cfg.stage not in STAGES:
        raise ConfigError(f"unknown stage {cfg.stage!r}; allowed: {', '.join(STAGES)}")
    if cfg.get("actors", "local") not in ("local", "ray"):
        raise ConfigError(f"actors={cfg.actors} is not a backend; allowed: local, ray")
    if cfg.ray.acting not in ("actors", "central"):
        raise ConfigError(f"ray.acting={cfg.ray.acting} is not a way to act; allowed: actors, central")
    if isinstance(cfg.ray.broadcast_every, bool) or not isinstance(cfg.ray.broadcast_every, int) \
            or cfg.ray.broadcast_every < 1:
        raise ConfigError(f"ray.broadcast_every={cfg.ray.broadcast_every!r} must be a positive integer (unrolls)")
    if not isinstance(cfg.seed, int) or isinstance(cfg.seed, bool):
        raise ConfigError(f"seed={cfg.seed!r} must be an integer")
    if not isinstance(cfg.video, bool):
        raise ConfigError(f"video={cfg.video!r} must be true or false")
    controller, body = cfg.controller, cfg.body
    if controller.needs_humanoid and not body.humanoid:
        allowed = [c for c in group_options("controller")
                   if not OmegaConf.load(CONF_DIR / "controller" / f"{c}.yaml").get("needs_humanoid", True)]
        raise ConfigError(f"controller={controller.name} needs motion-capture skills of the CMU humanoid, "
                          f"not body={body.name}; allowed with {body.name}: {', '.join(allowed)}")
    if cfg.algorithm.name not in controller.algorithms:
        raise ConfigError(f"algorithm={cfg.algorithm.name} does not train controller={controller.name}; "
                          f"allowed: {', '.join(controller.algorithms)}")
    if body.camera not in ("bodycam", "egocentric"):
        raise ConfigError(f"body.camera={body.camera!r}; allowed: bodycam, egocentric")
    if body.kind == "rolling_ball" and body.camera != "egocentric":
        raise ConfigError(f"body.camera={body.camera!r} does not exist on rolling_ball; allowed: egocentric")
    if cfg.task.kind not in RUNNABLE_TASK_KINDS:
        raise ConfigError(f"task={cfg.task.name} has no environment; allowed: "
                          f"{', '.join(t for t in group_options('task') if t != cfg.task.name)}")
    if (cfg.task.kind == "tracking" or cfg.stage in MOCAP_STAGES) and not body.humanoid:
        humanoids = [b for b in group_options("body") if OmegaConf.load(CONF_DIR / "body" / f"{b}.yaml").get(
            "humanoid", True)]
        raise ConfigError(f"motion-capture tracking needs a CMU humanoid body, not body={body.name}; "
                          f"allowed: {', '.join(humanoids)}")
    for key, example in (("termination_error", "a positive pose error (e.g. 0.15)"),
                         ("heading_termination", "a positive heading error in rad (e.g. 0.5)")):
        threshold = cfg.task.get(key)
        if threshold is not None and (isinstance(threshold, bool) or not isinstance(threshold, (int, float))
                                      or threshold <= 0):
            raise ConfigError(f"task.{key}={threshold!r} must be {example} or null (off)")
    if cfg.task.kind == "tracking" and cfg.stage == "train":
        raise ConfigError("task=tracking is the low-level tracking task: train experts with stage=lowlevel "
                          "(or drive it with stage=rollout); stage=train takes a high-level task: "
                          f"{', '.join(t for t in group_options('task') if t != 'tracking')}")
    for key in ("switch_starts", "cut_ins", "pushes"):
        share = cfg.lowlevel.get(key, 0.0)
        if isinstance(share, bool) or not isinstance(share, (int, float)) or not 0 <= share <= 1:
            raise ConfigError(f"lowlevel.{key}={share!r} must be a probability from 0 to 1 (e.g. 0.5)")
    kickstart = cfg.lowlevel.get("kickstart_cost", 0.0)
    if isinstance(kickstart, bool) or not isinstance(kickstart, (int, float)) or kickstart < 0:
        raise ConfigError(f"lowlevel.kickstart_cost={kickstart!r} must be a weight of 0 (off) or more (e.g. 0.1)")
    if kickstart > 0 and int(cfg.lowlevel.bc_rollouts) < 1:
        raise ConfigError(f"lowlevel.bc_rollouts={cfg.lowlevel.bc_rollouts} gives kickstarting no teacher walks: "
                          f"at least 1 (e.g. 600)")
    force, steps = cfg.lowlevel.get("push_force", 500.0), cfg.lowlevel.get("push_steps", 3)
    if isinstance(force, bool) or not isinstance(force, (int, float)) or force <= 0:
        raise ConfigError(f"lowlevel.push_force={force!r} must be a positive force in newtons (e.g. 500.0)")
    if isinstance(steps, bool) or not isinstance(steps, int) or steps < 1:
        raise ConfigError(f"lowlevel.push_steps={steps!r} must be a whole number of control steps, at least 1 (e.g. 3)")
    if float(cfg.algorithm.get("updates_per_unroll", 1)) <= 0:
        raise ConfigError(f"algorithm.updates_per_unroll={cfg.algorithm.updates_per_unroll} must be positive "
                          f"(e.g. 0.25: one learner update per 4 unrolls)")
    if float(cfg.task.control_timestep) <= 0 or float(cfg.task.physics_timestep) <= 0:
        raise ConfigError("task.control_timestep and task.physics_timestep must be positive")
    ratio = float(cfg.task.control_timestep) / float(cfg.task.physics_timestep)
    if abs(ratio - round(ratio)) > 1e-6:
        raise ConfigError(f"task.control_timestep={cfg.task.control_timestep} is not a multiple of "
                          f"task.physics_timestep={cfg.task.physics_timestep}")


def compose(overrides: Sequence[str] = ()) -> DictConfig:
    """The composed, validated config, as `hvc-run` would see it (for tests and notebooks)."""
    from hydra import compose as hydra_compose, initialize_config_dir

    check_group_overrides(overrides)
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        cfg = hydra_compose(config_name="config", overrides=list(overrides))
    validate(cfg)
    resolve_parallelism(cfg)
    return cfg
