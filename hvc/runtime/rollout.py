"""`stage=rollout`: random high-level actions on the fast env, no learning.

The actions are high-level ones through the configured controller (fragments of the
expert library, queries, or end_to_end body actions) when it can be built, else random
body actions (logged). It exercises what a training run will use (task, body, fast env,
controller, vector env, metrics, progress, video) and gives each task's random baseline.
"""
from __future__ import annotations

import logging
import time
from pathlib import Path

import numpy as np
from omegaconf import DictConfig
from tqdm import tqdm

from hvc.envs.fast_env import FastEnv
from hvc.envs.render import CameraRenderer
from hvc.io.metrics import MetricsLogger
from hvc.runtime.env_config import env_dicts, vector_env
from hvc.runtime.episodes import EpisodeRecorder, write_fragment_table
from hvc.runtime.video import write_video

log = logging.getLogger(__name__)
VIDEO_CAMERAS = ("walker/back", "walker/side", "walker/egocentric")


def run_rollout(cfg: DictConfig, run_dir: Path) -> dict:
    rng = np.random.default_rng(cfg.seed)
    returns: list[float] = []
    steps = 0
    start = time.perf_counter()
    with MetricsLogger(run_dir / "metrics.csv") as metrics, \
            tqdm(total=cfg.total_steps, desc=f"rollout {cfg.task.name}", unit="step",
                 disable=None, mininterval=1.0) as bar:
        env = vector_env(cfg)
        if env.controller is None:
            log.warning("rollout drives the body with random actions: %s", env.why_no_controller)
        else:
            log.info("rollout: random high-level actions through controller=%s (%s)", env.controller,
                     f"{env.action_space.n} choices" if env.action_space.discrete else f"{env.action_space.size}-D")
        hl_actions = 0
        recorder = EpisodeRecorder(run_dir / "episodes", int(cfg.record_episodes))
        if recorder.active and env.skills is not None and env.skills.fragments:
            write_fragment_table(run_dir / "fragments.csv", env.skills)
        try:
            obs = env.reset()
            while steps < cfg.total_steps:
                before = {k: v[0] for k, v in obs.items()}
                obs, rewards, _, dones, infos = env.step(env.random_actions(rng))
                recorder.add(before, float(rewards[0]), infos[0], bool(dones[0]))
                before, steps = steps, steps + env.num_envs
                bar.update(env.num_envs)
                hl_actions += sum(bool(info.get("new_action")) for info in infos)
                for info in infos:
                    if "episode_return" in info:
                        returns.append(info["episode_return"])
                        metrics.log(steps, {"episode_return": info["episode_return"],
                                            "episode_length": info["episode_length"]})
                if steps // cfg.log_every > before // cfg.log_every:
                    sps = steps / (time.perf_counter() - start)
                    metrics.log(steps, {"steps_per_second": sps})
                    bar.set_postfix(sps=f"{sps:.0f}", ret=f"{np.mean(returns[-10:]):.2f}" if returns else "-")
            metrics.log(steps, {"steps_per_second": steps / (time.perf_counter() - start),
                                "hl_actions": hl_actions})
        finally:
            env.close()
    summary = {"env_steps": steps, "episodes": len(returns), "hl_actions": hl_actions,
               "mean_episode_return": float(np.mean(returns)) if returns else float("nan")}
    if cfg.video:
        summary["video"] = str(record_video(cfg, run_dir / "rollout.mp4"))
    return summary


def record_video(cfg: DictConfig, path: Path) -> Path:
    """A third-person view beside the agent's camera (vision tasks), random actions."""
    task, body, render = env_dicts(cfg)
    env = FastEnv.build({**task, "layout_pool": 1}, body, render, seed=cfg.seed, render=False)
    env.reset()
    view, own = _cameras(env, render)
    frames = []
    for _ in range(cfg.video_steps):
        frames.append(np.concatenate(_views(env, view, own), axis=1))
        if env.step(env.random_action())[3]:
            env.reset()
    for r in (view, own):
        if r is not None:
            r.close()
    env.close()
    return write_video(path, frames, fps=1.0 / env.control_timestep)


def _cameras(env, render) -> tuple:
    """A third-person camera (the first of VIDEO_CAMERAS the model has) and the agent's own."""
    names = {env.model.cam(i).name for i in range(env.model.ncam)}
    camera = next((c for c in VIDEO_CAMERAS if c in names), None)
    view = CameraRenderer(env.model, camera, {**render, "height": 192, "width": 256}) if camera else None
    own = CameraRenderer(env.model, env.layout.camera, render) if env.layout.camera else None
    return view, own


def _views(env, view, own) -> list[np.ndarray]:
    """The current frame of each camera, the agent's scaled up to the third-person height."""
    parts = [view.render(env.data)] if view else []
    if own is not None:
        eye = own.render(env.data)
        scale = 192 // eye.shape[0]
        parts.append(np.kron(eye, np.ones((scale, scale, 1), np.uint8))[:192])
    return parts


def task_stills(cfg: DictConfig, steps: int = 0) -> list[np.ndarray]:
    """Fig. 5: the task's first state (after `steps` random actions) from a third-person camera
    and, on vision tasks, from the agent's own camera."""
    task, body, render = env_dicts(cfg)
    env = FastEnv.build({**task, "layout_pool": 1}, body, render, seed=cfg.seed, render=False)
    env.reset()
    for _ in range(steps):
        env.step(env.random_action())
    view, own = _cameras(env, render)
    try:
        return _views(env, view, own)
    finally:
        for r in (view, own):
            if r is not None:
                r.close()
        env.close()
