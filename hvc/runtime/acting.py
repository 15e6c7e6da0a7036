"""Acting: the high-level agent's batched steps on the envs, shared by training and `stage=record`.

The policy runs batched in this process (central inference, as in SEED RL: on a 2-core
machine one torch copy per actor would only compete for the cores); the learner turns its
output into what the envs get (`Learner.act`). Per env the actor carries what the agent sees
next: the previous reward, the previous action (the one in force, as the agent saw it) and
episode-start flags, zeroed where an episode ended.
"""
from __future__ import annotations

from dataclasses import dataclass, field

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


INPUTS = ("proprio", "task", "image", "prev_reward", "prev_action", "first")  # n + 1 per unroll
OUTCOMES = ("action", "log_mu", "reward", "discount", "new_action", "query")  # n per unroll


def unrolls_of(steps: list[Step], actor: Actor, start_state: np.ndarray, names) -> list[dict]:
    """One unroll per env from the actor's last `len(steps)` steps, as replay.add's keyword
    arguments for the fields `names` (hvc.runtime.hl_train.unroll_fields): inputs at n + 1
    steps (the last, the actor's current one, for bootstrapping), outcomes at n, the LSTM state
    at the start. Step's fields are named as replay's; the observation's keys too."""
    def value(step, name):
        return step.obs[name] if name in step.obs else getattr(step, name)

    tail = {**actor.obs, "prev_reward": actor.prev_reward, "prev_action": actor.prev_action, "first": actor.first}
    inputs = [k for k in INPUTS if k in names]
    outcomes = [k for k in OUTCOMES if k in names]
    out = []
    for e in range(len(start_state)):
        fields = {k: np.stack([value(s, k)[e] for s in steps] + [tail[k][e]]) for k in inputs}
        fields.update({k: np.stack([value(s, k)[e] for s in steps]) for k in outcomes})
        out.append({"state": start_state[e], **fields})
    return out


def random_returns(envs, episodes: int, rng: np.random.Generator) -> list[float]:
    """Returns of uniformly random high-level actions: the bar a learning curve must clear."""
    envs.reset()
    out: list[float] = []
    while len(out) < episodes:
        _, _, _, _, infos = envs.step(envs.random_actions(rng))
        out += [i["episode_return"] for i in infos if "episode_return" in i]
    return out[:episodes]


@dataclass
class Collected:
    """What acting produced for the learner since it last asked."""

    unrolls: list[dict]                                # replay.add's keyword arguments, one per unroll
    returns: list[float] = field(default_factory=list)  # of the episodes that ended in them
    env_steps: int = 0


class LocalActing:
    """The learner's process acting on its envs (worker processes and its own) in batched
    steps: each `collect` is one unroll of `n` steps per env. The agent acting is the one
    learning, so there are no weights to publish."""

    def __init__(self, actor: Actor, n: int, names):
        self.actor, self.n, self.names = actor, n, list(names)
        self.num_envs = actor.envs.num_envs

    def random_returns(self, episodes: int, rng: np.random.Generator) -> list[float]:
        out = random_returns(self.actor.envs, episodes, rng)
        self.actor.reset()
        return out

    def publish(self, updates: int) -> None:
        pass

    def collect(self) -> Collected:
        start_state = self.actor.agent.pack_state(self.actor.lstm)
        steps = [self.actor.step() for _ in range(self.n)]
        returns = [i["episode_return"] for s in steps for i in s.infos if "episode_return" in i]
        return Collected(unrolls_of(steps, self.actor, start_state, self.names), returns, self.n * self.num_envs)

    def close(self) -> None:
        self.actor.envs.close()
