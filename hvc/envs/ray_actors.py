"""Envs in Ray actors (`actors=ray`): the same interface as VectorEnv, so one learner can use
actors on other machines of a Ray cluster (`ray.address=<head>:6379`; none: a local Ray).

Each actor hosts one env with its controller and low-level experts (vector_env's _EnvHost);
the skills go to the object store once and every actor reads them from there. Acting stays
central and batched in the learner process, as with worker processes: an actor sends its
observation, the learner sends back the high-level action. With the LSTM agent acting for all
envs in one batch there are no weights to broadcast and no policy lag; the cost is one round
trip per control step, which the design note in the README sizes for hundreds of actors.
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


class RayVectorEnv(BatchedEnvs):
    """`num_envs` envs, one per Ray actor, stepped together; auto-resets finished episodes."""

    def __init__(self, task: Mapping[str, Any], body: Mapping[str, Any], render_settings: Mapping[str, Any] | None,
                 num_envs: int, seed: int = 0, drive=None, cpus_per_actor: float = 1.0):
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

    def _get(self, futures: list) -> list:
        ray = _ray()
        try:
            return ray.get(futures)
        except (ray.exceptions.RayActorError, ray.exceptions.RayTaskError) as error:
            self.close()
            raise WorkerError(f"a Ray env actor (task={self.task_name}) failed: {error}") from None

    def reset(self) -> dict[str, np.ndarray]:
        return self._stack(self._get([a.reset.remote() for a in self._actors]))

    def step(self, actions):
        return self._batch(self._get([a.step.remote(np.asarray(act)) for a, act in zip(self._actors, actions)]))

    def close(self) -> None:
        if self.closed:
            return
        self.closed = True
        ray = _ray()
        for actor in self._actors:
            ray.kill(actor)
