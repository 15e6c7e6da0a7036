"""Clip sets (Table A.2, Appendix B) and their control fragments.

A set is a list of entries (`conf/clips/*.yaml`): CMU id, step range at the control
timestep, behaviour label, and whether the behaviour is a gait cycle to loop. Entries
resolve against whichever mocap file is configured (dm_control's fitted file or our
converted one). A clip of n steps cut with fragment length T gives ceil(n / T)
fragments, fragment j starting at time index j * T.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Iterable, Mapping, Sequence

import numpy as np


@dataclass(frozen=True)
class ClipEntry:
    id: str
    behaviour: str
    start: int = 0
    end: int | None = None       # exclusive; None: to the clip's end
    cyclic: bool = False
    steps: int | None = None     # cyclic entries: length of the looped reference
    steer: bool = False          # cyclic entries: track it steered at random turning rates (steerable policy)

    @property
    def num_steps(self) -> int:
        if self.cyclic and self.steps is not None:
            return int(self.steps)
        if self.end is None:
            raise ValueError(f"clip entry {self.id} has no end; resolve it against a mocap file first")
        return int(self.end) - int(self.start)

    def as_dict(self) -> dict[str, Any]:
        return dict(id=self.id, behaviour=self.behaviour, start=self.start, end=self.end, cyclic=self.cyclic,
                    steps=self.steps, steer=self.steer)


@dataclass(frozen=True)
class Fragment:
    clip: int        # index of the entry in its set
    start: int       # time index within the entry's reference
    length: int      # control steps (the last fragment of a clip may be shorter)


def entries_of(clips_cfg: Mapping[str, Any]) -> list[ClipEntry]:
    """The set's entries, its includes already expanded (hvc.config.expand_clip_set, which
    composition applies)."""
    if clips_cfg.get("include"):
        raise ValueError(f"clip set {clips_cfg.get('name')!r} still lists include={list(clips_cfg['include'])}: "
                         f"expand it first (hvc.config.expand_clip_set)")
    fields = set(ClipEntry.__dataclass_fields__)
    out = []
    for raw in clips_cfg.get("entries") or []:
        unknown = set(raw) - fields
        if unknown:
            raise ValueError(f"clip set {clips_cfg.get('name')!r}: unknown entry keys {sorted(unknown)}; "
                             f"allowed: {', '.join(sorted(fields))}")
        out.append(ClipEntry(**raw))
    return out


def resolve(entries: Sequence[ClipEntry], mocap_file: str) -> list[ClipEntry]:
    """Checks every id exists in `mocap_file` and fills open-ended ranges from its lengths."""
    from hvc.mocap.clips import ClipNotFoundError
    from hvc.mocap.source import clip_lengths

    lengths = clip_lengths(mocap_file)
    resolved = []
    for e in entries:
        if e.id not in lengths:
            raise ClipNotFoundError(f"clip {e.id} ({e.behaviour}) is not in {mocap_file}; it has {len(lengths)} clips"
                           + (f", e.g. {', '.join(sorted(lengths)[:5])}" if lengths else ""))
        end = lengths[e.id] if e.end is None else int(e.end)
        if not 0 <= e.start < end <= lengths[e.id]:
            raise ValueError(f"clip {e.id}: steps [{e.start}, {end}) outside its {lengths[e.id]} steps")
        resolved.append(ClipEntry(e.id, e.behaviour, int(e.start), end, e.cyclic, e.steps, e.steer))
    return resolved


def fragments(entries: Iterable[ClipEntry], fragment_len: int) -> list[Fragment]:
    if fragment_len < 1:
        raise ValueError(f"fragment_len={fragment_len} must be a positive integer")
    out = []
    for c, e in enumerate(entries):
        n = e.num_steps
        for j in range(math.ceil(n / fragment_len)):
            out.append(Fragment(c, j * fragment_len, min(fragment_len, n - j * fragment_len)))
    return out


def select_entry(clips_cfg: Mapping[str, Any], clip: str | None) -> ClipEntry:
    """The entry a tracking or playback run uses: `clip` names an entry of the set by
    CMU id or behaviour; any other CMU id means that whole clip; None: the first entry."""
    entries = entries_of(clips_cfg)
    if clip is None:
        if not entries:
            raise ValueError(f"clip set {clips_cfg.get('name')!r} is empty; pass clip=<CMU id>")
        return entries[0]
    for e in entries:
        if clip in (e.id, e.behaviour):
            return e
    return ClipEntry(id=str(clip), behaviour="clip")


def fragment_keys(reference, starts: Sequence[int], length: int) -> np.ndarray:
    """Query-controller keys (Appendix A.4): features of each fragment's nominal start and
    end state — root velocity and gravity direction in the root frame, and the egocentric
    end-effector vectors — concatenated, one row per fragment."""
    def state(t: int) -> np.ndarray:
        q = reference.quaternion[t]
        w, x, y, z = q
        rot = np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])
        return np.concatenate([reference.velocity[t] @ rot, rot[2], reference.end_effectors[t].ravel()])
    last = reference.num_steps - 1
    return np.stack([np.concatenate([state(min(s, last)), state(min(s + length, last))]) for s in starts])
