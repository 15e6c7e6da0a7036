"""One replay buffer of fixed-length unrolls for both levels (the paper's actors write unrolls
of length N).

A ring of named fields in preallocated batch-major numpy arrays, declared once
(`Field`: per-unroll shape and dtype; `per_step` fields have the unroll's time axis first and
are sampled time-major, others, like the LSTM state at the unroll's start, stay batch-major).
`sample` returns torch tensors moved to a device once; `state_dict` / `load_state_dict` let a
resumed run keep its replay. The low level's SVG(0) + Retrace batches (`Batch`) come from
`pad_unroll` + `UnrollReplay`; the high level's unrolls are declared in hvc.runtime.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Mapping

import numpy as np
import torch


@dataclass(frozen=True)
class Field:
    shape: tuple[int, ...]     # one unroll's, time first if per_step
    dtype: type = np.float32
    per_step: bool = True


class UnrollReplay:
    def __init__(self, capacity: int, fields: Mapping[str, Field]):
        self.capacity = int(capacity)
        self.fields = dict(fields)
        self.arrays = {name: np.zeros((self.capacity, *f.shape), f.dtype) for name, f in self.fields.items()}
        self.position = 0
        self.size = 0

    @property
    def nbytes(self) -> int:
        return sum(a.nbytes for a in self.arrays.values())

    def add(self, **values) -> None:
        """One unroll: a value for every field."""
        missing = self.fields.keys() - values.keys()
        if missing:
            raise ValueError(f"unroll without fields {sorted(missing)}")
        i = self.position
        for name, value in values.items():
            self.arrays[name][i] = value
        self.position = (i + 1) % self.capacity
        self.size = min(self.size + 1, self.capacity)

    def sample(self, batch: int, rng: np.random.Generator, device: torch.device | str = "cpu") -> dict[str, torch.Tensor]:
        """`batch` unrolls drawn uniformly with replacement; per-step fields time-major."""
        idx = rng.integers(0, self.size, batch)
        out = {}
        for name, field in self.fields.items():
            rows = self.arrays[name][idx]
            out[name] = torch.from_numpy(np.swapaxes(rows, 0, 1).copy() if field.per_step else rows).to(device)
        return out

    def state_dict(self) -> dict:
        return {"position": self.position, "size": self.size,
                **{name: torch.from_numpy(a[:self.size].copy()) for name, a in self.arrays.items()}}

    def load_state_dict(self, state: dict) -> None:
        self.position, self.size = int(state["position"]), int(state["size"])
        for name, array in self.arrays.items():
            array[:self.size] = state[name].numpy()


def svg0_fields(unroll: int, obs_size: int, action_size: int) -> dict[str, Field]:
    """The low level's unrolls: what hvc.algorithms.svg0_retrace.Batch holds."""
    return {"obs": Field((unroll + 1, obs_size)), "actions": Field((unroll, action_size)),
            **{name: Field((unroll,)) for name in ("rewards", "discounts", "log_mu", "mask")}}


def pad_unroll(unroll: int, obs, actions, rewards, discounts, log_mu) -> dict[str, np.ndarray]:
    """An unroll of k <= `unroll` steps (an episode ended) padded to full length: obs (k + 1
    rows, the last the next obs) repeats its last row, the rest are zero, and mask marks the
    k real steps."""
    k = len(actions)
    obs = np.asarray(obs, np.float32)
    pad = unroll - k
    step = lambda x: np.concatenate([np.asarray(x, np.float32), np.zeros((pad, *np.shape(x)[1:]), np.float32)])  # noqa: E731
    return {"obs": np.concatenate([obs, np.repeat(obs[-1:], pad, 0)]), "actions": step(actions),
            "rewards": step(rewards), "discounts": step(discounts), "log_mu": step(log_mu),
            "mask": step(np.ones(k))}
