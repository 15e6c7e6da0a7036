"""Acting in Ray actors (`actors=ray ray.acting=actors`): each actor hosts one env with its
controller and low-level experts and a copy of the high-level agent, and returns whole unrolls,
so a round trip costs once per unroll, not once per control step as with central acting
(hvc.envs.ray_actors). The learner keeps the one agent that learns: it feeds its input
normaliser from the unrolls as they arrive and broadcasts its weights (normaliser included)
through the object store every `ray.broadcast_every` unrolls; each actor loads them before its
next unroll. An actor is resubmitted as soon as its unroll arrives, so acting goes on while the
learner learns. The policy lag this adds is what the off-policy corrections (V-trace, Retrace)
are for: replay stores the behaviour policy's log density.
"""
from __future__ import annotations

import copy
from pathlib import Path

import numpy as np
import torch
from omegaconf import DictConfig, OmegaConf

from hvc.envs.ray_actors import _ray, connect, get_or_fail
from hvc.runtime.acting import Actor, Collected, random_returns, unrolls_of


class UnrollActor:
    """One env (in the actor's own process) and the agent acting on it; run as a Ray actor."""

    def __init__(self, cfg: dict, task: dict, body: dict, render: dict | None, seed: int, drive,
                 record_dir: str | None):
        from hvc.envs.vector_env import VectorEnv
        from hvc.runtime.episodes import EpisodeRecorder
        from hvc.runtime.hl_train import build_agent, unroll_fields

        torch.set_num_threads(1)
        torch.manual_seed(seed)
        cfg = OmegaConf.create(cfg)
        cfg.seed = seed  # the learner's own sampling streams (Wolpertinger's choice among candidates)
        self.rng = np.random.default_rng(seed)
        # arrays from the object store are read-only views; the experts keep scratch buffers
        self.envs = VectorEnv(task, body, render, 1, seed=seed, drive=copy.deepcopy(drive), in_process=1)
        self.facts = {"observation_sizes": self.envs.observation_sizes, "action_space": self.envs.action_space,
                      "controller": self.envs.controller, "why_not": self.envs.why_no_controller}
        self.actor, self.version = None, -1
        if self.envs.controller is None:  # the learner reads facts() and stops with the reason
            return
        spec, agent, learner = build_agent(cfg, self.envs)
        self.n = int(cfg.task.agent.unroll)
        self.names = list(unroll_fields(spec, self.n, query=learner.keeps_query))
        recorder = EpisodeRecorder.for_run(cfg, Path(record_dir), self.envs.skills) if record_dir else None
        self.actor = Actor(agent, learner, self.envs, recorder, update_normalizer=False)

    def get_facts(self) -> dict:
        return self.facts

    def random_returns(self, episodes: int) -> list[float]:
        out = random_returns(self.envs, episodes, self.rng)
        self.actor.reset()
        return out

    def unroll(self, version: int, weights: list) -> tuple[dict, list[float]]:
        """One unroll of n steps with the newest weights (`weights`: [an object ref], boxed so
        that Ray resolves it only when this actor has not loaded that version yet)."""
        if version != self.version:
            self.actor.agent.load_state_dict(_ray().get(weights[0]))
            self.version = version
        start_state = self.actor.agent.pack_state(self.actor.lstm)
        steps = [self.actor.step() for _ in range(self.n)]
        returns = [i["episode_return"] for s in steps for i in s.infos if "episode_return" in i]
        return unrolls_of(steps, self.actor, start_state, self.names)[0], returns


class RayActing:
    """`num_envs` UnrollActors on the Ray cluster (`ray.address`, or a local Ray). Until
    `attach` it stands in for the envs where the agent is built (observation sizes, action
    space, skills); then it is the training loop's source of unrolls, like LocalActing."""

    def __init__(self, cfg: DictConfig, seed: int, run_dir: Path | None):
        from hvc.controllers.factory import Drive
        from hvc.errors import ControllerUnavailable
        from hvc.runtime.env_config import env_dicts
        from hvc.skills import skills_for_job

        ray = _ray()
        connect(cfg.ray.address, cfg.ray.num_cpus)
        self.task_name, self.num_envs, self.closed = str(cfg.task.name), int(cfg.num_envs), False
        self.broadcast_every = int(cfg.ray.broadcast_every)
        task, body, render = env_dicts(cfg)
        try:
            self.skills = skills_for_job(cfg)
        except ControllerUnavailable as error:
            self.skills, self.controller, self.why_no_controller, self._actors = None, None, str(error), []
            return
        controller = OmegaConf.to_container(cfg.controller, resolve=True)
        shared_drive = ray.put(Drive(controller, self.skills))  # the skills go to the object store once
        plain_cfg = OmegaConf.to_container(cfg, resolve=True)
        record = run_dir is not None and int(cfg.get("record_episodes", 0)) > 0
        host = ray.remote(num_cpus=float(cfg.ray.cpus_per_actor))(UnrollActor)
        self._actors = [host.remote(plain_cfg, task, body, render, seed + i, shared_drive,
                                    str(run_dir) if record and i == 0 else None)  # env 0 records, as locally
                        for i in range(self.num_envs)]
        # every actor built before acting starts: one still importing would deliver its first
        # unroll only after the others' tenth, and a failing one should stop the run here
        facts = self._get([a.get_facts.remote() for a in self._actors])[0]
        self.observation_sizes, self.action_space = facts["observation_sizes"], facts["action_space"]
        self.controller, self.why_no_controller = facts["controller"], facts["why_not"]
        self.agent = None
        self._pending: dict = {}
        self._version, self._weights, self._unrolls_since_broadcast = -1, None, 0

    def attach(self, agent) -> "RayActing":
        """The learning agent whose weights the actors act with and whose normaliser the unrolls feed."""
        self.agent = agent
        return self

    def _get(self, futures):
        return get_or_fail(futures, self.close, f"a Ray acting actor (task={self.task_name})")

    def random_returns(self, episodes: int, rng: np.random.Generator) -> list[float]:
        """Random-action episodes spread over the actors (each with its own seeded stream)."""
        share = -(-episodes // self.num_envs)
        returns = self._get([a.random_returns.remote(share) for a in self._actors])
        return [r for actor_returns in returns for r in actor_returns][:episodes]

    def publish(self, updates: int) -> None:
        """Broadcasts the agent's weights on the first call and then every `broadcast_every`
        unrolls collected (`updates`, the learner's count, is LocalActing's business)."""
        if self._weights is not None and self._unrolls_since_broadcast < self.broadcast_every:
            return
        weights = {k: v.detach().to("cpu") for k, v in self.agent.state_dict().items()}
        self._weights, self._version = [_ray().put(weights)], self._version + 1
        self._unrolls_since_broadcast = 0

    def collect(self) -> Collected:
        """The next unroll any actor finishes; that actor starts its next one at once."""
        ray = _ray()
        if not self._pending:
            self._pending = {a.unroll.remote(self._version, self._weights): a for a in self._actors}
        done, _ = ray.wait(list(self._pending), num_returns=1)
        actor = self._pending.pop(done[0])
        unroll, returns = self._get(done[0])
        self._pending[actor.unroll.remote(self._version, self._weights)] = actor
        self._unrolls_since_broadcast += 1
        seen = np.concatenate([unroll["proprio"][:-1], unroll["task"][:-1]], -1)  # the n steps acted on
        self.agent.normalizer.update(torch.from_numpy(seen).to(self.agent.policy_out.weight.device))
        return Collected([unroll], returns, len(unroll["reward"]))

    def close(self) -> None:
        if self.closed:
            return
        self.closed = True
        ray = _ray()
        for actor in self._actors:
            ray.kill(actor)
        self._pending = {}
