"""Envs in Ray actors (`actors=ray`): the same interface as VectorEnv, so one learner can use
actors on other machines of a Ray cluster (`ray.address=<head>:6379`; none: a local Ray).

Each actor hosts one env with its controller and low-level experts (vector_env's _EnvHost);
the skills go to the object store once and every actor reads them from there. This is central
acting (`ray.acting=central`, and `stage=rollout`): as with worker processes, an actor sends its
observation and the learner sends back the high-level action, so there are no weights to
broadcast and no policy lag, at the cost of one round trip per control step. Training acts in
the actors by default instead (hvc.runtime.ray_acting).
"""
from __future__ import annotations

from typing import Any, Mapping

import numpy as np

from hvc.envs.vector_env import BatchedEnvs, WorkerError, _EnvHost


def _ray():
    try:
        import ray
    except ImportError:
        raise WorkerError("actors=ray needs Ray: pip install 'hvc[ray]'") from None
    return ray


def get_or_fail(futures, close, what: str):
    """ray.get of `futures`; a Ray failure closes the caller's actors (`close`) and becomes one
    WorkerError naming `what`, instead of Ray's trace."""
    ray = _ray()
    try:
        return ray.get(futures)
    except ray.exceptions.RayError as error:
        close()
        raise WorkerError(f"{what} failed: {error}") from None


def connect(address: str | None = None, num_cpus: int | None = None) -> None:
    """Joins the Ray cluster at `address`, or starts a local one (loopback only) once per process."""
    ray = _ray()
    if ray.is_initialized():
        return
    if address:
        ray.init(address=address, log_to_driver=False)
    else:
        ray.init(num_cpus=num_cpus, include_dashboard=False, log_to_driver=False,
                 _node_ip_address="127.0.0.1")


class _Host(_EnvHost):
    """An actor's env host; Ray actors expose methods, not attributes. Arrays from the object
    store are read-only views; the experts keep scratch buffers, so the actor takes its own copy."""

    def __init__(self, task, body, render_settings, seed: int, drive):
        import copy

        super().__init__(task, body, render_settings, seed, copy.deepcopy(drive))

    def get_spec(self) -> dict:
        return self.spec

    def call(self, message: tuple):
        """("reset", None) or ("step", action): the one method a compiled graph runs."""
        command, payload = message
        if command == "crash":  # for tests: an actor failing mid-run
            raise RuntimeError(str(payload))
        return self.reset() if command == "reset" else self.step(payload)


class RayVectorEnv(BatchedEnvs):
    """`num_envs` envs, one per Ray actor, stepped together; auto-resets finished episodes."""

    def __init__(self, task: Mapping[str, Any], body: Mapping[str, Any], render_settings: Mapping[str, Any] | None,
                 num_envs: int, seed: int = 0, drive=None, cpus_per_actor: float = 1.0, compiled: bool = True):
        ray = _ray()
        self.task_name, self.num_envs, self.closed = task["name"], num_envs, False
        host = ray.remote(num_cpus=cpus_per_actor)(_Host)
        plain = lambda d: None if d is None else dict(d)  # noqa: E731
        shared_drive = ray.put(drive)  # with its skills, once into the object store, not once per actor
        self._actors = [host.remote(dict(task), dict(body), plain(render_settings), seed + i, shared_drive)
                        for i in range(num_envs)]
        spec = self._get([self._actors[0].get_spec.remote()])[0]
        self.action_size = spec["action_size"]
        self.action_low, self.action_high = spec["action_low"], spec["action_high"]
        self.observation_sizes = spec["observation_sizes"]
        self.action_space = spec["action_space"]
        self.controller = spec["controller"]
        self.why_no_controller = spec["why_not"]
        self.skills = getattr(drive, "skills", None)
        self._graph = None
        if compiled:
            from ray.dag import InputNode, MultiOutputNode

            with InputNode() as messages:
                graph = MultiOutputNode([a.call.bind(messages[i]) for i, a in enumerate(self._actors)])
            self._graph = graph.experimental_compile()

    def _get(self, futures) -> list:
        return get_or_fail(futures, self.close, f"a Ray env actor (task={self.task_name})")

    def _call(self, messages: list) -> list:
        if self._graph is not None:
            return self._get(self._graph.execute(*messages))
        return self._get([a.call.remote(m) for a, m in zip(self._actors, messages)])

    def reset(self) -> dict[str, np.ndarray]:
        return self._stack(self._call([("reset", None)] * self.num_envs))

    def step(self, actions):
        return self._batch(self._call([("step", np.asarray(a)) for a in actions]))

    def close(self) -> None:
        if self.closed:
            return
        self.closed = True
        ray = _ray()
        if self._graph is not None:
            self._graph.teardown()
        for actor in self._actors:
            ray.kill(actor)
