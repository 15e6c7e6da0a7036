"""Builds the configured controller for an env from the job's skills (hvc.skills): the class its
config's `_target_` names, so a new controller is one file plus one config file."""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Mapping

from hydra.utils import get_class

from hvc.controllers.base import ControlledEnv
from hvc.errors import ControllerUnavailable


@dataclass(frozen=True)
class Drive:
    """How an env is driven through the configured controller: what runtime hands each env
    worker (picklable: the controller's config and the job's skills), so that envs never build
    controllers themselves. `drive(env)` -> (ControlledEnv, None), or (None, the reason the
    controller cannot be built)."""

    controller: Mapping[str, Any]
    skills: Any = None

    @property
    def name(self) -> str:
        return self.controller["name"]

    def __call__(self, env):
        try:
            return ControlledEnv(env, build_controller(self.controller, env, self.skills)), None
        except (ControllerUnavailable, FileNotFoundError) as error:
            return None, str(error)


def build_controller(controller: Mapping[str, Any], env, skills=None):
    """The class the controller config's `_target_` names, built by its `from_config(config,
    env, skills)`. `skills` is the job's hvc.skills.Skills (None for a controller with
    `skills: none`), resolved once per job and handed to every env, so workers never load a
    library themselves."""
    name = controller.get("name", "?")
    if controller.get("skills", "clip_set") != "none" and skills is None:
        raise ControllerUnavailable(f"controller={name} needs skills; none were resolved for this job")
    if not controller.get("_target_"):
        raise ValueError(f"controller={name}: its config names no _target_ (the controller class)")
    return get_class(controller["_target_"]).from_config(controller, env, skills)
