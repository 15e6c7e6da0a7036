"""Files a run must never leave half-written (checkpoints, a cut metrics.csv): written to a
temp file beside the target and renamed over it, so a kill at any moment leaves the old file
or the new one. A full disk ends the run with one line and keeps the old file."""
from __future__ import annotations

import errno
import io
import os
from pathlib import Path
from typing import Any

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
