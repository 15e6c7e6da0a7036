"""Query-based selection (Appendix A.4): a continuous query in fragment-key space.

Keys are features of each fragment's nominal start and end state
(hvc.mocap.clip_sets.fragment_keys). The controller finds the k keys nearest a query;
the learner scores them with Q and chooses by Boltzmann exploration, then the chosen
fragment runs exactly as in the fragments controller.
"""
from __future__ import annotations

import numpy as np

from hvc.controllers.base import ActionSpace
from hvc.controllers.fragments import FragmentsController


class QueryController(FragmentsController):
    def __init__(self, skills, k_nearest: int):
        super().__init__(skills)
        raw = skills.keys
        self.key_mean, self.key_std = raw.mean(0), raw.std(0) + 1e-6
        self.keys = (raw - self.key_mean) / self.key_std  # queries live in this normalised space
        self.k = min(int(k_nearest), len(self.keys))
        self.selection_space = self.action_space
        self.action_space = ActionSpace(discrete=False, size=self.keys.shape[1], low=-3.0, high=3.0)

    @classmethod
    def from_config(cls, config, env, skills) -> "QueryController":
        return cls(skills, int(config["k_nearest"]))

    def nearest(self, query: np.ndarray) -> np.ndarray:
        """Indices of the k fragments whose keys are nearest the query (Euclidean)."""
        d = np.sum((self.keys - np.asarray(query, np.float32)) ** 2, axis=1)
        return np.argpartition(d, self.k - 1)[:self.k] if self.k < len(d) else np.arange(len(d))

    def set_action(self, action) -> None:
        """A query (continuous) selects its nearest fragment; an index selects directly."""
        if np.ndim(action) == 0:
            super().set_action(int(action))
            return
        candidates = self.nearest(action)
        d = np.sum((self.keys[candidates] - action) ** 2, axis=1)
        super().set_action(int(candidates[np.argmin(d)]))
