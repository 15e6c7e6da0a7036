"""The motion-capture stages of `hvc-run`: info, convert, playback, openloop.

Each is a thin driver over the library (hvc.mocap, hvc.lowlevel) that prints
`key=value` lines scripts can parse and writes its outputs into the run directory.
"""
from __future__ import annotations

from pathlib import Path
import numpy as np
from omegaconf import DictConfig

from hvc.io.metrics import MetricsLogger
from hvc.mocap.clip_sets import entries_of, fragments, resolve, select_entry
from hvc.mocap.source import find_mocap_file
from hvc.runtime.env_config import env_dicts


def mocap_file_of(cfg: DictConfig) -> Path:
    return find_mocap_file(cfg.mocap_file, str(cfg.body.get("model_version", "2019")))


def run_info(cfg: DictConfig, run_dir: Path) -> dict:
    mocap_file = mocap_file_of(cfg)
    entries = resolve(entries_of(cfg.clips), str(mocap_file))
    frags = fragments(entries, cfg.fragment_len)
    print(f"clip set {cfg.clips.name} from {mocap_file} (fragment_len={cfg.fragment_len}, "
          f"dt={cfg.task.control_timestep})")
    for c, e in enumerate(entries):
        count = sum(f.clip == c for f in frags)
        print(f"clip id={e.id} behaviour={e.behaviour} start={e.start} end={e.end} steps={e.num_steps} "
              f"cyclic={str(e.cyclic).lower()} fragments={count}")
    print(f"clips={len(entries)} fragments={len(frags)}")
    return {"clips": len(entries), "fragments": len(frags), "mocap_file": str(mocap_file)}


def run_convert(cfg: DictConfig, run_dir: Path) -> dict:
    from hvc.mocap.convert import convert_folder

    if not cfg.source:
        raise ValueError("stage=convert needs source=<folder of ASF/AMC/BVH files>")
    version = str(cfg.body.get("model_version", "2019"))
    out = Path(cfg.out) if cfg.out else Path("outputs/mocap") / f"cmu_{version}.h5"
    out.parent.mkdir(parents=True, exist_ok=True)
    ids = convert_folder(str(cfg.source), str(out), walker_version=version, dt=float(cfg.task.control_timestep))
    print(f"converted clips={len(ids)} out={out}")
    return {"clips": ids, "out": str(out)}


def run_playback(cfg: DictConfig, run_dir: Path) -> dict:
    """Renders the reference of `clip` kinematically (no physics) to a video."""
    from hvc.envs.fast_env import FastEnv
    from hvc.envs.render import CameraRenderer
    from hvc.runtime.video import write_video

    import mujoco

    entry = select_entry(cfg.clips, cfg.clip)
    task, body, render = env_dicts(cfg, entry, tracking=True)
    env = FastEnv.build(task, body, render, seed=cfg.seed, render=False)
    logic = env.layout.logic
    camera = CameraRenderer(env.model, "walker/side", {**render, "height": 240, "width": 320})
    frames = []
    for t in range(logic.reference.num_steps):
        logic.set_reference_state(env.data, t)
        mujoco.mj_forward(env.model, env.data)
        frames.append(camera.render(env.data))
    camera.close()
    env.close()
    path = write_video(run_dir / f"playback_{entry.id}.mp4", frames, fps=1.0 / env.control_timestep)
    print(f"playback clip={entry.id} steps={len(frames)} video={path}")
    return {"clip": entry.id, "steps": len(frames), "video": str(path)}


def run_openloop(cfg: DictConfig, run_dir: Path) -> dict:
    """The open-loop baseline on each clip of the set (or on `clip=` alone)."""
    from hvc.envs.fast_env import FastEnv
    from hvc.lowlevel.evaluation import evaluate_open_loop

    mocap_file = mocap_file_of(cfg)
    entries = [select_entry(cfg.clips, cfg.clip)] if cfg.clip else resolve(entries_of(cfg.clips), str(mocap_file))
    results = {}
    with MetricsLogger(run_dir / "metrics.csv") as metrics:
        for e in entries:
            task, body, render = env_dicts(cfg, e, tracking=True)
            env = FastEnv.build(task, body, render, seed=cfg.seed, render=False)
            scores = evaluate_open_loop(env, cfg.episodes)
            env.close()
            metrics.log(0, {f"{k}/{e.id}": v for k, v in scores.items()})
            results[e.id] = scores
            print(f"openloop clip={e.id} behaviour={e.behaviour} completion={scores['openloop_completion']:.2f} "
                  f"reward={scores['openloop_reward']:.2f} fall_rate={scores['openloop_fall_rate']:.2f} "
                  f"steps={scores['openloop_steps']:.1f}")
    return {"clips": results, "mean_completion": float(np.mean([r["openloop_completion"] for r in results.values()]))}


