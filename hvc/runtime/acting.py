"""Acting: the high-level agent's batched steps on the envs, shared by training and `stage=record`.

The policy runs batched in this process (central inference, as in SEED RL: on a 2-core
machine one torch copy per actor would only compete for the cores); the learner turns its
output into what the envs get (`Learner.act`). Per env the actor carries what the agent sees
next: the previous reward, the previous action (the one in force, as the agent saw it) and
episode-start flags, zeroed where an episode ended.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from hvc.agents.network import HighLevelAgent
from hvc.algorithms.learner import Acted


@dataclass
class Step:
    """One batched env step: the inputs the agent acted on, what it chose and what came back."""

    obs: dict[str, np.ndarray]  # the observation acted on
    prev_reward: np.ndarray
    prev_action: np.ndarray
    first: np.ndarray           # 1 where this step starts an episode (LSTM reset)
    action: np.ndarray          # the high-level action in force after the step (replay's action)
    query: np.ndarray | None    # Wolpertinger: the query in force
    log_mu: np.ndarray
    reward: np.ndarray
    discount: np.ndarray        # the learner's: 0 wherever an episode ended (learning_discounts)
    new_action: np.ndarray      # 1 where the controller took a new action
    infos: list[dict]


def carry(acted: Acted, prev_action: np.ndarray, rewards: np.ndarray, dones: np.ndarray, infos):
    """After a step: (new-action flags, the action in force: the new one only where the
    controller took it, then the previous reward, previous action and episode-start flags the
    agent sees next, zeroed where an episode ended). The agent sees `acted.seen` of a new action
    (a raw continuous sample's clipped value, what the env got)."""
    new = np.array([float(i.get("new_action", False)) for i in infos], np.float32)
    held = new.reshape(-1, *([1] * (acted.action.ndim - 1))) > 0
    in_force = np.where(held, acted.action, prev_action)
    next_action = np.where(held, acted.seen, prev_action)
    next_reward = rewards.astype(np.float32)
    next_action[dones], next_reward[dones] = 0, 0.0
    return new, in_force, next_reward, next_action, dones.astype(np.float32)


def learning_discounts(discounts: np.ndarray, dones: np.ndarray) -> np.ndarray:
    """The discounts the learner sees: 0 wherever an episode ended, time limits included.
    The actors reset at once, so the next stored step is a new episode's first: a time
    limit's env discount of 1 would bootstrap from that state and carry V-trace and
    Retrace traces across the boundary (IMPALA also treats truncation as termination)."""
    return np.where(dones, 0.0, discounts).astype(np.float32)


class Actor:
    """The agent and its learner acting on `envs`; `recorder` (hvc.runtime.episodes) gets env 0's
    steps; `update_normalizer` feeds the agent's input statistics (training, not playback)."""

    def __init__(self, agent: HighLevelAgent, learner, envs, recorder=None, update_normalizer: bool = True):
        self.agent, self.learner, self.envs, self.recorder = agent, learner, envs, recorder
        self.update_normalizer = update_normalizer
        self.device = agent.policy_out.weight.device
        spec, E = agent.spec, envs.num_envs
        self.obs = envs.reset()
        self.lstm = agent.initial_state(E)
        self.prev_reward, self.first = np.zeros(E, np.float32), np.ones(E, np.float32)
        self.prev_action = np.zeros(E, np.int64) if spec.discrete else np.zeros((E, spec.action_size), np.float32)
        self.query = None  # the query in force, once a Wolpertinger learner has chosen one

    def reset(self) -> None:
        """New episodes in every env (after steps taken outside the actor, e.g. random baselines)."""
        self.obs = self.envs.reset()
        self.lstm = self.agent.initial_state(self.envs.num_envs)
        self.prev_reward[:], self.first[:], self.prev_action[:] = 0, 1, 0

    def policy(self) -> tuple[torch.Tensor, torch.Tensor]:
        """(policy output, core features) for the current inputs; advances the LSTM state."""
        tensor = lambda x: torch.from_numpy(x[None]).to(self.device)  # noqa: E731
        obs = self.obs
        if self.update_normalizer:
            self.agent.normalizer.update(torch.from_numpy(np.concatenate([obs["proprio"], obs["task"]], -1))
                                         .to(self.device))
        with torch.no_grad():
            out, h, self.lstm = self.agent(
                tensor(obs["proprio"]).float(), tensor(obs["task"]).float(), tensor(self.prev_reward),
                tensor(self.prev_action), self.lstm, image=tensor(obs["image"]) if "image" in obs else None,
                done=tensor(self.first))
        return out[0], h[0]

    def step(self) -> Step:
        before = (self.obs, self.prev_reward, self.prev_action, self.first)
        acted = self.learner.act(*self.policy())
        self.obs, rewards, discounts, dones, infos = self.envs.step(acted.send)
        new, in_force, self.prev_reward, self.prev_action, self.first = carry(
            acted, before[2], rewards, dones, infos)
        if acted.query is not None:
            self.query = acted.query if self.query is None else np.where(new[:, None] > 0, acted.query, self.query)
        if self.recorder is not None:
            self.recorder.add({k: v[0] for k, v in before[0].items()}, float(rewards[0]), infos[0], bool(dones[0]),
                              query=None if self.query is None else self.query[0])
        return Step(before[0], before[1], before[2], before[3], in_force,
                    None if self.query is None else self.query.copy(), acted.log_mu, rewards,
                    learning_discounts(discounts, dones), new, infos)
