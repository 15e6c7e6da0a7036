"""Files a run must never leave half-written (checkpoints, a cut metrics.csv): written to a
temp file beside the target and renamed over it, so a kill at any moment leaves the old file
or the new one. A full disk ends the run with one line and keeps the old file."""
from __future__ import annotations

import errno
import io
import json
import os
from pathlib import Path
from typing import Any, Mapping

import numpy as np
import torch

from hvc.errors import HvcUserError

NO_SPACE = (errno.ENOSPC, errno.EDQUOT)


class DiskFull(HvcUserError):
    """No space left (or over quota) where a run writes; what was there before is kept."""


def write_atomically(path: Path, data: bytes | memoryview) -> None:
    """Replaces `path` with `data`. The temp file is synced before the rename, so a crash of the
    machine does not leave an empty file in place of a good one; on any failure it is removed."""
    path = Path(path)
    tmp = path.with_name(path.name + ".tmp")
    try:
        with open(tmp, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException as error:
        tmp.unlink(missing_ok=True)
        if isinstance(error, OSError) and error.errno in NO_SPACE:
            kept = "the previous one is kept" if path.exists() else "there is no earlier one"
            raise DiskFull(f"no space left on {path.parent}: {path.name} not written; {kept}") from None
        raise


def save_checkpoint(state: dict[str, Any], path: Path) -> None:
    """torch.save of `state`, written atomically. It is serialised in memory first: torch's own
    file writer reports a full disk as "unexpected pos" and leaves its partial file behind."""
    buffer = io.BytesIO()
    torch.save(state, buffer)
    write_atomically(path, buffer.getbuffer())


def random_states(generators: Mapping[str, np.random.Generator], device: torch.device | None = None) -> dict:
    """Every random stream a run draws from, for its checkpoint: numpy generators by name (as
    JSON), torch's CPU stream and, for a run on CUDA, the device's."""
    out: dict[str, Any] = {name: json.dumps(g.bit_generator.state) for name, g in generators.items()}
    out["torch_rng"] = torch.get_rng_state()
    if device is not None and torch.device(device).type == "cuda":
        out["cuda_rng"] = torch.cuda.get_rng_state(device)
    return out


def restore_random_states(state: Mapping[str, Any], generators: Mapping[str, np.random.Generator],
                          device: torch.device | None = None) -> None:
    """Undoes random_states: a resumed run draws what it would have drawn had it not stopped."""
    for name, g in generators.items():
        g.bit_generator.state = json.loads(state[name])
    torch.set_rng_state(state["torch_rng"])
    if device is not None and torch.device(device).type == "cuda" and "cuda_rng" in state:
        torch.cuda.set_rng_state(state["cuda_rng"], device)
