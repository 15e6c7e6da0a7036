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
