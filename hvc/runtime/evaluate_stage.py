"""`hvc-run stage=evaluate`: each expert of a library on its clip, beside the open loop.

Per clip: `episodes` episodes from random start points with the expert's mean action;
completion (fraction of the remaining clip tracked before termination) and mean
per-step tracking reward, next to the open-loop baseline on the same clip. One line per
clip on stdout and in the run dir's `evaluation.txt`, a table in `metrics.csv`, and with
`video=true` a video of each expert beside its reference (kinematic replay) from the same
start. `library=` takes an `.npz` or a `stage=lowlevel` run dir, whose checkpoints are read as
they stand (training may go on).
Then the library's composability: its controller under random high-level actions.
"""
from __future__ import annotations

from pathlib import Path
from typing import Callable

import numpy as np
from omegaconf import DictConfig

from hvc.errors import HvcUserError
from hvc.io.metrics import MetricsLogger
from hvc.lowlevel.evaluation import evaluate, evaluate_open_loop, steering_response, switching_transitions
from hvc.lowlevel.library import ExpertLibrary, policy_observation, shipped_library
from hvc.runtime.env_config import env_dicts


STEERING_RATE_COUNT = 7  # commanded rates, evenly over the tracking task's turn_rates (training range)
STEERING_CYCLES = 8  # gait cycles per steering episode: long enough to fit a heading slope


def expert_env(cfg: DictConfig, expert, library: ExpertLibrary):
    """The tracking env of one expert: its clip, a steered cycle, or the switching walks."""
    from hvc.envs.fast_env import FastEnv
    from hvc.mocap.clip_sets import ClipEntry

    task, body, render = env_dicts(cfg, ClipEntry(**expert.entry), tracking=True, with_mocap=False)
    if expert.entry["id"] == "switching":
        from hvc.envs.switching_tracking import switching_clip
        from hvc.mocap.source import find_mocap_file

        if "switching" not in library.meta:
            raise HvcUserError("this switching library does not record its transition graph (meta 'switching'); "
                             "reassemble it with `hvc-run stage=lowlevel clips=switching resume=<run dir>`")
        task["clip"] = switching_clip(library.meta["switching_entries"], library.meta["switching"], library.behaviours)
        if not library.behaviours:
            task["mocap_file"] = str(find_mocap_file(cfg.mocap_file, str(cfg.body.get("model_version", "2019"))))
    else:
        task["reference"] = expert.reference
    return FastEnv.build(task, body, render, seed=cfg.seed, render=False)


def structured_scores(cfg: DictConfig, env, expert, act, metrics: MetricsLogger,
                      say: Callable[[str], None] = print) -> dict[str, float]:
    """The steerable policy's turning-rate response and the switching policy's completed
    transitions (Sec. 2.2); nothing for a single-clip expert."""
    clip = expert.entry["id"]
    if expert.entry.get("steer"):
        rates = np.linspace(*env.layout.logic.turn_rates, STEERING_RATE_COUNT)
        per_rate = max(1, int(cfg.episodes) // len(rates))
        rows = steering_response(env, act, rates, per_rate, cycles=STEERING_CYCLES)
        for row in rows:
            metrics.log(0, {f"achieved_rate/{clip}/{row['commanded_rate']:+.1f}": row["achieved_rate"],
                            f"completion/{clip}/{row['commanded_rate']:+.1f}": row["completion"]})
            say(f"steer clip={clip} commanded_rate={row['commanded_rate']:+.2f} "
                f"achieved_rate={row['achieved_rate']:+.2f} completion={row['completion']:.2f} "
                f"fall_rate={row['fall_rate']:.2f}")
        error = [abs(r["achieved_rate"] - r["commanded_rate"]) for r in rows if np.isfinite(r["achieved_rate"])]
        return {"steering_rate_error": float(np.mean(error)) if error else float("nan")}
    if clip == "switching":
        from hvc.controllers.switching import gait_cycle_steps

        scores = switching_transitions(env, act, int(cfg.episodes), gait_cycle_steps(env.layout.logic.behaviours))
        say(f"switch clip={clip} transitions_completed={scores['transitions_completed']:.2f} "
            f"of {scores['transitions_attempted']:.0f}")
        names = [e.get("behaviour", e["id"]) for e in env.layout.logic.entries]
        for key in [k for k in scores if k.startswith("attempted/")]:
            a, b = (int(i) for i in key.split("/")[1].split("->"))
            say(f"switch from={names[a]} to={names[b]} completed={scores['completed/' + key[10:]]:.2f} "
                f"of {scores[key]:.0f}")
        return scores
    return {}


def evaluated_library(cfg: DictConfig) -> tuple[ExpertLibrary, str]:
    """(library, where from): `library=` (a file, or a stage=lowlevel run dir finished or still
    training), else the set's skills as a job would resolve them (hvc.skills): the shipped
    library only when its experts are the set's entries, so a `clips.entries=` override is
    not scored on the experts the set shipped with; `library=shipped` names the set's shipped one.
    A switching library with a set of clips is scored per behaviour, as fragments play it."""
    from hvc.skills import OWN_POLICY, skills_for_job

    name = str(cfg.clips.name)
    if cfg.get("library"):
        path = shipped_library(name) if cfg.library == "shipped" else Path(cfg.library)
        if path.is_dir():
            from hvc.runtime.lowlevel_stage import library_from_run

            library = library_from_run(path, cfg.get("mocap_file"))
        else:
            library = ExpertLibrary.load(path)
        return (library if name in OWN_POLICY else library.as_clip_experts()), str(path)
    from hvc.runtime.composability import composability_config

    # resolved once: the composability measure below drives the same skills
    skills = skills_for_job(composability_config(cfg, name if name in OWN_POLICY else "fragments"))
    return skills.library, skills.source


def run_evaluate(cfg: DictConfig, run_dir: Path) -> dict:
    library, path = evaluated_library(cfg)
    with open(run_dir / "evaluation.txt", "w") as report, MetricsLogger(run_dir / "metrics.csv") as metrics:
        def say(line: str) -> None:  # kept beside summary.json, wherever stdout went
            print(line)
            report.write(line + "\n")
            report.flush()

        say(f"library={path} experts={len(library)} episodes={cfg.episodes}")
        results = {}
        for expert in library.experts:
            env = expert_env(cfg, expert, library)
            act = lambda obs, logic, e=expert: e.act(policy_observation(obs))  # noqa: E731
            scores = evaluate(env, act, cfg.episodes)
            scores.update(evaluate_open_loop(env, cfg.episodes))
            clip = expert.entry["id"]
            scores.update(structured_scores(cfg, env, expert, act, metrics, say))
            metrics.log(0, {f"{k}/{clip}": v for k, v in scores.items()})
            results[clip] = scores
            say(f"eval clip={clip} completion={scores['completion']:.2f} reward={scores['reward']:.2f} "
                f"openloop_completion={scores['openloop_completion']:.2f} "
                f"openloop_reward={scores['openloop_reward']:.2f}")
            say(f"energy clip={clip} " + " ".join(f"{k.removeprefix('energy_')}={v:.2f}" for k, v in scores.items()
                                                 if k.startswith("energy_")))
            if cfg.video:
                record_expert_video(env, expert, run_dir / f"expert_{expert.entry['behaviour']}_{clip}.mp4")
            env.close()
        composed = composability(cfg, metrics, say)
    return {"library": path, "clips": results, **({"composability": composed} if composed else {})}


def composability(cfg: DictConfig, metrics: MetricsLogger, say: Callable[[str], None] = print) -> dict | None:
    """The library's skills under random high-level actions (hvc.runtime.composability): one
    line for the steps until a fall, and one per clip-to-clip switch for fragments; for
    fragments the same again with each switch played on through its clip (`compose_held`)."""
    from hvc.errors import ControllerUnavailable
    from hvc.runtime.composability import cold_switching, composability_config

    name = str(cfg.clips.name)
    controller = name if name in ("steerable", "switching") else "fragments"
    result = None
    for prefix, hold in [("compose", False)] + ([("compose_held", True)] if controller == "fragments" else []):
        try:
            scores = cold_switching(composability_config(cfg, controller), int(cfg.episodes), int(cfg.seed), hold=hold)
        except ControllerUnavailable as error:  # e.g. a stage=lowlevel run dir still training: no library file yet
            say(f"compose skipped: {error}")
            return None
        low, high = scores["median_ci95"]
        say(f"{prefix} controller={controller} clips={name} episodes={scores['episodes']} "
            f"mean_steps={scores['mean_steps']:.1f} median_steps={scores['median_steps']:g} "
            f"median_ci95={low:g}-{high:g} fall_rate={scores['fall_rate']:.2f} cap={scores['cap']}")
        row = {f"{prefix}_{k}": scores[k] for k in ("mean_steps", "median_steps", "fall_rate")}
        row.update({f"{prefix}_median_ci95_low": low, f"{prefix}_median_ci95_high": high})
        until = f"next {scores['horizon']} steps" + (" played on, or to the clip's end" if hold else "")
        for pair, switch in scores["switches"].items():
            a, b = pair.split("->")
            say(f"{prefix}_switch from={a} to={b} survived={switch['survived']:.2f} of {switch['of']} ({until})")
            row[f"{prefix}_survived/{pair}"] = switch["survived"]
        metrics.log(0, row)
        if hold:  # the random driver's scores, with the held driver's under "held"
            result["held"] = scores
        else:
            result = scores
    return result


def record_expert_video(env, expert, path: Path) -> Path:
    """The expert (left) beside its reference replayed kinematically (right), same start."""
    import mujoco

    from hvc.envs.render import CameraRenderer
    from hvc.runtime.video import write_video

    settings = {"height": 240, "width": 320, "shadows": True, "reflections": False, "skybox": True}
    ghost = mujoco.MjData(env.model)
    view = CameraRenderer(env.model, "walker/side", settings)
    obs = env.reset()
    logic = env.layout.logic
    frames = []
    while True:
        logic_t = logic.t
        logic.set_reference_state(ghost, logic_t)
        mujoco.mj_forward(env.model, ghost)
        frames.append(np.concatenate([view.render(env.data), view.render(ghost)], axis=1))
        obs, _, _, done = env.step(expert.act(policy_observation(obs)))
        if done:
            break
    view.close()
    return write_video(path, frames, fps=1.0 / env.control_timestep)
