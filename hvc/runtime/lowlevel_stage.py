"""`hvc-run stage=lowlevel`: train one expert per clip of a set, in parallel processes.

Each clip trains in its own process and run directory (`experts/<i>_<behaviour>_<id>/`:
metrics.csv, checkpoint.pt, progress.json); the parent shows one progress bar per clip
and, when all are done, assembles the expert library. `resume=<run dir>` continues a
killed run in place: finished clips are kept, the others restart from their checkpoints;
with a larger `total_steps=`, finished clips go on too, with their critic and replay.
"""
from __future__ import annotations

import json
import logging
import multiprocessing as mp
import os
import signal
import time
import traceback
from pathlib import Path

import numpy as np
from omegaconf import DictConfig, OmegaConf

from hvc.config import ConfigError, group_config
from hvc.envs.switching_tracking import switching_clip
from hvc.errors import HvcUserError
from hvc.mocap.clip_sets import entries_of, resolve
from hvc.mocap.source import find_mocap_file
from hvc.provenance import run_commands
from hvc.runtime.env_config import env_dicts
from hvc.runtime.progress import Progress
from hvc.runtime.signals import raise_interrupt

log = logging.getLogger(__name__)


def expert_dir(run_dir: Path, index: int, entry) -> Path:
    return run_dir / "experts" / f"{index}_{entry.behaviour}_{entry.id}"


def _train_worker(task, body, render, cfg_ll, out_dir: str, total_steps: int, seed: int, parent: int,
                  warm_start=None) -> None:
    from hvc.lowlevel.train import train_expert

    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C goes to the parent, which stops us cleanly
    out = Path(out_dir)
    try:
        result = train_expert(task, body, render, cfg_ll, out, total_steps, seed, parent_pid=parent,
                              warm_start=warm_start)
        (out / "result.json").write_text(json.dumps(result, indent=2))
    except Exception:  # noqa: BLE001 - recorded for the parent, which names the clip
        (out / "error.txt").write_text(traceback.format_exc())
        raise


def _library(source: str):
    from hvc.lowlevel.library import ExpertLibrary, shipped_library

    return ExpertLibrary.load(shipped_library() if source == "shipped" else Path(source))


def reusable_experts(cfg: DictConfig, entries) -> dict[int, tuple]:
    """{entry index: (expert, its env steps)} from `lowlevel.reuse`: a library, `shipped`
    (every shipped library of clip experts, the set's own first) or a list of those, whose experts of the same skill (clip, range,
    looping: hvc.skills.skill_key) are kept rather than retrained, under this set's behaviour
    names (the paper augments a set "without any additional work": gaps = the 4 base
    behaviours + 8 jumps; forage's walk-and-turns serve heterogeneous forage's turns). A
    switching library gives one expert per behaviour (ExpertLibrary.as_clip_experts)."""
    from hvc.lowlevel.library import Expert, ExpertLibrary
    from hvc.skills import shipped_clip_libraries, skill_key

    source = cfg.lowlevel.get("reuse")
    if not source or cfg.clips.get("switching"):
        return {}
    sources = [source] if isinstance(source, str) else list(source)  # a list: the first holding a skill wins
    paths = [p for s in sources for p in (shipped_clip_libraries(cfg.clips) if s == "shipped" else [Path(s)])]
    by_skill: dict[tuple, tuple] = {}
    for path in paths:
        library = ExpertLibrary.load(path).as_clip_experts()
        steps = library.meta.get("provenance", {}).get("env_steps") or [0] * len(library.experts)
        for expert, n in zip(library.experts, steps):
            by_skill.setdefault(skill_key(expert.entry), (expert, int(n)))
    found = {}
    for i, entry in enumerate(entries):
        if skill_key(entry.as_dict()) in by_skill:
            expert, n = by_skill[skill_key(entry.as_dict())]
            found[i] = (Expert(entry.as_dict(), expert.policy, expert.reference, expert.scores), n)
    log.info("reusing %d of %d experts from %s", len(found), len(entries), source)
    return found


def warm_start_policies(cfg: DictConfig, entries) -> dict[int, object]:
    """{entry index: policy} from `lowlevel.warm_start`, a library whose expert tracking the
    same frames of the same clip starts that entry's training (its behaviour, looped length
    and steering may differ): clips=steerable lowlevel.warm_start=shipped starts the
    steerable policy from the run expert, which already runs its gait cycle. For
    clips=switching, {0: [one expert per behaviour]}, which the switching policy distils, or
    from a switching library of the same behaviours, {0: its policy}, which goes on training."""
    source = cfg.lowlevel.get("warm_start")
    if not source:
        return {}
    library = _library(source)
    if cfg.clips.get("switching") and "switching_entries" in library.meta:
        mine = [(e.id, e.start, e.end, e.behaviour) for e in entries]
        theirs = [(e["id"], e.get("start"), e.get("end"), e["behaviour"]) for e in library.meta["switching_entries"]]
        if mine != theirs:
            raise ConfigError(f"lowlevel.warm_start={source} is a switching policy over {theirs}, not over "
                              f"clips={cfg.clips.name}'s behaviours {mine}")
        log.info("switching policy: goes on from the switching policy of %s (unless it resumes)", source)
        return {0: library.experts[0].policy}
    frames = lambda e: (e["id"], int(e.get("start") or 0), e.get("end"), bool(e.get("cyclic")))  # noqa: E731
    by_frames: dict[tuple, list] = {}
    for expert in library.experts:
        by_frames.setdefault(frames(expert.entry), []).append(expert)
    found = {}
    for i, entry in enumerate(entries):
        candidates = by_frames.get(frames(entry.as_dict()), [])
        if len(candidates) > 1:
            raise ConfigError(f"lowlevel.warm_start={source} has {len(candidates)} experts of the frames of "
                              f"{entry.id} ({[c.entry['behaviour'] for c in candidates]}); keep one in the library")
        if candidates:
            found[i] = candidates[0].policy
    have = sorted({frames(e.entry)[:3] for e in library.experts})
    if cfg.clips.get("switching"):
        missing = [e.id for i, e in enumerate(entries) if i not in found]
        if missing:
            raise ConfigError(f"lowlevel.warm_start={source} lacks experts for behaviours {missing} of "
                             f"clips={cfg.clips.name}; the switching policy distils one per behaviour (it has {have})")
        log.info("switching policy: distils %d experts of %s (unless it resumes from a checkpoint)", len(found), source)
        return {0: [found[i] for i in range(len(entries))]}
    if not found:
        raise ConfigError(f"lowlevel.warm_start={source} has no expert for any clip of clips={cfg.clips.name} "
                         f"(it has {have})")
    log.info("warm start for %d of %d clips from %s (clips with a checkpoint resume from it instead)", len(found),
             len(entries), source)
    return found


def run_lowlevel(cfg: DictConfig, run_dir: Path) -> dict:
    mocap_file = find_mocap_file(cfg.mocap_file, str(cfg.body.get("model_version", "2019")))
    entries = resolve(entries_of(cfg.clips), str(mocap_file))
    cfg_ll = OmegaConf.to_container(cfg.lowlevel, resolve=True)
    reused = reusable_experts(cfg, entries)
    warm = warm_start_policies(cfg, entries)
    if float(cfg.lowlevel.get("kickstart_cost", 0.0)) > 0 and not isinstance(warm.get(0), list):
        raise ConfigError(f"lowlevel.kickstart_cost={cfg.lowlevel.kickstart_cost} needs teachers: clips=switching and "
                          f"lowlevel.warm_start=<a library of one expert per behaviour> (got clips={cfg.clips.name}, "
                          f"lowlevel.warm_start={cfg.lowlevel.get('warm_start')})")
    jobs = []
    if cfg.clips.get("switching"):  # one policy over the whole set (the switching controller's)
        spec = OmegaConf.to_container(cfg.clips.switching, resolve=True)
        combined = switching_entry(cfg)
        out = expert_dir(run_dir, 0, combined)
        out.mkdir(parents=True, exist_ok=True)
        task, body, render = env_dicts(cfg, entries[0], tracking=True)
        task["clip"] = switching_clip(entries, spec)
        if not _finished(out, int(cfg.total_steps)):
            (out / "result.json").unlink(missing_ok=True)  # going on: it scored the policy as it was
            jobs.append((combined, out, (task, body, render, cfg_ll, str(out), int(cfg.total_steps), int(cfg.seed),
                                         os.getpid(), warm.get(0))))
    for i, entry in enumerate(entries if not cfg.clips.get("switching") else []):
        if i in reused:
            continue
        out = expert_dir(run_dir, i, entry)
        out.mkdir(parents=True, exist_ok=True)
        (out / "error.txt").unlink(missing_ok=True)
        if _finished(out, int(cfg.total_steps)):
            continue  # finished in an earlier attempt of this run
        (out / "result.json").unlink(missing_ok=True)  # going on: it scored the policy as it was
        task, body, render = env_dicts(cfg, entry, tracking=True)
        jobs.append((entry, out, (task, body, render, cfg_ll, str(out), int(cfg.total_steps), int(cfg.seed) + i,
                                   os.getpid(), warm.get(i))))
    if not jobs and cfg.get("resume"):
        log.warning("%s is complete: every clip it trains has done total_steps=%d; the library is assembled "
                    "again; pass a larger total_steps= to go on", run_dir, int(cfg.total_steps))
    for var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ.setdefault(var, "1")  # one BLAS thread per clip process (inherited at spawn)
    ctx = mp.get_context("spawn")
    limit = int(cfg.lowlevel.workers) or len(jobs) or 1
    running: list[tuple] = []
    bars = {str(out): Progress(f"{entry.behaviour} {entry.id}", int(cfg.total_steps), _steps_done(out),
                              float(cfg.progress_seconds), position=k) for k, (entry, out, _) in enumerate(jobs)}
    pending = list(jobs)
    failed = []
    previous = signal.signal(signal.SIGTERM, raise_interrupt)  # `kill` stops workers too
    try:
        while pending or running:
            while pending and len(running) < limit:
                entry, out, args = pending.pop(0)
                proc = ctx.Process(target=_train_worker, args=args, name=f"hvc-expert-{entry.id}")
                proc.start()
                bars[str(out)].restart()
                running.append((entry, out, proc))
            time.sleep(2.0)
            for entry, out, proc in list(running):
                alive = proc.is_alive()  # before reading: a finished worker's last report is read too
                _report(bars[str(out)], out)
                if not alive:
                    running.remove((entry, out, proc))
                    if proc.exitcode != 0:
                        failed.append(f"clip {entry.id} ({entry.behaviour}) failed, exit code {proc.exitcode}; "
                                      f"see {out / 'error.txt'}")
    finally:
        for _, _, proc in running:  # Ctrl-C / kill: workers save a checkpoint at their next unroll and stop
            proc.terminate()
        for _, _, proc in running:
            proc.join(timeout=120)
        for out, bar in bars.items():
            bar.close("finished" if (Path(out) / "result.json").exists()
                      else "failed" if any(out in f for f in failed) else "stopped")
        signal.signal(signal.SIGTERM, previous)
    if failed:
        raise RuntimeError("; ".join(failed))
    if cfg.clips.get("switching"):
        entries = [combined]
    library = assemble_library(cfg, run_dir, entries, mocap_file, reused)
    if not cfg.clips.get("switching"):
        score_reused(cfg, library, sorted(reused))
    path = library.save(run_dir / f"experts_{cfg.clips.name}.npz")
    for e in library.experts:
        scored = (f"completion={e.scores['eval_completion']:.2f} reward={e.scores['eval_reward']:.2f}"
                  if "eval_completion" in e.scores else f"not scored (`hvc-run stage=evaluate library={path}`)")
        print(f"expert clip={e.entry['id']} behaviour={e.entry['behaviour']} {scored}")
    print(f"library={path}")
    return {"library": str(path), "experts": {f"{e.entry['behaviour']} ({e.entry['id']})": e.scores
                                             for e in library.experts}}  # one clip can give two entries


def _report(bar: Progress, out: Path) -> None:
    """Moves a clip's bar to what its worker last wrote in progress.json."""
    try:
        done = json.loads((out / "progress.json").read_text())
        bar.update(int(done["env_steps"]), done.get("episode_return"), done.get("learner_steps"))
    except (OSError, ValueError, KeyError):
        pass


def _finished(out: Path, total_steps: int) -> bool:
    """Whether a clip is done: evaluated at its end (result.json), and not behind a larger
    `total_steps` that its checkpoint can go on to."""
    return (out / "result.json").exists() and (_steps_done(out) >= total_steps
                                               or not (out / "checkpoint.pt").exists())


def _steps_done(out: Path) -> int:
    """A clip's env steps in an earlier attempt of this run (its progress.json), else 0."""
    try:
        return int(json.loads((out / "progress.json").read_text())["env_steps"])
    except (OSError, ValueError, KeyError):
        return 0


def switching_entry(cfg: DictConfig):
    """The one entry that stands for a switching run's policy over the whole clip set."""
    from hvc.mocap.clip_sets import ClipEntry

    return ClipEntry(id="switching", behaviour="switching", steps=int(cfg.clips.switching.steps))


def library_from_run(run_dir: Path, mocap_file: str | None = None):
    """The library of a `stage=lowlevel` run dir as its checkpoints stand now, finished or
    not (checkpoints are replaced atomically, so a running run can be read): what
    `stage=evaluate library=<run dir>` scores while training goes on."""
    run_dir = Path(run_dir)
    config = run_dir / "config_resolved.yaml"
    if not config.is_file():
        raise HvcUserError(f"library={run_dir} is a directory but not a stage=lowlevel run dir "
                           "(no config_resolved.yaml)")
    cfg = OmegaConf.load(config)
    mocap = find_mocap_file(mocap_file or cfg.mocap_file, str(cfg.body.get("model_version", "2019")))
    entries = [switching_entry(cfg)] if cfg.clips.get("switching") else resolve(entries_of(cfg.clips), str(mocap))
    reused = reusable_experts(cfg, entries)
    missing = [str(expert_dir(run_dir, i, e)) for i, e in enumerate(entries)
               if i not in reused and not (expert_dir(run_dir, i, e) / "checkpoint.pt").exists()]
    if missing:
        raise HvcUserError(f"library={run_dir}: no checkpoint yet in {missing} (one is written every "
                          f"lowlevel.checkpoint_seconds={cfg.lowlevel.checkpoint_seconds})")
    return assemble_library(cfg, run_dir, entries, mocap, reused)


def score_reused(cfg: DictConfig, library, indices) -> None:
    """Scores the reused experts that came without scores (a switching library's behaviours, played one
    expert each) as training scores its own: lowlevel.eval_episodes from random starts, mean action. A
    reused expert with scores keeps them: they are its own training's."""
    from hvc.lowlevel.evaluation import evaluate
    from hvc.lowlevel.library import policy_observation
    from hvc.runtime.evaluate_stage import expert_env

    episodes = int(cfg.lowlevel.eval_episodes)
    for i in indices:
        expert = library.experts[i]
        if expert.scores or episodes < 1:
            continue
        env = expert_env(cfg, expert, library)
        try:
            expert.scores = evaluate(env, lambda obs, logic, e=expert: e.act(policy_observation(obs)), episodes, "eval_")
        finally:
            env.close()


def assemble_library(cfg: DictConfig, run_dir: Path, entries, mocap_file: Path, reused: dict | None = None):
    """The expert library from the clips' checkpoints and evaluation results (and the
    experts reused from another library, as they are); a clip still training has no
    evaluation result yet, and its expert no scores."""
    import torch

    from hvc.agents.mlp import GaussianPolicy, NumpyPolicy
    from hvc.lowlevel.library import Expert, ExpertLibrary, provenance
    from hvc.mocap.reference import build_reference

    experts, steps, behaviours = [], [], []
    for i, entry in enumerate(entries):
        if reused and i in reused:
            expert, n = reused[i]
            experts.append(expert)
            steps.append(n)
            continue
        out = expert_dir(run_dir, i, entry)
        state = torch.load(out / "checkpoint.pt", weights_only=True)
        policy = GaussianPolicy.from_weights(state["learner"]["policy"], cfg.lowlevel.hidden, cfg.lowlevel.sigma)
        tracking = cfg.task if cfg.task.kind == "tracking" else group_config("task", "tracking")
        if entry.id == "switching":  # the switching policy: one Markov walk over the set stands for it
            from hvc.mocap.switching import MAX_ACCEL, markov_reference

            behaviours = [build_reference(e.as_dict(), str(mocap_file), int(tracking.cycle_repeats),
                                          int(tracking.cycle_blend))
                          for e in resolve(entries_of(cfg.clips), str(mocap_file))]
            graph = {int(k): list(v) for k, v in cfg.clips.switching.graph.items()}
            reference, _ = markov_reference(behaviours, graph, int(entry.steps), np.random.default_rng(0),
                                            max_accel=float(cfg.clips.switching.get("max_accel", MAX_ACCEL)))
        else:
            reference = build_reference(entry.as_dict(), str(mocap_file), int(tracking.cycle_repeats),
                                        int(tracking.cycle_blend))
        result = out / "result.json"
        scores = json.loads(result.read_text()) if result.exists() else {}
        steps.append(int(state["counters"]["env_steps"]))
        experts.append(Expert(entry.as_dict(), NumpyPolicy.from_torch(policy), reference, scores))
    meta = {"clip_set": str(cfg.clips.name), "body": str(cfg.body.name), "sigma": float(cfg.lowlevel.sigma),
            **({"switching_entries": [e.as_dict() for e in resolve(entries_of(cfg.clips), str(mocap_file))],
                "switching": OmegaConf.to_container(cfg.clips.switching, resolve=True)}
               if cfg.clips.get("switching") else {}),
            "hidden": list(cfg.lowlevel.hidden), "control_timestep": float(cfg.task.control_timestep),
            "provenance": provenance(steps, {"mocap_file": str(mocap_file), "training_command": _training_command(run_dir),
                                                 "run_commands": run_commands(run_dir)})}
    return ExpertLibrary(experts, meta, behaviours)


def _training_command(run_dir: Path) -> str:
    """The command that started the run (Hydra's record in the run dir), not a later resume's."""
    overrides = run_dir / ".hydra" / "overrides.yaml"
    if not overrides.exists():
        return ""
    import yaml

    return " ".join(["hvc-run", *yaml.safe_load(overrides.read_text())])
