"""Vectorised envs: FastEnvs in worker processes (spawn start method), and optionally
some stepped by the main process itself while the workers step theirs.

Why the main process steps envs too: a step waits for the slowest env, and waking a
worker and shipping its result through a pipe costs more than a rolling ball's physics
step (docs/results/design_measurements). The main
process idles during that wait; stepping envs itself uses the wait, and leaves fewer
processes to wake.

After a start-up handshake on a pipe, commands and results go through each worker's
shared-memory mailbox (hvc.envs.mailbox), whose waits spin before they sleep: a pipe's
wake-ups cost a large share of a humanoid step (docs/results/vector_env).

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

from hvc.envs.mailbox import Mailbox, action_layout, observation_layout
from hvc.envs.spaces import ActionSpace

_POLL_SECONDS = 0.1  # how often a wait checks that the other side is still alive


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
        return and length reported in info. Scalars are Python's own, wherever the env runs
        (they cross to the parent pickled)."""
        info = {}
        if self.driven:
            obs, reward, discount, done, step_info = self.driven.step(action if self.driven.needs_action else None)
            info["new_action"] = bool(step_info["new_action"])
            info["hl_action"] = _plain_scalar(step_info["hl_action"])
        else:
            obs, reward, discount, done = self.env.step(action)
        if done:
            info.update(episode_return=float(self.env.episode_return), episode_length=int(self.env.episode_steps))
            obs = self.reset()
        return obs, float(reward), float(discount), bool(done), info

    def close(self) -> None:
        self.env.close()


def _plain_scalar(value):
    return value.item() if isinstance(value, np.generic) else value


def _mailbox(spec: dict, semaphores, name: str | None = None) -> Mailbox:
    return Mailbox(action_layout(spec["action_space"]), observation_layout(spec["observation_sizes"]),
                   semaphores, name)


def _worker(conn, task, body, render_settings, seed: int, drive, semaphores) -> None:
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    mailbox = None
    try:
        host = _EnvHost(task, body, render_settings, seed, drive)
        conn.send(("ready", host.spec))
        _, name = conn.recv()
        mailbox = _mailbox(host.spec, semaphores, name)
        parent_alive = lambda: not conn.poll(0)  # noqa: E731 - the parent sends nothing more: EOF
        while True:
            command, payload, arrays = mailbox.wait_command(parent_alive, _POLL_SECONDS)
            if command == "reset":
                mailbox.reply("ok", arrays=host.reset())
            elif command == "step":
                obs, *rest = host.step(arrays["action"])
                mailbox.reply("ok", tuple(rest), arrays=obs)
            elif command == "crash":  # for tests: a worker failing mid-run
                raise RuntimeError(str(payload))
            elif command == "close":
                host.close()
                mailbox.reply("ok")
                return
    except (EOFError, KeyboardInterrupt, BrokenPipeError):
        return
    except Exception:  # noqa: BLE001 - forwarded to the parent with its traceback
        try:
            error = traceback.format_exc()[-100_000:]
            mailbox.reply("error", error) if mailbox else conn.send(("error", error))
        except (BrokenPipeError, OSError):
            pass
    finally:
        if mailbox is not None:
            mailbox.close()


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
        self._conns, self._procs, self._hosts, self._mailboxes = [], [], [], []
        workers = num_envs - in_process
        plain = lambda d: None if d is None else dict(d)  # noqa: E731
        semaphores = [(ctx.Semaphore(0), ctx.Semaphore(0)) for _ in range(workers)]
        for i in range(workers):
            parent, child = ctx.Pipe()
            proc = ctx.Process(target=_worker, args=(child, dict(task), dict(body), plain(render_settings),
                                                      seed + i, drive, semaphores[i]),
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
        for i in range(workers):
            self._mailboxes.append(_mailbox(specs[i], semaphores[i]))
            self._conns[i].send(("mailbox", self._mailboxes[i].name))
        self.action_size = specs[0]["action_size"]
        self.action_low, self.action_high = specs[0]["action_low"], specs[0]["action_high"]
        self.observation_sizes = specs[0]["observation_sizes"]
        self.action_space = specs[0]["action_space"]          # what step() takes
        self.controller = specs[0]["controller"]              # None: raw body actions
        self.why_no_controller = specs[0]["why_not"]
        self.skills = getattr(drive, "skills", None)

    def _send(self, index: int, command: str, payload=None, arrays=None) -> None:
        self._mailboxes[index].post(command, payload, arrays)

    def _receive(self, index: int):
        """The worker's reply: through its mailbox, or the pipe during the start-up handshake."""
        conn, proc = self._conns[index], self._procs[index]
        try:
            if index < len(self._mailboxes):
                status, payload, obs = self._mailboxes[index].wait_reply(proc.is_alive, _POLL_SECONDS)
                if obs is not None:  # a reset's observation, or a step's with the rest as payload
                    payload = obs if payload is None else (obs, *payload)
            else:
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
            self._send(i, "reset")
        here = self._in_process("reset")
        return self._stack([self._receive(i) for i in range(len(self._conns))] + here)

    def step(self, actions: np.ndarray):
        workers = len(self._conns)
        for i in range(workers):
            self._send(i, "step", arrays={"action": np.asarray(actions[i])})
        here = self._in_process("step", actions)
        return self._batch([self._receive(i) for i in range(workers)] + here)

    def close(self) -> None:
        if getattr(self, "closed", False):
            return
        self.closed = True
        for mailbox, proc in zip(self._mailboxes, self._procs):
            if proc.is_alive():
                mailbox.post("close")
        for conn in self._conns:  # EOF ends a worker still in its start-up handshake
            conn.close()
        for proc in self._procs:
            proc.join(timeout=5)
            if proc.is_alive():
                proc.terminate()
                proc.join(timeout=5)
        for mailbox in self._mailboxes:
            mailbox.close()
        for host in self._hosts:
            host.close()

    def __enter__(self) -> "VectorEnv":
        return self

    def __exit__(self, *exc) -> None:
        self.close()
