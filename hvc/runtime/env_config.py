"""Plain (task, body, render) dicts for building envs from a composed config.

The tracking task needs two things the config only names: the clip-set entry to track
(`clip=`) and the mocap file it resolves against (`mocap_file=` or the search order of
hvc.mocap.source); both are filled in here, once, before any env is built.
"""
from __future__ import annotations

import logging
from typing import Any

from omegaconf import DictConfig, OmegaConf

from hvc.config import group_config

log = logging.getLogger(__name__)


def _plain(node) -> Any:
    return OmegaConf.to_container(node, resolve=True)


def _with_start_poses(cfg: DictConfig, task: dict, body: dict) -> dict:
    """Adds the clip set's entries and mocap file, the source of the start poses, to a
    navigation task of the humanoid driven end to end; without a mocap file the body starts
    upright (logged). Controllers with skills start from their own library's references."""
    if not (task.get("init_from_clips") and body.get("humanoid")) or cfg.controller.get("skills") != "none":
        return task
    from hvc.mocap.clip_sets import entries_of, resolve
    from hvc.mocap.source import find_mocap_file

    try:
        mocap_file = find_mocap_file(cfg.mocap_file, str(body.get("model_version", "2019")))
    except FileNotFoundError as error:
        log.warning("start poses: %s; the body starts upright instead", error)
        return task
    task["init_clips"] = [e.as_dict() for e in resolve(entries_of(cfg.clips), str(mocap_file))]
    task["mocap_file"] = str(mocap_file)
    return task


def vector_env(cfg: DictConfig, seed: int | None = None):
    """`cfg.num_envs` envs of the configured task, body and controller (with its experts),
    seeded `seed` (default cfg.seed), seed + 1, ...; the one place a run's VectorEnv is built.
    Its `controller` is None when the controller cannot be built (the caller decides)."""
    from hvc.controllers.factory import Drive
    from hvc.envs.vector_env import VectorEnv
    from hvc.errors import ControllerUnavailable
    from hvc.skills import skills_for_job

    task, body, render = env_dicts(cfg)
    try:
        skills = skills_for_job(cfg)
    except ControllerUnavailable as error:  # the caller decides: rollout drives the body, train stops
        skills, why_not = None, str(error)
    else:
        why_not = None
    seed = int(cfg.seed if seed is None else seed)
    controller = _plain(cfg.controller)
    drive = Drive(controller, skills) if controller else None  # workers build the controller from it
    if cfg.get("actors", "local") == "ray":  # envs in Ray actors, on this machine or a cluster
        from hvc.envs.ray_actors import RayVectorEnv, connect

        connect(cfg.ray.address, cfg.ray.num_cpus)
        envs = RayVectorEnv(task, body, render, int(cfg.num_envs), seed=seed, drive=drive,
                            cpus_per_actor=float(cfg.ray.cpus_per_actor), compiled=bool(cfg.ray.compiled))
    else:
        envs = VectorEnv(task, body, render, int(cfg.num_envs), seed=seed, drive=drive,
                         in_process=int(cfg.in_process_envs))
    if why_not:
        envs.why_no_controller = why_not
    return envs


def env_dicts(cfg: DictConfig, entry=None, tracking: bool = False,
              with_mocap: bool = True) -> tuple[dict, dict, dict]:
    """`tracking=True` builds the tracking task whatever `task` says (playback, openloop);
    `entry` overrides the clip chosen by `clip=`; `with_mocap=False` leaves the mocap file
    out (the caller supplies the reference, e.g. from an expert library)."""
    body, render = _plain(cfg.body), _plain(cfg.render)
    if cfg.task.kind == "tracking":
        task = _plain(cfg.task)
    elif tracking:
        task = _plain(OmegaConf.merge(group_config("task", "tracking"), {"reward": _plain(cfg.reward)}))
    else:
        return _with_start_poses(cfg, _plain(cfg.task), body), body, render
    from hvc.mocap.clip_sets import select_entry
    from hvc.mocap.source import find_mocap_file

    entry = entry if entry is not None else select_entry(cfg.clips, cfg.clip)
    task["clip"] = entry.as_dict()
    if with_mocap:
        task["mocap_file"] = str(find_mocap_file(cfg.mocap_file, str(body.get("model_version", "2019"))))
    return task, body, render
