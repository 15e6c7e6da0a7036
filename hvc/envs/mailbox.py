"""A worker's mailbox in shared memory: how VectorEnv and an env worker process exchange
commands and results step after step.

Why not a pipe: on a virtual machine, waking a process that sleeps in `recv` costs more than a
humanoid step's share of the second core (docs/results/vector_env). Here each side waits by
spinning on a semaphore's non-blocking acquire (yielding the core between tries) for a few
milliseconds, which the other side's answer beats while acting, and only then blocks on it, so
a worker idling through the learner's updates does not burn its core. The semaphores also
order the memory: what one side wrote before `release` is what the other reads after
`acquire`, on any CPU.

Arrays travel in fixed slots (actions to the worker, observations back), not pickled; the
rest of a message (the command, reward, info, an error's traceback) is pickled into a byte
area. Arrays that do not fit their slots' shapes and dtypes are pickled with the rest, so a
wrong layout costs speed, never correctness.
"""
from __future__ import annotations

import os
import pickle
import time
from multiprocessing import shared_memory
from typing import Any, Callable

import numpy as np

SPIN_SECONDS = 0.005  # longer than the policy's forward between two steps, so acting never sleeps
MESSAGE_BYTES = 1 << 18
_ALIGN = 64

Layout = dict[str, tuple[tuple[int, ...], str]]  # slot name: (shape, dtype)


def observation_layout(observation_sizes: dict[str, Any]) -> Layout:
    """Slots for a FastEnv's observations: float32 vectors, and a uint8 image of (h, w, 3)."""
    return {k: ((int(v),), "float32") if np.isscalar(v) else (tuple(int(d) for d in v), "uint8")
            for k, v in observation_sizes.items()}


def action_layout(action_space) -> Layout:
    """The slot for one env's action as VectorEnv hands it over: an int64 index or float32s."""
    return {"action": ((), "int64") if action_space.discrete else ((int(action_space.size),), "float32")}


class _Direction:
    """One way through the block: a message length, a byte area and the array slots."""

    def __init__(self, buf, offset: int, layout: Layout):
        self.length = np.ndarray((1,), np.int64, buf, offset)
        offset += _ALIGN
        self.area = buf[offset:offset + MESSAGE_BYTES]
        offset += MESSAGE_BYTES
        self.slots = {}
        for key, (shape, dtype) in layout.items():
            self.slots[key] = np.ndarray(shape, dtype, buf, offset)
            offset += _aligned(self.slots[key].nbytes)
        self.end = offset

    @staticmethod
    def size(layout: Layout) -> int:
        return _ALIGN + MESSAGE_BYTES + sum(_aligned(int(np.prod(shape)) * np.dtype(dtype).itemsize)
                                            for shape, dtype in layout.values())

    def write(self, head: str, payload: Any, arrays: dict[str, np.ndarray] | None) -> None:
        in_slots = arrays is not None and arrays.keys() == self.slots.keys() and all(
            np.shape(v) == self.slots[k].shape and np.asarray(v).dtype == self.slots[k].dtype
            for k, v in arrays.items())
        if in_slots:
            for key, slot in self.slots.items():
                slot[...] = arrays[key]
        data = pickle.dumps((head, payload, None if in_slots else arrays, in_slots), pickle.HIGHEST_PROTOCOL)
        if len(data) > len(self.area):
            raise ValueError(f"a message of {len(data)} bytes exceeds the mailbox's {len(self.area)}")
        self.area[:len(data)] = data
        self.length[0] = len(data)

    def read(self) -> tuple[str, Any, dict[str, np.ndarray] | None]:
        head, payload, arrays, in_slots = pickle.loads(self.area[:int(self.length[0])])
        if in_slots:
            arrays = {k: slot.copy() for k, slot in self.slots.items()}
        return head, payload, arrays


class Mailbox:
    """Commands (with `command_layout`'s arrays) to the worker, replies (with `reply_layout`'s)
    back, in one shared-memory block. The parent creates it and unlinks it on `close`; the
    worker attaches by `name`. `semaphores` are (command posted, reply posted), made by the
    parent's multiprocessing context and passed to the worker when it starts."""

    def __init__(self, command_layout: Layout, reply_layout: Layout, semaphores, name: str | None = None):
        self.command_posted, self.reply_posted = semaphores
        self._owner = name is None
        size = _Direction.size(command_layout) + _Direction.size(reply_layout)
        self.shm = shared_memory.SharedMemory(name=name, create=self._owner, size=size if self._owner else 0)
        self._command = _Direction(self.shm.buf, 0, command_layout)
        self._reply = _Direction(self.shm.buf, self._command.end, reply_layout)

    @property
    def name(self) -> str:
        return self.shm.name

    # parent side
    def post(self, command: str, payload: Any = None, arrays: dict[str, np.ndarray] | None = None) -> None:
        self._command.write(command, payload, arrays)
        self.command_posted.release()

    def wait_reply(self, alive: Callable[[], bool], poll_seconds: float):
        """(status, payload, arrays) of the worker's reply; EOFError if `alive()` turns false first."""
        _wait(self.reply_posted, alive, poll_seconds)
        return self._reply.read()

    # worker side
    def wait_command(self, parent_alive: Callable[[], bool], poll_seconds: float):
        """(command, payload, arrays); EOFError once `parent_alive()` turns false."""
        _wait(self.command_posted, parent_alive, poll_seconds)
        return self._command.read()

    def reply(self, status: str, payload: Any = None, arrays: dict[str, np.ndarray] | None = None) -> None:
        self._reply.write(status, payload, arrays)
        self.reply_posted.release()

    def close(self) -> None:
        self._command = self._reply = None  # views of the buffer must go before it closes
        self.shm.close()
        if self._owner:
            self.shm.unlink()


def _aligned(n: int) -> int:
    return -(-n // _ALIGN) * _ALIGN


def _wait(semaphore, alive: Callable[[], bool], poll_seconds: float) -> None:
    """Spin on `semaphore` for SPIN_SECONDS, then block on it `poll_seconds` at a time,
    raising EOFError when the peer is found dead between tries."""
    deadline = time.perf_counter() + SPIN_SECONDS
    while time.perf_counter() < deadline:
        if semaphore.acquire(False):
            return
        os.sched_yield()  # a busy machine: the peer may be waiting for this core
    while not semaphore.acquire(True, poll_seconds):
        if not alive():
            raise EOFError
