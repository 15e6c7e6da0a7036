"""Vectorised envs: FastEnvs in worker processes (spawn start method), and optionally
some stepped by the main process itself while the workers step theirs.

Why the main process steps envs too: a step waits for the slowest env, and waking a
worker and shipping its result through a pipe costs more than a rolling ball's physics
step (docs/results/design_measurements). The main
process idles during that wait; stepping envs itself uses the wait, and leaves fewer
processes to wake.

Spawn, not fork: each worker imports mujoco and creates its GL context itself, which
is what EGL and OSMesa need. Workers ignore SIGINT so Ctrl-C reaches only the parent,
which then shuts them down; a worker that raises or dies surfaces as a WorkerError
naming the worker and the task instead of a hang.
"""
from __future__ import annotations

import multiprocessing as mp
import signal
import traceback
from typing import Any, Mapping

import numpy as np

from hvc.envs.spaces import ActionSpace

_POLL_SECONDS = 1.0


class WorkerError(RuntimeError):
    pass


class _EnvHost:
    """One env, driven through its controller when one is configured: what a worker process
    serves, or what the main process steps itself (VectorEnv's `in_process` envs). `drive`
    (hvc.controllers.factory.Drive, from runtime; None: raw body actions) builds the controller."""

    def __init__(self, task, body, render_settings, seed: int, drive):
        from hvc.envs.fast_env import FastEnv

        self.env = env = FastEnv.build(task, body, render_settings, seed=seed)
        self.driven, why_not = drive(env) if drive else (None, None)
        space = self.driven.action_space if self.driven else ActionSpace(
            discrete=False, size=env.action_size, low=float(env.action_low.min()), high=float(env.action_high.max()))
        self.spec = {"action_size": env.action_size, "action_low": env.action_low, "action_high": env.action_high,
                     "observation_sizes": env.observation_sizes, "action_space": space,
                     "controller": drive.name if self.driven else None, "why_not": why_not}

    def reset(self):
        return self.driven.reset() if self.driven else self.env.reset()

    def step(self, action):
        """(obs, reward, discount, done, info); a finished episode is reset at once and its
        return and length reported in info."""
        info = {}
        if self.driven:
            obs, reward, discount, done, step_info = self.driven.step(action if self.driven.needs_action else None)
            info["new_action"] = step_info["new_action"]
            info["hl_action"] = step_info["hl_action"]
        else:
            obs, reward, discount, done = self.env.step(action)
        if done:
            info.update(episode_return=self.env.episode_return, episode_length=self.env.episode_steps)
            obs = self.reset()
        return obs, reward, discount, done, info

    def close(self) -> None:
        self.env.close()


def _worker(conn, index: int, task, body, render_settings, seed: int, drive) -> None:
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        host = _EnvHost(task, body, render_settings, seed, drive)
        conn.send(("ready", host.spec))
        while True:
            command, payload = conn.recv()
            if command == "reset":
                conn.send(("ok", host.reset()))
            elif command == "step":
                conn.send(("ok", host.step(payload)))
            elif command == "crash":  # for tests: a worker failing mid-run
                raise RuntimeError(str(payload))
            elif command == "close":
                host.close()
                conn.send(("ok", None))
                return
    except (EOFError, KeyboardInterrupt, BrokenPipeError):
        return
    except Exception:  # noqa: BLE001 - forwarded to the parent with its traceback
        try:
            conn.send(("error", traceback.format_exc()))
        except (BrokenPipeError, OSError):
            pass


class BatchedEnvs:
    """What VectorEnv and the Ray backend share: stacking per-env results into batches and
    random actions from the action space step() takes (`action_space`, `num_envs` set by them)."""

    @staticmethod
    def _stack(observations: list[dict]) -> dict[str, np.ndarray]:
        return {k: np.stack([o[k] for o in observations]) for k in observations[0]}

    def _batch(self, results: list):
        """Per-env (obs, reward, discount, done, info) as stacked arrays and a list of infos."""
        obs, rewards, discounts, dones, infos = zip(*results)
        return (self._stack(list(obs)), np.asarray(rewards, np.float32), np.asarray(discounts, np.float32),
                np.asarray(dones, bool), list(infos))

    def random_actions(self, rng: np.random.Generator) -> list:
        """One random action per env from the action space step() takes."""
        return [self.action_space.sample(rng) for _ in range(self.num_envs)]


class VectorEnv(BatchedEnvs):
    """`num_envs` FastEnvs stepped together; auto-resets finished episodes.

    `step(actions)` returns stacked observations, rewards, discounts, dones and a list of
    per-env info dicts holding `episode_return`/`episode_length` when an episode ended.
    With a `drive` (hvc.controllers.factory.Drive: the controller config and the job's skills,
    resolved once and sent to each worker), each env is driven through its controller and the
    actions are high-level ones (used only when the controller asks: `new_action`). `skills`
    is the job's skills, for whoever acts on these envs (runtime sets it).

    The last `in_process` envs run in this process (after the workers have been sent their
    actions, so both overlap); the others, envs 0 .. num_envs - in_process - 1, in workers.
    """

    def __init__(self, task: Mapping[str, Any], body: Mapping[str, Any],
                 render_settings: Mapping[str, Any] | None, num_envs: int, seed: int = 0,
                 drive=None, in_process: int = 0):
        if not 0 <= in_process <= num_envs:
            raise ValueError(f"in_process={in_process} must be between 0 and num_envs={num_envs}")
        self.task_name = task["name"]
        self.num_envs = num_envs
        self.closed = False
        ctx = mp.get_context("spawn")
        self._conns, self._procs, self._hosts = [], [], []
        workers = num_envs - in_process
        plain = lambda d: None if d is None else dict(d)  # noqa: E731
        for i in range(workers):
            parent, child = ctx.Pipe()
            proc = ctx.Process(target=_worker, args=(child, i, dict(task), dict(body), plain(render_settings),
                                                      seed + i, drive),
                               daemon=True, name=f"hvc-env-{i}")
            proc.start()
            child.close()
            self._conns.append(parent)
            self._procs.append(proc)
        try:
            for i in range(workers, num_envs):
                self._hosts.append(_EnvHost(dict(task), dict(body), plain(render_settings), seed + i, drive))
        except BaseException:
            self.close()
            raise
        specs = [self._receive(i) for i in range(workers)] + [host.spec for host in self._hosts]
        self.action_size = specs[0]["action_size"]
        self.action_low, self.action_high = specs[0]["action_low"], specs[0]["action_high"]
        self.observation_sizes = specs[0]["observation_sizes"]
        self.action_space = specs[0]["action_space"]          # what step() takes
        self.controller = specs[0]["controller"]              # None: raw body actions
        self.why_no_controller = specs[0]["why_not"]
        self.skills = getattr(drive, "skills", None)

    def _send(self, index: int, message) -> None:
        try:
            self._conns[index].send(message)
        except OSError:  # broken pipe / reset: the worker is gone
            self._procs[index].join(timeout=1)
            code = self._procs[index].exitcode
            self.close()
            raise WorkerError(f"env worker {index} (task={self.task_name}) died with exit code {code}") from None

    def _receive(self, index: int):
        conn, proc = self._conns[index], self._procs[index]
        try:
            while not conn.poll(_POLL_SECONDS):
                if not proc.is_alive():
                    raise EOFError
            status, payload = conn.recv()
        except (EOFError, OSError):
            proc.join(timeout=1)
            self.close()
            raise WorkerError(f"env worker {index} (task={self.task_name}) died "
                              f"with exit code {proc.exitcode}") from None
        if status == "error":
            self.close()
            raise WorkerError(f"env worker {index} (task={self.task_name}) failed:\n{payload}")
        return payload

    def _in_process(self, command: str, actions=None) -> list:
        """`command` on every in-process env. A failure closes everything (the workers hold
        replies to the same command that no one will read) and names the env and task."""
        results = []
        try:
            for j, host in enumerate(self._hosts):
                results.append(host.reset() if command == "reset"
                               else host.step(np.asarray(actions[len(self._conns) + j])))
        except Exception as error:
            index = len(self._conns) + len(results)
            self.close()
            raise WorkerError(f"env {index} (task={self.task_name}, in the main process) failed: "
                              f"{type(error).__name__}: {error}") from error
        return results

    def reset(self) -> dict[str, np.ndarray]:
        for i in range(len(self._conns)):
            self._send(i, ("reset", None))
        here = self._in_process("reset")
        return self._stack([self._receive(i) for i in range(len(self._conns))] + here)

    def step(self, actions: np.ndarray):
        workers = len(self._conns)
        for i in range(workers):
            self._send(i, ("step", np.asarray(actions[i])))
        here = self._in_process("step", actions)
        return self._batch([self._receive(i) for i in range(workers)] + here)

    def close(self) -> None:
        if getattr(self, "closed", False):
            return
        self.closed = True
        for conn, proc in zip(self._conns, self._procs):
            if proc.is_alive():
                try:
                    conn.send(("close", None))
                except (BrokenPipeError, OSError):
                    pass
        for proc in self._procs:
            proc.join(timeout=5)
            if proc.is_alive():
                proc.terminate()
                proc.join(timeout=5)
        for conn in self._conns:
            conn.close()
        for host in self._hosts:
            host.close()

    def __enter__(self) -> "VectorEnv":
        return self

    def __exit__(self, *exc) -> None:
        self.close()
