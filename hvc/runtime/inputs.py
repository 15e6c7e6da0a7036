"""Every file a command names, checked before any work (before envs are built): a bad one
fails in one line naming the option, the file and what is wrong with it, instead of a
traceback from h5py, numpy or torch seconds or hours into the run."""
from __future__ import annotations

import zipfile
import zlib
from pathlib import Path
from typing import Iterator

from omegaconf import DictConfig, OmegaConf

from hvc.errors import BadInputFile, MissingInputFile

# Options that take an expert library (a .npz or a stage=lowlevel run dir); "shipped" names the shipped one.
LIBRARY_OPTIONS = ("library", "lowlevel.reuse", "lowlevel.warm_start")


def check_inputs(cfg: DictConfig, resumed: Path | None = None) -> None:
    """Raises BadInputFile (or LibraryVersionError) on the first bad file `cfg` names;
    `resumed` is the run dir a resume continues."""
    from hvc.mocap.source import check_mocap_file

    if cfg.get("mocap_file"):
        check_mocap_file(Path(str(cfg.mocap_file)).expanduser(), f"mocap_file={cfg.mocap_file}")
    for option, value in _library_options(cfg):
        check_library(option, Path(value).expanduser())
    if resumed is not None:
        check_run_dir(f"resume={resumed}", resumed)
    if cfg.get("from_run"):
        check_run_dir(f"from_run={cfg.from_run}", Path(str(cfg.from_run)))


def _library_options(cfg: DictConfig) -> Iterator[tuple[str, str]]:
    for option in LIBRARY_OPTIONS:
        value = OmegaConf.select(cfg, option)
        for item in (value if OmegaConf.is_list(value) else [value]):  # lowlevel.reuse takes a list too
            if item and str(item) != "shipped":
                yield option, str(item)
    for name, value in (cfg.get("libraries") or {}).items():
        if value and str(value) != "shipped":
            yield f"libraries.{name}", str(value)


def check_library(option: str, path: Path) -> None:
    """An expert library file, or a dir holding one or a stage=lowlevel run's checkpoints."""
    from hvc.lowlevel.library import check_library_file

    if not path.exists():
        raise MissingInputFile(f"{option}={path} does not exist")
    if path.is_file():
        check_library_file(path, f"{option}={path}")
        return
    libraries = sorted(path.glob("experts_*.npz"))
    if not libraries and not (path / "config_resolved.yaml").is_file():
        raise BadInputFile(f"{option}={path} is a directory without an expert library (experts_*.npz) "
                           f"and not a stage=lowlevel run dir")
    for library in libraries:
        check_library(option, library)
    _check_checkpoints(f"{option}={path}", path)


def check_run_dir(option: str, run_dir: Path) -> None:
    """A run dir to continue or play: it exists, is a run's, and its checkpoints are whole."""
    if not run_dir.exists():
        raise MissingInputFile(f"{option} does not exist")
    if not run_dir.is_dir():
        raise BadInputFile(f"{option} is a file; it takes a run dir")
    if not (run_dir / "config_resolved.yaml").is_file():
        raise BadInputFile(f"{option} is not a run dir (no config_resolved.yaml)")
    _check_checkpoints(option, run_dir)


def _check_checkpoints(option: str, run_dir: Path) -> None:
    for path in [run_dir / "checkpoint.pt", *sorted(run_dir.glob("experts/*/checkpoint.pt"))]:
        if path.is_file():
            check_checkpoint(path, option)


def check_checkpoint(path: Path, option: str) -> None:
    """torch.save writes a zip archive: a truncated one has no central directory, a corrupt
    one fails an entry's checksum; either is found without unpickling anything."""
    where = f"{option}: {path}"
    if not zipfile.is_zipfile(path):
        raise BadInputFile(f"{where} is truncated or corrupt (not a complete checkpoint archive); restore it, or "
                           f"delete it to start that run over")
    try:
        with zipfile.ZipFile(path) as archive:
            bad = archive.testzip()
    except (zipfile.BadZipFile, zlib.error, OSError) as error:
        bad = str(error)
    if bad:
        raise BadInputFile(f"{where} is corrupt ({bad} fails its check); restore it, or delete it to start "
                           f"that run over")
