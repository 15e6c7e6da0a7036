"""A stopped (or running) run packed to continue on another machine: its dir as one .tar.gz,
small enough to commit. Replay buffers are left out of the checkpoints, as the high-level
learner's already are: a resumed run refills its replay before it learns again, and the
expert checkpoints' replay is most of their size. Everything else is kept as it is.

    python -m hvc.io.pack <run dir> <out.tar.gz>
    tar xzf <out.tar.gz> -C <parent dir>  &&  hvc-run resume=<parent dir>/<run name>

Packing a run still writing is safe: checkpoints are replaced atomically, and a resume drops
the metrics rows logged after its checkpoint (hvc.io.metrics.continue_metrics).
"""
from __future__ import annotations

import argparse
import io
import os
import tarfile
from pathlib import Path

import torch

SKIPPED_SUFFIXES = (".lock", ".tmp")  # another process's lock; a checkpoint being written


def pack_run(run_dir: Path, out: Path) -> dict[str, int]:
    """Writes `out`; returns how many checkpoints lost their replay and the bytes packed."""
    run_dir, out = Path(run_dir).resolve(), Path(out)
    if not run_dir.is_dir():
        raise FileNotFoundError(f"run dir {run_dir} does not exist")
    tmp = out.with_name(out.name + ".tmp")  # a failed pack never replaces a good one
    try:
        stripped = _write(run_dir, tmp)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    os.replace(tmp, out)
    return {"checkpoints_without_replay": stripped, "bytes": out.stat().st_size}


def _write(run_dir: Path, out: Path) -> int:
    """The tar of `run_dir`, its checkpoints without replay; how many had one."""
    stripped = 0
    with tarfile.open(out, "w:gz") as tar:
        for path in sorted(run_dir.rglob("*")):
            if path.is_dir() or path.name.endswith(SKIPPED_SUFFIXES):
                continue
            name = str(Path(run_dir.name) / path.relative_to(run_dir))
            if path.name == "checkpoint.pt":
                state = torch.load(path, map_location="cpu", weights_only=True)
                if state.pop("replay", None) is not None:
                    buffer = io.BytesIO()
                    torch.save(state, buffer)
                    info = tarfile.TarInfo(name)
                    info.size, info.mtime = buffer.tell(), int(path.stat().st_mtime)
                    buffer.seek(0)
                    tar.addfile(info, buffer)
                    stripped += 1
                    continue
            tar.add(path, name, recursive=False)
    return stripped


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("run_dir", type=Path)
    parser.add_argument("out", type=Path, help="the .tar.gz to write")
    args = parser.parse_args(argv)
    done = pack_run(args.run_dir, args.out)
    print(f"packed {args.run_dir} into {args.out}: {done['bytes'] / 2 ** 20:.1f} MiB, "
          f"{done['checkpoints_without_replay']} checkpoints without their replay (it refills on resume)")


if __name__ == "__main__":
    main()
