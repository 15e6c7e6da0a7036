"""Builds the configured controller for an env (and the expert library it drives)."""
from __future__ import annotations

from pathlib import Path
from typing import Any, Mapping


from hvc.errors import ControllerUnavailable


def library_path(library: str | None, clip_set: str) -> Path:
    from hvc.lowlevel.library import shipped_library

    return Path(library) if library else shipped_library(clip_set)


def build_controller(controller: Mapping[str, Any], env, library: str | None = None, clip_set: str = "go_to_target"):
    name = controller["name"]
    if name == "end_to_end":
        from hvc.controllers.end_to_end import EndToEndController

        return EndToEndController(env.action_low, env.action_high)
    from hvc.lowlevel.library import ExpertLibrary

    if name in ("steerable", "switching"):
        try:
            lib = ExpertLibrary.load(library_path(library, name))
        except FileNotFoundError as error:
            raise ControllerUnavailable(
                f"controller={name} needs the {name} low-level policy (`hvc-run stage=lowlevel clips={name}`, "
                f"then library=<its experts_{name}.npz>): {error}") from None
        from hvc.controllers.structured import SteerableController, SwitchingController

        if name == "steerable":
            return SteerableController(lib.experts[0], controller.get("steering_range", (-1.5, 1.5)))
        return SwitchingController(lib.experts[0], _behaviours(lib), controller.get("hold_steps"))
    lib = ExpertLibrary.load(library_path(library, clip_set))
    if name == "fragments":
        from hvc.controllers.fragments import FragmentsController

        return FragmentsController(lib, int(controller["fragment_len"]))
    if name == "query":
        from hvc.controllers.query import QueryController

        return QueryController(lib, int(controller["fragment_len"]), int(controller["k_nearest"]))
    raise ValueError(f"controller={name!r}; allowed: steerable, switching, fragments, query, end_to_end")


def _behaviours(lib) -> list:
    """The switching policy's behaviour references: stored in the library, or (libraries made
    before they were) rebuilt from the entries it was trained on."""
    if lib.behaviours:
        return lib.behaviours
    from hvc.lowlevel.tracking import build_reference
    from hvc.mocap.source import find_mocap_file

    entries = lib.meta.get("switching_entries")
    if not entries:
        raise ControllerUnavailable("this switching library does not list its behaviours (switching_entries)")
    mocap_file = str(find_mocap_file(None, "2019"))
    return [build_reference(e, mocap_file) for e in entries]
