"""The expert library: all experts of a clip set in one file, loadable without pickle.

An `.npz` (numpy, `allow_pickle=False`) holding, per expert, the policy's weights and
observation normalisation, and the reference it tracks (pose, velocities, end effectors,
time input per step: the bank of start poses for the tasks' initialisation and the
material of the query controller's fragment keys); plus JSON metadata: format version,
clip entries, evaluation scores and provenance (commands, steps, code version).
A file from an incompatible format version fails to load with a clear message.
"""
from __future__ import annotations

import json
import shlex
import sys
import zipfile
import zlib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Sequence

import numpy as np

import hvc
from hvc.agents.mlp import NumpyPolicy
from hvc.errors import BadInputFile, ControllerUnavailable, LibraryVersionError, MissingInputFile
from hvc.mocap.reference import Reference
from hvc.provenance import code_version

LIBRARY_VERSION = 1
REFERENCE_FIELDS = ("joints", "joints_velocity", "position", "quaternion", "velocity", "angular_velocity",
                    "end_effectors", "phase")
SHIPPED_DIR = Path(__file__).resolve().parents[1] / "data"


def policy_observation(obs: dict) -> np.ndarray:
    """What a low-level expert sees (`Expert.act`'s input): proprioception then the time input."""
    return np.concatenate([obs["proprio"], obs["task"]])


@dataclass
class Expert:
    entry: dict[str, Any]
    policy: NumpyPolicy
    reference: Reference
    scores: dict[str, float] = field(default_factory=dict)

    def act(self, obs: np.ndarray) -> np.ndarray:
        return self.policy(obs)


@dataclass
class ExpertLibrary:
    experts: list[Expert]
    meta: dict[str, Any]
    # the switching policy's k behaviour references: its controller and evaluation need
    # them, and a shipped library must work without the mocap files
    behaviours: list[Reference] = field(default_factory=list)

    def __len__(self) -> int:
        return len(self.experts)

    @property
    def clip_ids(self) -> list[str]:
        return [e.entry["id"] for e in self.experts]

    def behaviour_experts(self) -> list[Expert]:
        """A switching library's policy as one expert per behaviour: the policy with that
        behaviour's 1-of-k code held (it sees proprioception, the phase, then the code), on the
        behaviour's clip and reference, so fragments and query drive one network trained on the
        switches between behaviours; a library of clip experts as it is."""
        if not self.behaviours:
            return self.experts
        policy, k = self.experts[0].policy, len(self.behaviours)
        return [Expert(entry, policy.with_fixed_inputs(np.eye(k, dtype=np.float32)[b]), reference, {})
                for b, (entry, reference) in enumerate(zip(self.meta["switching_entries"], self.behaviours))]

    def as_clip_experts(self) -> "ExpertLibrary":
        """This library as one of clip experts (behaviour_experts), for the fragments and query
        controllers; its provenance's env steps go with each behaviour."""
        if not self.behaviours:
            return self
        experts = self.behaviour_experts()
        meta = {k: v for k, v in self.meta.items() if k not in ("switching", "switching_entries")}
        steps = meta.get("provenance", {}).get("env_steps")
        if steps is not None:
            meta["provenance"] = {**meta["provenance"], "env_steps": list(steps) * len(experts)}
        return ExpertLibrary(experts, meta)

    def subset(self, keep: Sequence[int]) -> "ExpertLibrary":
        """The experts at `keep`, with their provenance env steps (a list by position) kept in step."""
        meta = dict(self.meta)
        steps = meta.get("provenance", {}).get("env_steps")
        if steps is not None:
            meta["provenance"] = {**meta["provenance"], "env_steps": [steps[i] for i in keep]}
        return ExpertLibrary([self.experts[i] for i in keep], meta, self.behaviours)

    def save(self, path: str | Path) -> Path:
        path = Path(path)
        steps = self.meta.get("provenance", {}).get("env_steps")
        if steps is not None and len(steps) != len(self.experts):  # they pair by position: a misreport
            raise ValueError(f"provenance env_steps has {len(steps)} entries for {len(self.experts)} experts; "
                             f"cut a library with ExpertLibrary.subset, which keeps them in step")
        arrays: dict[str, np.ndarray] = {}
        for i, e in enumerate(self.experts):
            for j, (w, b) in enumerate(zip(e.policy.weights, e.policy.biases)):
                arrays[f"e{i}/w{j}"], arrays[f"e{i}/b{j}"] = w, b
            arrays[f"e{i}/obs_mean"] = e.policy.mean_obs
            arrays[f"e{i}/obs_std"] = 1.0 / e.policy.inv_std
            for name in REFERENCE_FIELDS:
                arrays[f"e{i}/ref/{name}"] = np.asarray(getattr(e.reference, name), np.float32)
        for k, ref in enumerate(self.behaviours):
            for name in REFERENCE_FIELDS:
                arrays[f"b{k}/ref/{name}"] = np.asarray(getattr(ref, name), np.float32)
        meta = {**self.meta, "version": LIBRARY_VERSION,
                "behaviours": [{"id": r.clip_id, "dt": r.dt, "cyclic": r.cyclic} for r in self.behaviours],
                "experts": [{"entry": e.entry, "scores": e.scores, "layers": len(e.policy.weights),
                             "dt": e.reference.dt, "cyclic": e.reference.cyclic} for e in self.experts]}
        arrays["meta"] = np.array(json.dumps(meta))
        path.parent.mkdir(parents=True, exist_ok=True)
        np.savez_compressed(path, **arrays)
        return path

    @classmethod
    def load(cls, path: str | Path) -> "ExpertLibrary":
        """Raises BadInputFile or LibraryVersionError in one line for a file that is no library."""
        path = Path(path)
        data, meta = _open(path, f"expert library {path}")
        try:
            with data:
                experts = []
                for i, info in enumerate(meta["experts"]):
                    policy = NumpyPolicy([data[f"e{i}/w{j}"] for j in range(info["layers"])],
                                         [data[f"e{i}/b{j}"] for j in range(info["layers"])],
                                         data[f"e{i}/obs_mean"], data[f"e{i}/obs_std"])
                    ref = Reference(clip_id=info["entry"]["id"], dt=float(info["dt"]), cyclic=bool(info["cyclic"]),
                                    **{name: data[f"e{i}/ref/{name}"].astype(np.float64) for name in REFERENCE_FIELDS})
                    experts.append(Expert(info["entry"], policy, ref, info.get("scores", {})))
                behaviours = [Reference(clip_id=info["id"], dt=float(info["dt"]), cyclic=bool(info["cyclic"]),
                                        **{name: data[f"b{k}/ref/{name}"].astype(np.float64)
                                           for name in REFERENCE_FIELDS})
                              for k, info in enumerate(meta.get("behaviours", []))]
        except (zipfile.BadZipFile, zlib.error) as error:
            raise BadInputFile(f"expert library {path} is corrupt ({error})") from None
        except KeyError as error:
            raise BadInputFile(f"expert library {path} is incomplete (no entry {error})") from None
        return cls(experts, {k: v for k, v in meta.items() if k not in ("experts", "behaviours")}, behaviours)


def _open(path: Path, name: str):
    """(the open .npz, its metadata), once the file is known to be an expert library of this
    version; errors name the file as `name`. numpy's own errors would suggest loading
    pickles, which an expert library never holds."""
    if not path.is_file():
        raise MissingInputFile(f"{name} does not exist")
    try:
        data = np.load(path, allow_pickle=False)
    except (zipfile.BadZipFile, EOFError):
        raise BadInputFile(f"{name} is truncated or corrupt (not a complete .npz archive)") from None
    except ValueError:  # neither .npz nor .npy: numpy took it for a pickle
        raise BadInputFile(f"{name} is not an .npz archive") from None
    if not isinstance(data, np.lib.npyio.NpzFile):
        raise BadInputFile(f"{name} is a single .npy array, not an .npz expert library")
    try:
        return data, _meta(data, name)
    except BaseException:
        data.close()
        raise


def _meta(data, name: str) -> dict:
    if "meta" not in data.files:
        raise BadInputFile(f"{name} is an .npz archive without a 'meta' entry, so not an expert library "
                           f"(stage=lowlevel writes those: experts_<clips>.npz)")
    try:
        meta = json.loads(str(data["meta"]))
    except (zipfile.BadZipFile, zlib.error, ValueError) as error:
        raise BadInputFile(f"{name} has a corrupt 'meta' entry ({error})") from None
    version = meta.get("version") if isinstance(meta, dict) else None
    if version != LIBRARY_VERSION:
        raise LibraryVersionError(f"{name} has format version {version}; this hvc "
                                  f"({hvc.__version__}) reads version {LIBRARY_VERSION}: retrain with "
                                  f"`hvc-run stage=lowlevel` or use a matching hvc")
    return meta


def check_library_file(path: str | Path, name: str | None = None) -> None:
    """Everything ExpertLibrary.load would refuse, and every entry's checksum, without
    building the experts: for checking a user's file before any work. Errors name the file
    as `name` (e.g. the option that gave it)."""
    path = Path(path)
    name = name or f"expert library {path}"
    data, _ = _open(path, name)
    with data:
        try:
            bad = data.zip.testzip()
        except zlib.error:
            bad = "an entry"
    if bad:
        raise BadInputFile(f"{name} is corrupt ({bad} fails its checksum)")


def provenance(steps: Sequence[int], extra: dict[str, Any] | None = None) -> dict[str, Any]:
    return {"command": shlex.join(["hvc-run", *sys.argv[1:]]), "env_steps": list(steps),
            "code_version": code_version(), **(extra or {})}


def shipped_library(clip_set: str = "go_to_target") -> Path:
    """`hvc/data/experts_<set>.npz`, or one line naming the sets that ship one."""
    path = SHIPPED_DIR / f"experts_{clip_set}.npz"
    if not path.is_file():
        shipped = sorted(p.stem.removeprefix("experts_") for p in SHIPPED_DIR.glob("experts_*.npz"))
        raise ControllerUnavailable(f"no library ships for clips={clip_set}; shipped: {', '.join(shipped)}; train one with "
                                    f"`hvc-run stage=lowlevel clips={clip_set}` and pass its library file instead")
    return path
