"""`device=`: where the high-level agent and its learner run (`auto`: CUDA when torch sees it).

The agent acts on the same device as it learns: on 2 CPU cores a second copy for acting
would only compete for them, and on a GPU one copy avoids shipping weights every update.
Replay stays in host memory; each sampled batch moves to the device once per update.
Checkpoints hold CPU tensors' device-independent state, so a run trained on a GPU records
and resumes on a CPU.
"""
from __future__ import annotations

import re

import torch

from hvc.config import ConfigError

_DEVICE = re.compile(r"(auto|cpu|cuda|cuda:\d+)")


def torch_device(value: str) -> torch.device:
    """The device `value` names; ConfigError in one line for a bad name or a missing GPU."""
    value = str(value)
    if not _DEVICE.fullmatch(value):
        raise ConfigError(f"device={value} is not a device; allowed: auto, cpu, cuda, cuda:N")
    if value == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if value.startswith("cuda"):
        if not torch.cuda.is_available():
            build = "a CPU-only build" if torch.version.cuda is None else f"built for CUDA {torch.version.cuda}"
            raise ConfigError(f"device={value}: torch {torch.__version__} ({build}) sees no CUDA device; "
                              f"allowed here: auto, cpu")
        index, count = int(value.partition(":")[2] or 0), torch.cuda.device_count()
        if index >= count:
            raise ConfigError(f"device={value}: this machine has {count} CUDA device(s); allowed: cuda:0 to "
                              f"cuda:{count - 1}")
    return torch.device(value)


def resolve_device(cfg) -> None:
    """`cfg.device` as the device it resolves to (auto: cuda or cpu), so run dirs record it."""
    cfg.device = str(torch_device(cfg.device))
