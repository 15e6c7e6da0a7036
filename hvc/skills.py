"""Skills: the low-level policies one job's controller drives, resolved once per job.

A fragments or query job needs the experts of *its own* clip set; a steerable or switching
job its own policy. Resolving them per job (not once per sweep, not once per env worker)
is what lets a sweep's arms differ in clip set. The order, first match wins:

1. the library named for the set: `libraries.<set>=<file.npz>`;
2. `library=<file.npz>` (one job's skills; refused in a sweep whose arms differ in skills);
   either one `shipped`: the set's shipped library, by name; a switching library given to
   fragments or query is played as one expert per behaviour;
3. the shipped library of the set (`hvc/data/experts_<set>.npz`);
4. fragments and query only: a library assembled from experts of other libraries (named ones
   first, then shipped ones) when every clip of the set has one: the x2 / x4 sets of
   Appendix B repeat the 4-behaviour set's clips, so they need no new training;
5. otherwise one line naming the set, its clips without an expert, and the command that
   trains them.
"""
from __future__ import annotations

import json
import logging
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path
from typing import Any, Iterable, Mapping, Sequence

import numpy as np
from omegaconf import DictConfig, OmegaConf

from hvc.errors import ControllerUnavailable

log = logging.getLogger(__name__)

# Shipped libraries of controllers with a policy of their own (`skills: own`), not experts of clips.
OWN_POLICY = ("steerable", "switching")
# Entry fields that identify an expert's skill; the behaviour label is the set's own name for it.
_SKILL_FIELDS = ("id", "start", "end", "cyclic", "steps", "steer")


@dataclass
class Skills:
    """What a controller of one job drives: its library, where it came from, and for the
    fragment controllers the fragments and their query keys, cut once."""

    controller: str
    clip_set: str
    library: Any  # hvc.lowlevel.library.ExpertLibrary
    source: str
    fragment_len: int | None = None
    assembled_from: dict[str, str] = field(default_factory=dict)  # clip -> library, when assembled

    @classmethod
    def from_library(cls, library, fragment_len: int | None = None, controller: str = "fragments") -> "Skills":
        """Skills of a library in hand (tests, benchmarks, analyses of one library file)."""
        return cls(controller, str(library.meta.get("clip_set", "")), library, "given", fragment_len)

    @cached_property
    def fragments(self) -> list:
        from hvc.mocap.clip_sets import ClipEntry, fragments

        if self.fragment_len is None:
            return []
        return fragments([ClipEntry(**e.entry) for e in self.library.experts], self.fragment_len)

    @cached_property
    def keys(self) -> np.ndarray:
        """Query keys of every fragment (Appendix A.4), raw (the controller normalises them)."""
        from hvc.mocap.clip_sets import fragment_keys

        return np.asarray([fragment_keys(self.library.experts[f.clip].reference, [f.start], f.length)[0]
                           for f in self.fragments], np.float32)

    def describe(self) -> dict[str, Any]:
        """What a run dir records of its skills (skills.json) and its log line says."""
        out = {"controller": self.controller, "clip_set": self.clip_set, "source": self.source,
               "experts": len(self.library.experts),
               "behaviours": [e.entry["behaviour"] for e in self.library.experts]}
        if self.fragment_len is not None:
            out.update(fragment_len=self.fragment_len, fragments=len(self.fragments))
        if self.assembled_from:
            out["assembled_from"] = self.assembled_from
        return out

    def summary_line(self) -> str:
        d = self.describe()
        counts = f" fragments={d['fragments']} (fragment_len={d['fragment_len']})" if "fragments" in d else ""
        return f"skills: controller={self.controller} clips={self.clip_set} experts={d['experts']}{counts} " \
               f"from {self.source}"

    def write(self, run_dir: Path) -> Path:
        path = Path(run_dir) / "skills.json"
        path.write_text(json.dumps(self.describe(), indent=2))
        return path


def skill_set(cfg: DictConfig) -> str | None:
    """The name the job's skills go by: the clip set, or the steerable/switching policy's
    own; None for a controller without skills (end to end)."""
    kind = cfg.controller.get("skills", "clip_set")
    if kind == "none":
        return None
    return str(cfg.controller.name) if kind == "own" else str(cfg.clips.name)


def named_library(cfg: DictConfig, set_name: str) -> str | None:
    """The library a user named for `set_name`: libraries.<set>, else library= ("shipped": the
    set's shipped one, so that `-m library=shipped,<file>` compares a new library with it)."""
    from hvc.lowlevel.library import shipped_library

    libraries = cfg.get("libraries") or {}
    named = libraries.get(set_name) or cfg.get("library") or None
    return str(shipped_library(set_name)) if named == "shipped" else named


# Sweep keys whose arms may run different skills.
SKILL_KEYS = ("clips", "task", "controller")


def check_sweep_library(argv: Sequence[str]) -> None:
    """Refuses one `library=` for a sweep whose arms differ in skills, before any job: it
    would serve every arm (the x1 / x2 / x4 arms would all run the x1 set). `library=shipped`
    names each arm's own set's library, so it passes."""
    from hvc.config import ConfigError

    if not {"-m", "--multirun"} & set(argv):
        return
    given = dict(a.split("=", 1) for a in argv if "=" in a and not a.startswith("-"))
    if given.get("library") in (None, "", "null", "shipped"):
        return
    swept = {k for k, v in given.items() if _is_sweep(v)} | set(_file_sweep_params(argv))
    varying = [k for k in SKILL_KEYS if k in swept]
    if varying:
        raise ConfigError(f"library={given['library']} would serve every arm of this sweep, whose arms differ in "
                          f"{', '.join(varying)}; name a library per clip set instead: libraries.<set>=<file> "
                          f"(e.g. libraries.go_to_target_x2=<file>), or leave it out to use the shipped or "
                          f"assembled skills of each set")


def _is_sweep(value: str) -> bool:
    return "," in value or value.startswith(("range(", "choice(", "glob("))


def _file_sweep_params(argv: Sequence[str]) -> dict:
    """hydra.sweeper.params of the primary config the command names (a sweeps/ file)."""
    import yaml

    def option(long: str, short: str) -> str | None:
        for i, a in enumerate(argv):
            if a in (long, short) and i + 1 < len(argv):
                return argv[i + 1]
            if a.startswith(f"{long}="):
                return a.split("=", 1)[1]
        return None

    config_dir, name = option("--config-dir", "-cd"), option("--config-name", "-cn")
    if not config_dir or not name:
        return {}
    path = Path(config_dir) / f"{name.removesuffix('.yaml')}.yaml"
    if not path.is_file():
        return {}
    data = yaml.safe_load(path.read_text()) or {}
    return ((data.get("hydra") or {}).get("sweeper") or {}).get("params") or {}


_CACHE: dict[str, Skills] = {}


def skills_for_job(cfg: DictConfig) -> Skills | None:
    """The job's skills, resolved on first use and kept for the process's later callers (the
    envs, the query learner, the recorder): one load per job. Keyed by what decides them, so
    the jobs of a sweep run in one process each get their own."""
    set_name = skill_set(cfg)
    if set_name is None:
        return None
    fragment_len = _fragment_len(cfg)
    libraries = cfg.get("libraries")  # absent from the saved config of a run older than the key
    key = json.dumps([str(cfg.controller.name), set_name, named_library(cfg, set_name),
                      OmegaConf.to_container(libraries, resolve=True) if libraries is not None else {}, fragment_len,
                      OmegaConf.to_container(cfg.clips, resolve=True)], sort_keys=True, default=str)
    if key not in _CACHE:
        _CACHE.clear()  # one job's skills at a time
        _CACHE[key] = resolve_skills(cfg)
        log.info(_CACHE[key].summary_line())
    return _CACHE[key]


def resolve_skills(cfg: DictConfig) -> Skills | None:
    """The order of the module docstring; raises ControllerUnavailable in one line."""
    from hvc.lowlevel.library import SHIPPED_DIR

    controller, set_name = str(cfg.controller.name), skill_set(cfg)
    if set_name is None:
        return None
    fragment_len = _fragment_len(cfg)
    named = named_library(cfg, set_name)
    own = cfg.controller.get("skills") == "own"
    if named:
        library = load_library(named)
        # a switching policy given to fragments or query: one expert per behaviour, its code held
        return Skills(controller, set_name, library if own else library.as_clip_experts(), str(named), fragment_len)
    shipped = SHIPPED_DIR / f"experts_{set_name}.npz"
    entries = None if own else _set_entries(cfg.clips)
    if shipped.is_file():
        library = load_library(shipped)
        if own or _holds_entries(library, entries):
            return Skills(controller, set_name, library, f"shipped {shipped.name}", fragment_len)
        log.info("the shipped %s was trained on other entries than clips=%s now lists; assembling the set's "
                 "experts instead", shipped.name, set_name)
    if own:
        raise ControllerUnavailable(
            f"controller={controller} needs the {controller} low-level policy and none is shipped: train it with "
            f"`hvc-run stage=lowlevel clips={controller}`, then pass libraries.{controller}=<run dir>/"
            f"experts_{controller}.npz")
    sources = _expert_sources(cfg)
    library, found = assemble(entries, sources)
    missing = [e for e, where in zip(entries, found) if where is None]
    if missing:
        names = ", ".join(f"{e.id} [{e.start}, {e.end}) ({e.behaviour})" for e in _unique(missing))
        searched = ", ".join(sources) or "none"
        raise ControllerUnavailable(
            f"clips={set_name} has no skills: no expert for {names} in the libraries searched ({searched}); "
            f"train them with `hvc-run stage=lowlevel clips={set_name} lowlevel.reuse=shipped`, then pass "
            f"libraries.{set_name}=<run dir>/experts_{set_name}.npz")
    assembled_from = {f"{e.behaviour} ({e.id})": where for e, where in zip(entries, found)}
    return Skills(controller, set_name, library,
                  f"assembled from {', '.join(sorted(set(found)))}", fragment_len, assembled_from)


def _set_entries(clips_cfg) -> list:
    """The set's entries, from an expanded copy of its config (a saved config may not be)."""
    from hvc.config import expand_clip_set
    from hvc.mocap.clip_sets import entries_of

    clips = OmegaConf.create(OmegaConf.to_container(clips_cfg, resolve=True))
    expand_clip_set(clips)
    return entries_of(clips)


def _holds_entries(library, entries) -> bool:
    """Whether a library's experts are the set's entries, in order: a `clips.entries=` override
    must not be served the experts the set shipped with."""
    return [skill_key(e.entry) for e in library.experts] == [skill_key(e.as_dict()) for e in entries]


def _fragment_len(cfg: DictConfig) -> int | None:
    """Controllers that drive a clip set's experts cut them into fragments of `fragment_len`."""
    return int(cfg.fragment_len) if cfg.controller.get("skills", "clip_set") == "clip_set" else None


def load_library(path: str | Path):
    """An expert library file, or the one a stage=lowlevel run dir assembled."""
    from hvc.lowlevel.library import ExpertLibrary

    path = Path(path)
    if path.is_dir():
        found = sorted(path.glob("experts_*.npz"))
        if len(found) != 1:
            raise ControllerUnavailable(f"library dir {path} holds {len(found)} expert libraries (experts_*.npz); "
                                        f"name the file")
        path = found[0]
    if not path.is_file():
        raise ControllerUnavailable(f"expert library {path} does not exist")
    return ExpertLibrary.load(path)


def _expert_sources(cfg: DictConfig) -> list[str]:
    """Libraries to assemble a set from: those the user named, then the shipped libraries of
    the sets it includes (their experts are the ones that set was trained with), then the
    other shipped ones; steerable and switching policies are not experts of clips."""
    from hvc.lowlevel.library import SHIPPED_DIR, shipped_library

    named = [str(shipped_library(s)) if p == "shipped" else str(p) for s, p in (cfg.get("libraries") or {}).items() if p]
    included = [SHIPPED_DIR / f"experts_{s}.npz" for s in _included_sets(cfg.clips)]
    ordered = named + [str(p) for p in included if p.is_file()] + [str(p) for p in shipped_clip_libraries()]
    return list(dict.fromkeys(ordered))


def shipped_clip_libraries(clips_cfg: Mapping[str, Any] | None = None) -> list[Path]:
    """The shipped libraries of clip experts (not the steerable and switching policies); with a clip
    set, its own and those of the sets it includes first: a skill several libraries hold is served
    by the library of the set it belongs to (forage's copies of the base experts may be older)."""
    from hvc.lowlevel.library import SHIPPED_DIR

    every = sorted(p for p in SHIPPED_DIR.glob("experts_*.npz") if p.stem.removeprefix("experts_") not in OWN_POLICY)
    if clips_cfg is None:
        return every
    first = [SHIPPED_DIR / f"experts_{s}.npz" for s in [clips_cfg.get("name"), *_included_sets(clips_cfg)]]
    return list(dict.fromkeys([p for p in first if p in every] + every))


def _included_sets(clips_cfg: Mapping[str, Any]) -> list[str]:
    """Every set the job's set includes (hvc.config.expand_clip_set lists them)."""
    return list(clips_cfg.get("included") or [])


def skill_key(entry: Mapping[str, Any]) -> tuple:
    """What makes two clip entries one skill: the clip, its range, looping and steering (not
    the behaviour's name, which each set gives its own)."""
    return tuple(entry.get(k) for k in _SKILL_FIELDS)


def assemble(entries: Sequence, sources: Iterable[str]):
    """(library, where each entry's expert came from or None): each entry gets the first
    expert of `sources` with the same clip, range and looping, relabelled with the set's
    behaviour name. The library is None when an entry has no expert."""
    from hvc.lowlevel.library import Expert, ExpertLibrary

    by_skill: dict[tuple, tuple[Any, str]] = {}
    for source in sources:
        library = load_library(source)
        for expert in library.experts:
            by_skill.setdefault(skill_key(expert.entry), (expert, Path(source).name))
    picked = [by_skill.get(skill_key(e.as_dict())) for e in entries]
    found = [None if p is None else p[1] for p in picked]
    if any(p is None for p in picked):
        return None, found
    experts = [Expert({**p[0].entry, "behaviour": e.behaviour}, p[0].policy, p[0].reference, p[0].scores)
               for e, p in zip(entries, picked)]
    return ExpertLibrary(experts, {"assembled_from": sorted(set(found))}), found


def _unique(entries: Sequence) -> list:
    seen, out = set(), []
    for e in entries:
        if skill_key(e.as_dict()) not in seen:
            seen.add(skill_key(e.as_dict()))
            out.append(e)
    return out
