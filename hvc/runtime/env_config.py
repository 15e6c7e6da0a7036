"""Plain (task, body, render) dicts for building envs from a composed config.

The tracking task needs two things the config only names: the clip-set entry to track
(`clip=`) and the mocap file it resolves against (`mocap_file=` or the search order of
hvc.mocap.source); both are filled in here, once, before any env is built.
"""
from __future__ import annotations

from typing import Any

from omegaconf import DictConfig, OmegaConf

from hvc.config import group_config


def _plain(node) -> Any:
    return OmegaConf.to_container(node, resolve=True)


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
        return _plain(cfg.task), body, render
    from hvc.mocap.clip_sets import select_entry
    from hvc.mocap.source import find_mocap_file

    entry = entry if entry is not None else select_entry(cfg.clips, cfg.clip)
    task["clip"] = entry.as_dict()
    if with_mocap:
        task["mocap_file"] = str(find_mocap_file(cfg.mocap_file, str(body.get("model_version", "2019"))))
    return task, body, render
