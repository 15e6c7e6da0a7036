"""`hvc-run stage=evaluate`: each expert of a library on its clip, beside the open loop.

Per clip: `episodes` episodes from random start points with the expert's mean action;
completion (fraction of the remaining clip tracked before termination) and mean
per-step tracking reward, next to the open-loop baseline on the same clip. One line per
clip on stdout, a table in `metrics.csv`, and with `video=true` a video of each expert
beside its reference (kinematic replay) from the same start.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
from omegaconf import DictConfig

from hvc.lowlevel.evaluation import evaluate, evaluate_open_loop, policy_observation
from hvc.lowlevel.library import ExpertLibrary, shipped_library
from hvc.runtime.env_config import env_dicts
from hvc.runtime.metrics import MetricsLogger


def expert_env(cfg: DictConfig, expert):
    from hvc.envs.fast_env import FastEnv
    from hvc.mocap.clip_sets import ClipEntry

    task, body, render = env_dicts(cfg, ClipEntry(**expert.entry), tracking=True, with_mocap=False)
    task["reference"] = expert.reference
    return FastEnv.build(task, body, render, seed=cfg.seed, render=False)


def run_evaluate(cfg: DictConfig, run_dir: Path) -> dict:
    path = Path(cfg.library) if cfg.get("library") else shipped_library(str(cfg.clips.name))
    library = ExpertLibrary.load(path)
    print(f"library={path} experts={len(library)} episodes={cfg.episodes}")
    results = {}
    with MetricsLogger(run_dir / "metrics.csv") as metrics:
        for expert in library.experts:
            env = expert_env(cfg, expert)
            scores = evaluate(env, lambda obs, logic, e=expert: e.act(policy_observation(obs)), cfg.episodes)
            scores.update(evaluate_open_loop(env, cfg.episodes))
            clip = expert.entry["id"]
            metrics.log(0, {f"{k}/{clip}": v for k, v in scores.items()})
            results[clip] = scores
            print(f"eval clip={clip} completion={scores['completion']:.2f} reward={scores['reward']:.2f} "
                  f"openloop_completion={scores['openloop_completion']:.2f} "
                  f"openloop_reward={scores['openloop_reward']:.2f}")
            if cfg.video:
                record_expert_video(env, expert, run_dir / f"expert_{expert.entry['behaviour']}_{clip}.mp4")
            env.close()
    return {"library": str(path), "clips": results}


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
