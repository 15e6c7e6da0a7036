"""`hvc-run`: compose the config with Hydra, validate it, dispatch the stage. Nothing else."""
from __future__ import annotations

import json
import logging
import sys
from pathlib import Path

import hydra
from hydra import compose
from hydra.core.hydra_config import HydraConfig
from omegaconf import DictConfig, OmegaConf

from hvc.config import CONF_DIR, ConfigError, check_group_overrides, resolve_parallelism, validate
from hvc.errors import HvcUserError
from hvc.provenance import record_command
from hvc.runtime.run_dirs import merge_overrides, save_overrides, saved_overrides

log = logging.getLogger("hvc")


USER_ERRORS = (FileNotFoundError, HvcUserError, ConfigError)


@hydra.main(config_path=str(CONF_DIR), config_name="config", version_base="1.3")
def _run(cfg: DictConfig) -> None:
    try:
        validate(cfg)
        run_dir = Path(HydraConfig.get().runtime.output_dir)
        given = list(HydraConfig.get().overrides.task)  # this job's own: a multirun job's values
        options = given
        if cfg.get("resume"):  # go on with the run's own options, this command's winning
            run_dir = _run_to_resume(cfg, run_dir)
            options = merge_overrides(saved_overrides(run_dir), given)
            cfg = _composed(cfg, given, options)
        resolve_parallelism(cfg)
    except ConfigError as error:
        print(f"hvc-run: error: {error}", file=sys.stderr)
        sys.exit(2)
    overrides = HydraConfig.get().overrides  # this job's own: a multirun job's values, not the sweep's lists
    resumed = [f"resume={run_dir}" if cfg.get("resume") and o.startswith("resume=") else o  # resume=true: the
               for o in overrides.task]                                                     # run it found
    record_command(run_dir, [*resumed, *(o for o in overrides.hydra if not o.startswith("hydra.mode="))])
    save_overrides(run_dir, options)
    # Hydra keeps the unresolved config in .hydra/; this one has every interpolation filled in.
    (run_dir / "config_resolved.yaml").write_text(OmegaConf.to_yaml(cfg, resolve=True))
    log.info("stage=%s run dir %s", cfg.stage, run_dir)
    try:
        summary = _dispatch(cfg, run_dir)
    except USER_ERRORS as error:  # a missing file or clip, an unavailable controller: one line, no traceback
        print(f"hvc-run: error: {error}", file=sys.stderr)
        sys.exit(2)
    except KeyboardInterrupt:  # Ctrl-C or `kill`: the stage has saved its checkpoint
        print(f"hvc-run: stopped; continue with resume={run_dir}", file=sys.stderr)
        sys.exit(130)
    (run_dir / "summary.json").write_text(json.dumps(summary, indent=2))


def _run_to_resume(cfg: DictConfig, output_dir: Path) -> Path:
    """resume=<run dir>, or resume=true: the newest earlier run of this job."""
    if cfg.resume is True:
        from hydra.types import RunMode

        from hvc.runtime.run_dirs import latest_run_dir

        if HydraConfig.get().mode == RunMode.MULTIRUN:
            raise ConfigError("resume=true picks one run; a sweep's jobs would all pick the same one: "
                              "resume each with resume=<run dir>")
        run_dir = latest_run_dir(OmegaConf.to_container(cfg, resolve=True), output_dir)
        log.info("resume=true: continuing %s", run_dir)
    else:
        run_dir = Path(cfg.resume)
    if not run_dir.is_dir():
        raise ConfigError(f"resume={cfg.resume} is not a run directory")
    return run_dir


def _composed(cfg: DictConfig, given: list[str], options: list[str]) -> DictConfig:
    """The config for `options` (a resume's: the run's own options restored), `cfg` itself
    when they are the command's own `given` ones (resume=<dir> restored them before Hydra)."""
    if options == given:
        return cfg
    log.info("resuming with the run's own options: %s", " ".join(o for o in options if o not in given))
    cfg = compose(config_name="config", overrides=options)
    validate(cfg)
    return cfg


def _dispatch(cfg: DictConfig, run_dir: Path) -> dict:
    if cfg.stage == "rollout":
        from hvc.runtime.rollout import run_rollout

        summary = run_rollout(cfg, run_dir)
    elif cfg.stage == "train":
        from hvc.runtime.hl_train import run_hl_training

        summary = run_hl_training(cfg, run_dir)
    elif cfg.stage == "record":
        from hvc.runtime.record import run_record

        summary = run_record(cfg, run_dir)
    elif cfg.stage == "lowlevel":
        from hvc.runtime.lowlevel_stage import run_lowlevel

        summary = run_lowlevel(cfg, run_dir)
    elif cfg.stage == "evaluate":
        from hvc.runtime.evaluate_stage import run_evaluate

        summary = run_evaluate(cfg, run_dir)
    else:  # validate() admits only known stages
        from hvc.runtime.mocap_stages import STAGES

        summary = STAGES[cfg.stage](cfg, run_dir)
    return summary


def _with_resumed_options(argv: list[str]) -> list[str]:
    """`resume=<run dir>`: the run's saved options after this command's (which win), before
    Hydra composes, so that an option of the run's own groups (task.turn_rate_repeat of
    task=tracking) can be changed on resume, and Hydra's run dir set to the run's.
    resume=true is merged in _run, once found."""
    dirs = [a.partition("=")[2] for a in argv if a.startswith("resume=")]
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


def main() -> None:
    try:
        sys.argv = [sys.argv[0], *_with_resumed_options(sys.argv[1:])]
        check_group_overrides(a for a in sys.argv[1:] if not a.startswith("-"))
    except ConfigError as error:
        print(f"hvc-run: error: {error}", file=sys.stderr)
        sys.exit(2)
    _run()


if __name__ == "__main__":
    main()
