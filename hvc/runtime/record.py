"""`stage=record`: play a trained high-level agent and record its episodes for the analyses.

`record_episodes=N` during training saves the first N episodes, those of an untrained
agent. This stage loads a training run's checkpoint with the config that run was trained
with (`from_run=<run dir>`), plays its policy (sampling, as it acted in training) in one
env and writes episodes/, fragments.csv, a copy of the checkpoint and the config it played
with into its own run dir: the analysis scripts take this dir as they take a training
run's. Only seed and record_episodes come from the command line.
"""
from __future__ import annotations

import logging
import shutil
from pathlib import Path

import numpy as np
import torch
from omegaconf import DictConfig, OmegaConf
from tqdm import tqdm

from hvc.config import expand_clip_set, group_config
from hvc.errors import HvcUserError
from hvc.runtime.acting import Actor
from hvc.runtime.episodes import EpisodeRecorder
from hvc.runtime.hl_train import build_agent, load_checkpoint, make_envs
from hvc.skills import skills_for_job

log = logging.getLogger(__name__)


def trained_config(cfg: DictConfig) -> DictConfig:
    """The config `from_run` was trained with, playing `record_episodes` episodes in one env."""
    if not cfg.get("from_run"):
        raise HvcUserError("stage=record needs from_run=<run dir of a stage=train run>")
    source = Path(cfg.from_run)
    for name in ("checkpoint.pt", "config_resolved.yaml"):
        if not (source / name).is_file():
            raise HvcUserError(f"from_run={source} has no {name}: not a stage=train run dir")
    trained = _with_named_classes(OmegaConf.load(source / "config_resolved.yaml"))
    expand_clip_set(trained.clips)  # a run saved before composition expanded them
    if trained.stage != "train":
        raise HvcUserError(f"from_run={source} is a stage={trained.stage} run; stage=record plays stage=train runs")
    if int(cfg.record_episodes) <= 0:
        raise HvcUserError(f"stage=record needs record_episodes=N with N > 0, got {cfg.record_episodes}")
    return OmegaConf.merge(trained, {"num_envs": 1, "in_process_envs": 1, "seed": int(cfg.seed),
                                     "record_episodes": int(cfg.record_episodes)})


def _with_named_classes(trained: DictConfig) -> DictConfig:
    """A run trained before the controller and algorithm configs named their classes
    (`_target_`, the controller's `skills` kind) gets them from today's config of the same name."""
    for group in ("controller", "algorithm"):
        node = trained[group]
        current = group_config(group, str(node.name))
        for key in ("_target_", "skills"):
            if key in current and key not in node:
                node[key] = current[key]
    return trained


def run_record(cfg: DictConfig, run_dir: Path) -> dict:
    torch.set_num_threads(1)
    torch.manual_seed(int(cfg.seed))  # the policy's samples: a seed gives the same episodes
    trained = trained_config(cfg)
    source = Path(cfg.from_run)
    skills = skills_for_job(trained)
    if skills is not None:
        skills.write(run_dir)
    # this run's own record: the config it played with (the training run's, plus the above)
    played = OmegaConf.merge(trained, {"stage": "record", "from_run": str(source)})
    (run_dir / "config_resolved.yaml").write_text(OmegaConf.to_yaml(played, resolve=True))
    state = load_checkpoint(source / "checkpoint.pt")
    envs = make_envs(trained)
    try:
        _, agent, learner = build_agent(trained, envs)
        agent.load_state_dict(state["agent"])
        agent.eval()
        shutil.copy(source / "checkpoint.pt", run_dir / "checkpoint.pt")  # for analysis/saliency.py
        recorder = EpisodeRecorder.for_run(trained, run_dir, envs.skills)
        actor = Actor(agent, learner, envs, recorder, update_normalizer=False)
        returns: list[float] = []
        with tqdm(total=recorder.max_episodes, desc="record", unit="episode", disable=None) as bar:
            while recorder.active:
                info = actor.step().infos[0]
                if "episode_return" in info:
                    returns.append(float(info["episode_return"]))
                    bar.update(1)
                    bar.set_postfix(ret=f"{np.mean(returns):.1f}")
    finally:
        envs.close()
    log.info("recorded %d episodes of %s (trained %d env steps): mean return %.2f", len(returns), source,
             int(state["counters"]["env_steps"]), float(np.mean(returns)))
    return {"from_run": str(source), "trained_env_steps": int(state["counters"]["env_steps"]),
            "episodes": len(returns), "mean_return": float(np.mean(returns)), "returns": returns}
