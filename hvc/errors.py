"""Errors a user can fix (a missing file or clip, a policy not trained yet, a library of
another version): `hvc-run` prints them as one line instead of a traceback."""
from __future__ import annotations


class HvcUserError(Exception):
    """Base of the errors reported as `hvc-run: error: <message>`."""


class ClipNotFoundError(HvcUserError, KeyError):
    """A clip id is not in the HDF5 file; the message names both (KeyError would quote it)."""

    def __str__(self) -> str:
        return str(self.args[0]) if self.args else ""


class ControllerUnavailable(HvcUserError, RuntimeError):
    """The controller's low-level policy does not exist yet (named in the message)."""


class LibraryVersionError(HvcUserError, RuntimeError):
    """An expert library written by an incompatible format version."""


class NonFiniteLoss(HvcUserError, FloatingPointError):
    """A loss or gradient became NaN or inf; raised before the optimiser steps, so the
    weights (and the checkpoint a run writes on its way out) are the last good ones."""


class BadInputFile(HvcUserError):
    """A file the user named (library, mocap file, run dir, checkpoint) is missing,
    truncated or of another kind; the message names the file and what is wrong with it."""


class RunDirInUse(HvcUserError):
    """Another hvc-run writes to this run dir; a second writer would double its metrics."""


class MissingInputFile(BadInputFile, FileNotFoundError):
    """A named file that does not exist (a FileNotFoundError too, for callers that fall back)."""
