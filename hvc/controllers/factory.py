"""Builds the configured controller for an env (and the expert library it drives)."""
from __future__ import annotations

from pathlib import Path
from typing import Any, Mapping


class ControllerUnavailable(RuntimeError):
    """The controller's low-level policy does not exist yet (named in the message)."""


def library_path(library: str | None, clip_set: str) -> Path:
    from hvc.lowlevel.library import shipped_library

    return Path(library) if library else shipped_library(clip_set)


def build_controller(controller: Mapping[str, Any], env, library: str | None = None, clip_set: str = "go_to_target"):
    name = controller["name"]
    if name == "end_to_end":
        from hvc.controllers.end_to_end import EndToEndController

        return EndToEndController(env.action_low, env.action_high)
    if name in ("steerable", "switching"):
        raise ControllerUnavailable(
            f"controller={name} needs the {name} low-level policy (one policy trained on "
            f"{'a run cycle with random turning rates' if name == 'steerable' else 'a Markov chain over behaviours'}); "
            f"it is not trained or shipped yet; allowed today: fragments, query, end_to_end")
    from hvc.lowlevel.library import ExpertLibrary

    lib = ExpertLibrary.load(library_path(library, clip_set))
    if name == "fragments":
        from hvc.controllers.fragments import FragmentsController

        return FragmentsController(lib, int(controller["fragment_len"]))
    if name == "query":
        from hvc.controllers.query import QueryController

        return QueryController(lib, int(controller["fragment_len"]), int(controller["k_nearest"]))
    raise ValueError(f"controller={name!r}; allowed: steerable, switching, fragments, query, end_to_end")
