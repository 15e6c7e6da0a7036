"""Which mocap HDF5 file a run uses, and what is in it.

Search order: an explicit `mocap_file=`; `$HVC_MOCAP_FILE`; dm_control's fitted CMU file
for the body's model version in `~/.dm_control/` or `$DM_CONTROL_DATA`; our conversion of
the offline clips (`outputs/mocap/cmu_<version>.h5`, made by `hvc-run stage=convert`,
or on first use from `../shared/mocap/cmu` when that folder exists, and extended when
clips are added to that folder).
"""
from __future__ import annotations

import fcntl
import logging
import os
import shutil
from pathlib import Path

import h5py

from hvc.errors import BadInputFile, MissingInputFile

log = logging.getLogger(__name__)

REPO_ROOT = Path(__file__).resolve().parents[2]
# The offline CMU clips: ../shared/mocap next to the checkout, or $HVC_SHARED_MOCAP.
SHARED_CLIPS = Path(os.environ.get("HVC_SHARED_MOCAP", REPO_ROOT.parent / "shared" / "mocap")) / "cmu"
DM_CONTROL_FILES = {"2019": "cmu_2019_08756c01.h5", "2020": "cmu_2020_dfe3e9e0.h5"}
MIRROR_ATTR = "hvc_shared_folder"  # stamped on our conversion of the shared clips: the folder it mirrors


def converted_file(model_version: str) -> Path:
    return REPO_ROOT / "outputs" / "mocap" / f"cmu_{model_version}.h5"


def find_mocap_file(explicit: str | None, model_version: str = "2019") -> Path:
    """The mocap file a run uses (the search order above); where no other file is found first,
    our conversion of the shared clips, made or extended on the way."""
    if explicit:
        return check_mocap_file(Path(explicit).expanduser(), f"mocap_file={explicit}")
    candidates = []
    if os.environ.get("HVC_MOCAP_FILE"):
        candidates.append(Path(os.environ["HVC_MOCAP_FILE"]).expanduser())
    for root in (os.environ.get("DM_CONTROL_DATA"), "~/.dm_control"):
        if root:
            candidates.append(Path(root).expanduser() / DM_CONTROL_FILES[str(model_version)])
    ours = converted_file(str(model_version))
    candidates.append(ours)
    for path in candidates:
        if path == ours and SHARED_CLIPS.is_dir():
            return update_conversion(SHARED_CLIPS, ours, str(model_version))
        if path.exists():
            return path
    raise FileNotFoundError(
        "no mocap file: searched " + ", ".join(str(c) for c in candidates)
        + "; convert clips with `hvc-run stage=convert source=<folder of ASF/AMC/BVH> out=<file.h5>` "
          "and pass mocap_file=<file.h5>")


def update_conversion(source: Path, out: Path, model_version: str) -> Path:
    """`out`, our conversion of the clips under `source`: made on first use (or again when
    unreadable), and extended when clips have been added to `source` since (only those are
    converted). It is built in a copy that then replaces `out` whole, under a lock, so jobs
    started together neither convert twice nor read a half-written file. A file that is not a
    conversion of `source` (`stage=convert` of another folder, or at another dt) is left as it
    is, and so is a usable one when the new clips cannot be converted (a warning says why)."""
    try:
        wanted = _clip_ids(source)  # the folder scanned once per call
        have = _mirrored(out, source, wanted)
        if have is None or (have and not wanted - have):
            return out  # nothing to do: no lock, so a read-only checkout works
        out.parent.mkdir(parents=True, exist_ok=True)
        with open(out.with_name(out.name + ".lock"), "w") as lock:
            fcntl.flock(lock, fcntl.LOCK_EX)
            have = _mirrored(out, source, wanted)  # another job may have extended it meanwhile
            if have is not None and (not have or wanted - have):
                _convert_into(source, out, have, model_version)
    except (OSError, ValueError) as error:  # a clip the converter cannot read, a folder we cannot write
        try:
            check_mocap_file(out)
        except BadInputFile:
            raise error from None  # nothing usable to fall back on
        log.warning("kept %s as it is; the clips added to %s could not be converted: %s", out, source, error)
    return out


def _convert_into(source: Path, out: Path, have: set[str], model_version: str) -> None:
    from hvc.mocap.convert import convert_folder

    partial = out.with_name(out.name + ".partial")
    if have:
        shutil.copyfile(out, partial)
    else:
        partial.unlink(missing_ok=True)
    log.info("converting the clips in %s that %s lacks", source, out)
    convert_folder(str(source), str(partial), walker_version=model_version, skip=have)
    with h5py.File(partial, "a") as f:
        f.attrs[MIRROR_ATTR] = str(source.resolve())
    os.replace(partial, out)


def _mirrored(out: Path, source: Path, wanted: set[str]) -> set[str] | None:
    """The clip ids of `out` when it is our conversion of `source` (empty: absent or
    unreadable, to be made); None when it is another file. Conversions made before files were
    stamped with their folder count as ours when their clips are among `wanted` (the folder's),
    at dt 0.03."""
    if not out.exists():
        return set()
    try:
        with h5py.File(out, "r") as f:
            ids, folder = set(f.keys()), f.attrs.get(MIRROR_ATTR)
            dts = {float(g.attrs.get("dt", 0.0)) for g in f.values()}
    except OSError as error:
        log.warning("%s is unreadable (%s); converting %s into it again", out, error, source)
        return set()
    if folder is not None:
        return ids if str(folder) == str(source.resolve()) else None
    return ids if ids <= wanted and dts <= {0.03} else None


def _clip_ids(source: Path) -> set[str]:
    from hvc.mocap.convert import clip_files, clip_id_from_path

    return {clip_id_from_path(p) for p in clip_files(source)}


def check_mocap_file(path: Path, name: str | None = None) -> Path:
    """`path` when it is an HDF5 file with clips; else BadInputFile in one line, not h5py's
    traceback (random bytes, a truncated copy, an empty file)."""
    name = name or f"mocap file {path}"
    if not path.exists():
        raise MissingInputFile(f"{name} does not exist")
    if not path.is_file():
        raise BadInputFile(f"{name} is a directory, not an HDF5 file")
    try:
        with h5py.File(path, "r") as f:
            clips = len(f.keys())
    except OSError as error:
        reason = str(error).split("(", 1)[-1].rstrip(")") if "(" in str(error) else str(error)
        raise BadInputFile(f"{name} is not a readable HDF5 file ({reason}): truncated, or another kind of file") \
            from None
    if not clips:
        raise BadInputFile(f"{name} holds no clips; `hvc-run stage=convert` writes a mocap file")
    return path


def clip_lengths(path: str | Path) -> dict[str, int]:
    """Clip id -> number of steps, from the file's attributes (no trajectory loading)."""
    with h5py.File(path, "r") as f:
        return {name: int(group.attrs["num_steps"]) for name, group in f.items() if "num_steps" in group.attrs}
