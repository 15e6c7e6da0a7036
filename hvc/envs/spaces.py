"""What an env's step takes: raw body actions, or a controller's high-level actions."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class ActionSpace:
    """A discrete choice among `n`, or a continuous vector of `size` within [low, high]."""

    discrete: bool
    n: int = 0
    size: int = 0
    low: float = -1.0
    high: float = 1.0

    def sample(self, rng: np.random.Generator):
        if self.discrete:
            return int(rng.integers(self.n))
        return rng.uniform(self.low, self.high, self.size).astype(np.float32)
