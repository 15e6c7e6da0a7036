"""`kill` (SIGTERM) handled like Ctrl-C, so that a stopped run still writes its checkpoint.

Background jobs started from a non-interactive shell ignore SIGINT, which leaves SIGTERM
as the usual way to stop them; without this, Python would die without running `finally`.
"""
from __future__ import annotations


def raise_interrupt(signum, frame):
    raise KeyboardInterrupt
