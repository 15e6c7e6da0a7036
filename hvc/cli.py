"""`hvc-run`: compose the config with Hydra, validate it and the files it names, dispatch the
stage. A user's error is one line; in a sweep a failed job is recorded and the sweep goes on."""
from __future__ import annotations

import json
import logging
import os
import sys
from pathlib import Path

import hydra
from hydra import compose
from hydra.core.hydra_config import HydraConfig
from hydra.errors import ConfigCompositionException, HydraException, OverrideParseException
from hydra.types import RunMode
from hydra.utils import get_method
from omegaconf import DictConfig, OmegaConf
from omegaconf.errors import ConfigAttributeError, ConfigKeyError, ValidationError

from hvc.config import CONF_DIR, ConfigError, check_group_overrides, resolve_parallelism, unknown_key, validate
from hvc.errors import HvcUserError
from hvc.provenance import record_command
from hvc.runtime.inputs import check_inputs, check_run_dir
from hvc.runtime.lock import locked
from hvc.runtime.run_dirs import branch_run, merge_overrides, remove_stub, save_overrides, saved_overrides
from hvc.runtime.sweep_report import SweepReport, forget_failure, record_failure, remove_stub_sweep

log = logging.getLogger("hvc")


USER_ERRORS = (FileNotFoundError, HvcUserError, ConfigError)
# Options that take a path: a value Hydra's override grammar cannot read as written (a sweep
# job dir such as 0_lowlevel.hidden-[16], or 0_fragment_len=1,seed=0 from before plain names) is quoted.
PATH_OPTIONS = ("resume", "branch_from", "from_run", "library", "mocap_file", "lowlevel.reuse", "lowlevel.warm_start",
                "hydra.run.dir")


@hydra.main(config_path=str(CONF_DIR), config_name="config", version_base="1.3")
def _run(cfg: DictConfig) -> None:
    """One job. A new run dir that a failure left holding only records (Hydra's and ours) is
    removed; in a sweep a failed job writes why into its dir and returns, so that the
    launcher goes on with the next job and the sweep ends with a summary (SweepReport)."""
    _standard_start_method()
    hydra_cfg = HydraConfig.get()
    job_dir = Path(hydra_cfg.runtime.output_dir)
    log_file = f"{hydra_cfg.job.name}.log"
    in_sweep = hydra_cfg.mode == RunMode.MULTIRUN
    resumed_here = cfg.get("resume") not in (None, True) and Path(str(cfg.resume)).resolve() == job_dir.resolve()
    if in_sweep:
        forget_failure(job_dir)
    try:
        _job(cfg, job_dir)
    except USER_ERRORS as error:
        if not in_sweep:
            print(f"hvc-run: error: {error}", file=sys.stderr)
            sys.exit(2)
        log.error("hvc-run: error: %s", error)
        record_failure(job_dir, list(hydra_cfg.overrides.task), str(error), "error", job_dir / log_file)
    except Exception as error:
        if not in_sweep:
            raise
        log.exception("job %s crashed; the sweep goes on", job_dir)
        record_failure(job_dir, list(hydra_cfg.overrides.task), f"{type(error).__name__}: {error}", "crash",
                       job_dir / log_file)
    finally:
        if not (in_sweep or resumed_here):
            remove_stub(job_dir, log_file)


def _job(cfg: DictConfig, job_dir: Path) -> None:
    validate(cfg)
    run_dir = job_dir
    given = list(HydraConfig.get().overrides.task)  # this job's own: a multirun job's values
    options = given
    branch = None
    if cfg.get("resume"):  # go on with the run's own options, this command's winning
        run_dir = _run_to_resume(cfg, job_dir)
        saved = saved_overrides(run_dir)
        branched = [o for o in given if o.startswith("branch_from=") and o not in saved]
        if branched:  # resuming a branch with its own branch_from= is fine (queue.sh passes it)
            raise ConfigError(f"{branched[0]} starts a new run, resume= continues {run_dir}, which was not "
                              f"branched from there: give one of them")
        options = merge_overrides(saved, given)
        cfg = _composed(cfg, given, options)
    elif cfg.get("branch_from"):  # a new run going on from a copy of another's state, with its options
        branch = Path(str(cfg.branch_from))
        check_run_dir(f"branch_from={branch}", branch)
        options = merge_overrides(saved_overrides(branch), given)
        cfg = _composed(cfg, given, options)
    resolve_parallelism(cfg)
    if cfg.stage == "train":
        from hvc.runtime.device import resolve_device

        resolve_device(cfg)
    check_inputs(cfg, run_dir if cfg.get("resume") else None)
    with locked(run_dir):
        if run_dir != job_dir:  # resume=true: the log goes on in the run it found
            _log_into(run_dir, job_dir)
        if branch is not None:
            branch_run(branch, run_dir, f"{HydraConfig.get().job.name}.log")
        overrides = HydraConfig.get().overrides  # this job's own: a multirun job's values, not the sweep's lists
        resumed = [f"resume={run_dir}" if cfg.get("resume") and o.startswith("resume=") else o  # resume=true:
                   for o in overrides.task]                                                     # the run it found
        record_command(run_dir, [*resumed, *(o for o in overrides.hydra if not o.startswith("hydra.mode="))])
        save_overrides(run_dir, options)
        # Hydra keeps the unresolved config in .hydra/; this one has every interpolation filled in.
        (run_dir / "config_resolved.yaml").write_text(OmegaConf.to_yaml(cfg, resolve=True))
        log.info("stage=%s run dir %s", cfg.stage, run_dir)
        if cfg.stage in ("train", "rollout"):  # resolved before any env is built: a set without skills fails first
            _write_skills(cfg, run_dir)
        if cfg.get("resume"):  # going on (a larger total_steps): finished again when it finishes
            (run_dir / "summary.json").unlink(missing_ok=True)
        try:
            summary = _dispatch(cfg, run_dir)
        except KeyboardInterrupt:  # Ctrl-C or `kill`: the stage has saved its checkpoint
            print(f"hvc-run: stopped; continue with resume={run_dir}", file=sys.stderr)
            sys.exit(130)
        (run_dir / "summary.json").write_text(json.dumps(summary, indent=2))


def _write_skills(cfg: DictConfig, run_dir: Path) -> None:
    """skills.json: which library and fragments this job's controller drives (hvc.skills).
    Training stops here on a set without skills; a rollout drives the body without them."""
    from hvc.errors import ControllerUnavailable
    from hvc.skills import skills_for_job

    try:
        skills = skills_for_job(cfg)
    except ControllerUnavailable:
        if cfg.stage == "train":
            raise
        return
    if skills is not None:
        skills.write(run_dir)


def _standard_start_method() -> None:
    """A job run inside joblib's worker (hydra/launcher=joblib) inherits the start method
    'loky', which the env and expert worker processes it spawns cannot find: they die at start
    and the job waits for them. Its own processes start with the standard one."""
    import multiprocessing as mp

    if mp.get_start_method(allow_none=True) not in (None, "spawn", "fork", "forkserver"):
        mp.set_start_method("spawn", force=True)


def _run_to_resume(cfg: DictConfig, output_dir: Path) -> Path:
    """resume=<run dir>, or resume=true: the newest earlier run of this job not in use."""
    if cfg.resume is True:
        from hvc.runtime.run_dirs import latest_run_dir

        if HydraConfig.get().mode == RunMode.MULTIRUN:
            raise ConfigError(RESUME_TRUE_IN_SWEEP)
        run_dir = latest_run_dir(OmegaConf.to_container(cfg, resolve=True), output_dir)
        log.info("resume=true: continuing %s", run_dir)
    else:
        run_dir = Path(cfg.resume)
    if not run_dir.is_dir():
        raise ConfigError(f"resume={cfg.resume} is not a run directory")
    return run_dir


RESUME_TRUE_IN_SWEEP = ("resume=true picks one run; a sweep's jobs would all pick the same one: "
                        "resume each with resume=<run dir>")


def _log_into(run_dir: Path, job_dir: Path) -> None:
    """Moves the job's log file, opened by Hydra in `job_dir`, into `run_dir` (its lines so far
    appended), so that the new dir is left a stub to remove."""
    root = logging.getLogger()
    for handler in [h for h in root.handlers if isinstance(h, logging.FileHandler)]:
        old = Path(handler.baseFilename)
        if old.parent != job_dir.resolve():
            continue
        root.removeHandler(handler)
        handler.close()
        new = run_dir / old.name
        with open(new, "a") as f:
            f.write(old.read_text())
        moved = logging.FileHandler(new)
        moved.setFormatter(handler.formatter)
        moved.setLevel(handler.level)
        root.addHandler(moved)


def _composed(cfg: DictConfig, given: list[str], options: list[str]) -> DictConfig:
    """The config for `options` (a resume's: the run's own options restored), `cfg` itself
    when they are the command's own `given` ones (resume=<dir> restored them before Hydra)."""
    if options == given:
        return cfg
    log.info("resuming with the run's own options: %s", " ".join(o for o in options if o not in given))
    cfg = compose(config_name="config", overrides=options)
    validate(cfg)
    return cfg


# stage -> the function that runs it, imported on use (a stage's imports are heavy: torch, mujoco)
STAGE_RUNNERS = {
    "rollout": "hvc.runtime.rollout.run_rollout",
    "train": "hvc.runtime.hl_train.run_hl_training",
    "record": "hvc.runtime.record.run_record",
    "lowlevel": "hvc.runtime.lowlevel_stage.run_lowlevel",
    "evaluate": "hvc.runtime.evaluate_stage.run_evaluate",
    "info": "hvc.runtime.mocap_stages.run_info",
    "convert": "hvc.runtime.mocap_stages.run_convert",
    "playback": "hvc.runtime.mocap_stages.run_playback",
    "openloop": "hvc.runtime.mocap_stages.run_openloop",
}


def _dispatch(cfg: DictConfig, run_dir: Path) -> dict:
    return get_method(STAGE_RUNNERS[cfg.stage])(cfg, run_dir)  # validate() admits only known stages


def _with_resumed_options(argv: list[str]) -> list[str]:
    """`resume=<run dir>`: the run's saved options after this command's (which win), before
    Hydra composes, so that an option of the run's own groups (task.turn_rate_repeat of
    task=tracking) can be changed on resume, and Hydra's run dir set to the run's.
    resume=true is merged in _job, once found."""
    dirs = [_unquoted(a.partition("=")[2]) for a in argv if a.startswith("resume=")]
    if len(dirs) != 1 or dirs[0].lower() == "true" or not Path(dirs[0]).is_dir():
        return argv
    if {"-m", "--multirun"} & set(argv):
        raise ConfigError(f"resume={dirs[0]} continues one run; a sweep's jobs would all write to it: "
                          f"resume each job's run on its own")
    given = [a for a in argv if not a.startswith("-")]
    restored = merge_overrides(saved_overrides(Path(dirs[0])), given)[:-len(given) or None]
    if not any(a.startswith("hydra.run.dir=") for a in argv):  # Hydra's log goes to the run too, not to
        restored.append(f"hydra.run.dir={dirs[0]}")            # a new dir of its own; its .hydra/ keeps
        restored.append("hydra.output_subdir=null")            # the first start's record
    return argv + restored


def _unquoted(value: str) -> str:
    return value[1:-1] if len(value) > 1 and value[0] == value[-1] and value[0] in "'\"" else value


def _quoted_paths(argv: list[str]) -> list[str]:
    """PATH_OPTIONS naming an existing path that Hydra's grammar cannot read unquoted, quoted."""
    from hydra.core.override_parser.overrides_parser import OverridesParser

    parser, out = OverridesParser.create(), []
    for arg in argv:
        key, sep, value = arg.partition("=")
        if sep and key in PATH_OPTIONS and Path(value).exists():
            try:
                parser.parse_override(arg)
            except OverrideParseException:
                escaped = value.replace("'", "\\'")
                arg = f"{key}='{escaped}'"
        out.append(arg)
    return out


def _check_sweep(argv: list[str]) -> None:
    """Errors of a whole sweep, told before its first job."""
    from hvc.skills import check_sweep_library

    if not {"-m", "--multirun"} & set(argv):
        return
    if any(a.lower() == "resume=true" for a in argv):
        raise ConfigError(RESUME_TRUE_IN_SWEEP)
    check_sweep_library(argv)


def _hydra_error(error: HydraException, argv: list[str]) -> str:
    """Hydra's multi-line message in one line; a key the config lacks gets a suggestion."""
    cause = error.__cause__
    if isinstance(error, ConfigCompositionException) and isinstance(cause, (ConfigAttributeError, ConfigKeyError)) \
            and cause.full_key:
        given = next((a for a in argv if a.lstrip("+~").partition("=")[0] == cause.full_key), cause.full_key)
        return f"{given}: {unknown_key(cause.full_key, [a for a in argv if not a.startswith('-')])}"
    if isinstance(error, ConfigCompositionException) and isinstance(cause, ValidationError):
        # a value of the wrong type for a typed key (hvc.schema): OmegaConf's first line says which
        return f"{str(error).strip()}: {str(cause).splitlines()[0]}"
    return " ".join(line.strip() for line in str(error).splitlines() if line.strip())


def main() -> None:
    # Hydra raises its own errors (a typo in a key, a bad override) to us instead of printing
    # them over several lines: they are told below in one.
    os.environ.setdefault("HYDRA_FULL_ERROR", "1")
    argv = sys.argv[1:]
    try:
        argv = _quoted_paths(_with_resumed_options(argv))
        check_group_overrides(a for a in argv if not a.startswith("-"))
        _check_sweep(argv)
        sys.argv = [sys.argv[0], *argv]
        _run()
    except ConfigError as error:
        print(f"hvc-run: error: {error}", file=sys.stderr)
        sys.exit(2)
    except HydraException as error:
        remove_stub_sweep()
        print(f"hvc-run: error: {_hydra_error(error, argv)}", file=sys.stderr)
        sys.exit(2)
    if SweepReport.failed:
        sys.exit(1)


if __name__ == "__main__":
    main()
