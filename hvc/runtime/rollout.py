"""The main job until high-level training lands: random body actions on the fast env.

It exercises everything a training run will use (task, body, fast env, vector env,
metrics, progress, video) and gives the random-policy baseline of each task.
"""
from __future__ import annotations

import time
from pathlib import Path

import numpy as np
from omegaconf import DictConfig
from tqdm import tqdm

from hvc.envs.fast_env import FastEnv
from hvc.envs.render import CameraRenderer
from hvc.envs.vector_env import VectorEnv
from hvc.runtime.env_config import env_dicts
from hvc.runtime.metrics import MetricsLogger
from hvc.runtime.video import write_video

VIDEO_CAMERAS = ("walker/back", "walker/side", "walker/egocentric")


def run_rollout(cfg: DictConfig, run_dir: Path) -> dict:
    task, body, render = env_dicts(cfg)
    rng = np.random.default_rng(cfg.seed)
    returns: list[float] = []
    steps = 0
    start = time.perf_counter()
    with MetricsLogger(run_dir / "metrics.csv") as metrics, \
            tqdm(total=cfg.total_steps, desc=f"rollout {task['name']}", unit="step",
                 disable=None, mininterval=1.0) as bar:
        env = VectorEnv(task, body, render, cfg.num_envs, seed=cfg.seed)
        try:
            env.reset()
            while steps < cfg.total_steps:
                _, rewards, _, dones, infos = env.step(env.random_actions(rng))
                before, steps = steps, steps + env.num_envs
                bar.update(env.num_envs)
                for info in infos:
                    if info:
                        returns.append(info["episode_return"])
                        metrics.log(steps, {"episode_return": info["episode_return"],
                                            "episode_length": info["episode_length"]})
                if steps // cfg.log_every > before // cfg.log_every:
                    sps = steps / (time.perf_counter() - start)
                    metrics.log(steps, {"steps_per_second": sps})
                    bar.set_postfix(sps=f"{sps:.0f}", ret=f"{np.mean(returns[-10:]):.2f}" if returns else "-")
            metrics.log(steps, {"steps_per_second": steps / (time.perf_counter() - start)})
        finally:
            env.close()
    summary = {"env_steps": steps, "episodes": len(returns),
               "mean_episode_return": float(np.mean(returns)) if returns else float("nan")}
    if cfg.video:
        summary["video"] = str(record_video(cfg, run_dir / "rollout.mp4"))
    return summary


def record_video(cfg: DictConfig, path: Path) -> Path:
    """A third-person view beside the agent's camera (vision tasks), random actions."""
    task, body, render = env_dicts(cfg)
    env = FastEnv.build({**task, "layout_pool": 1}, body, render, seed=cfg.seed, render=False)
    env.reset()
    names = {env.model.cam(i).name for i in range(env.model.ncam)}
    camera = next((c for c in VIDEO_CAMERAS if c in names), None)
    view = CameraRenderer(env.model, camera, {**render, "height": 192, "width": 256}) if camera else None
    own = CameraRenderer(env.model, env.layout.camera, render) if env.layout.camera else None
    frames = []
    for _ in range(cfg.video_steps):
        parts = [view.render(env.data)] if view else []
        if own is not None:
            eye = own.render(env.data)
            scale = 192 // eye.shape[0]
            parts.append(np.kron(eye, np.ones((scale, scale, 1), np.uint8))[:192])
        frames.append(np.concatenate(parts, axis=1))
        if env.step(env.random_action())[3]:
            env.reset()
    for r in (view, own):
        if r is not None:
            r.close()
    env.close()
    return write_video(path, frames, fps=1.0 / env.control_timestep)
