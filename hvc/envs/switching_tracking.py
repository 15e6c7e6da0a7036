"""Tracking for the switching policy (Sec. 2.2, Fig. 2B): one policy, k behaviours.

Each episode a Markov walk over the clip set's transition graph chains the behaviours'
references, cut where poses match best (hvc.mocap.switching); the policy sees the phase
and a 1-of-k code of the behaviour being tracked, which the high level later chooses.
With `reanchor` (the default) each behaviour of the walk starts from the heading and place
the body has reached (TrackingLogic.anchor), as the high level will switch from wherever
the body is.
"""
from __future__ import annotations

import numpy as np

from hvc.envs.tracking import TrackingLogic
from hvc.mocap.reference import build_reference
from hvc.mocap.switching import MAX_ACCEL, markov_reference


def switching_clip(entries, spec, behaviours=None) -> dict:
    """The tracking task's `clip` for switching walks: the behaviours' clip entries (dicts or
    ClipEntry) and the walk's spec (graph, steps, ...), with the behaviours' references when
    they are at hand (a library's); otherwise they are built from the task's mocap file."""
    clip = {"switching": True, "entries": [e if isinstance(e, dict) else e.as_dict() for e in entries], **spec}
    if behaviours:
        clip["behaviours"] = behaviours
    return clip


class SwitchingTrackingLogic(TrackingLogic):
    reference_per_episode = True
    def __init__(self, cfg, env):
        spec = cfg["clip"]  # {"switching": True, "entries": [...], "graph": {...}, "steps": n}
        self.entries = spec["entries"]  # the behaviours' clip entries (names in the evaluation)
        # the behaviours' references: given (from a library), or built from the mocap file
        self.behaviours = spec.get("behaviours") or [
            build_reference(e, cfg["mocap_file"], int(cfg.get("cycle_repeats", 4)), int(cfg.get("cycle_blend", 4)))
            for e in spec["entries"]]
        self.graph = {int(k): [int(v) for v in vs] for k, vs in spec["graph"].items()}
        self.steps = int(spec.get("steps") or 300)
        self.max_accel = float(spec.get("max_accel", MAX_ACCEL))
        self.observation_size = 1 + len(self.behaviours)
        self.labels = np.zeros(self.behaviours[0].num_steps, np.int64)
        super().__init__(cfg, env, reference=self.behaviours[0])

    def reset(self, model, data, rng):
        self.reference, self.labels = markov_reference(self.behaviours, self.graph, self.steps, rng,
                                                           max_accel=self.max_accel)
        if self.reanchor:  # each behaviour starts from where the body faces (TrackingLogic.anchor)
            self.anchors = frozenset((np.flatnonzero(np.diff(self.labels)) + 1).tolist())
        super().reset(model, data, rng)

    def observation(self, model, data):
        code = np.zeros(len(self.behaviours), np.float32)
        code[self.labels[self.t]] = 1.0
        return np.concatenate([[np.float32(self.reference.phase[self.t])], code]).astype(np.float32)
