"""Builds the configured controller for an env from the job's skills (hvc.skills)."""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Mapping

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
    """`skills` is the job's hvc.skills.Skills (None for end to end), resolved once per job
    and handed to every env, so workers never load a library themselves."""
    name = controller["name"]
    if name == "end_to_end":
        from hvc.controllers.end_to_end import EndToEndController

        return EndToEndController(env.action_low, env.action_high)
    if skills is None:
        raise ControllerUnavailable(f"controller={name} needs skills; none were resolved for this job")
    if name in ("steerable", "switching"):
        from hvc.controllers.steerable import SteerableController
        from hvc.controllers.switching import SwitchingController

        lib = skills.library
        if name == "steerable":
            return SteerableController(lib.experts[0], controller.get("steering_range", (-1.5, 1.5)))
        return SwitchingController(lib.experts[0], _behaviours(lib), controller.get("hold_steps"))
    if name == "fragments":
        from hvc.controllers.fragments import FragmentsController

        return FragmentsController(skills)
    if name == "query":
        from hvc.controllers.query import QueryController

        return QueryController(skills, int(controller["k_nearest"]))
    raise ValueError(f"controller={name!r}; allowed: steerable, switching, fragments, query, end_to_end")


def _behaviours(lib) -> list:
    """The switching policy's behaviour references: stored in the library, or (libraries made
    before they were) rebuilt from the entries it was trained on."""
    if lib.behaviours:
        return lib.behaviours
    from hvc.mocap.reference import build_reference
    from hvc.mocap.source import find_mocap_file

    entries = lib.meta.get("switching_entries")
    if not entries:
        raise ControllerUnavailable("this switching library does not list its behaviours (switching_entries)")
    mocap_file = str(find_mocap_file(None, "2019"))
    return [build_reference(e, mocap_file) for e in entries]
