"""A replay buffer of fixed-length unrolls (the paper's actors write unrolls of length N).

Stored batch-major in preallocated numpy arrays (a ring); `sample` returns time-major
torch tensors. An unroll cut short by the end of an episode is padded and masked.
`state_dict` / `load_state_dict` let a resumed run keep its replay.
It lives beside the learner whose `Batch` it fills (svg0_retrace), below every trainer
that uses it (the low-level expert trainer, hvc.lowlevel.train).
"""
from __future__ import annotations

import numpy as np
import torch

from hvc.algorithms.svg0_retrace import Batch

_FIELDS = ("obs", "actions", "rewards", "discounts", "log_mu", "mask")


class UnrollReplay:
    def __init__(self, capacity: int, unroll: int, obs_size: int, action_size: int):
        self.capacity, self.unroll = int(capacity), int(unroll)
        self.obs = np.zeros((capacity, unroll + 1, obs_size), np.float32)
        self.actions = np.zeros((capacity, unroll, action_size), np.float32)
        self.rewards = np.zeros((capacity, unroll), np.float32)
        self.discounts = np.zeros((capacity, unroll), np.float32)
        self.log_mu = np.zeros((capacity, unroll), np.float32)
        self.mask = np.zeros((capacity, unroll), np.float32)
        self.position = 0
        self.size = 0

    def add(self, obs, actions, rewards, discounts, log_mu) -> None:
        """One unroll of k <= unroll steps: obs has k + 1 rows (the last is the next obs)."""
        k = len(actions)
        i = self.position
        self.obs[i, :k + 1] = obs
        self.obs[i, k + 1:] = obs[-1]
        self.actions[i, :k] = actions
        self.actions[i, k:] = 0
        for name, values in (("rewards", rewards), ("discounts", discounts), ("log_mu", log_mu)):
            arr = getattr(self, name)
            arr[i, :k] = values
            arr[i, k:] = 0
        self.mask[i, :k] = 1
        self.mask[i, k:] = 0
        self.position = (i + 1) % self.capacity
        self.size = min(self.size + 1, self.capacity)

    def sample(self, batch_size: int, rng: np.random.Generator) -> Batch:
        idx = rng.integers(0, self.size, batch_size)
        return Batch(**{name: torch.from_numpy(np.swapaxes(getattr(self, name)[idx], 0, 1).copy())
                        for name in _FIELDS})

    def state_dict(self) -> dict:
        return {"position": self.position, "size": self.size,
                **{name: torch.from_numpy(getattr(self, name)[:self.size].copy()) for name in _FIELDS}}

    def load_state_dict(self, state: dict) -> None:
        self.position, self.size = int(state["position"]), int(state["size"])
        for name in _FIELDS:
            getattr(self, name)[:self.size] = state[name].numpy()
