"""Tracking evaluation: completion and reward per episode, for an expert or open loop.

Completion is the fraction of the clip remaining at the (random) start that was tracked
before termination; reward is the mean per-step tracking reward. The open-loop
baseline plays the reference's next pose as the action: position control makes the
pose itself an action, so it needs no learning and shows the bar experts must beat.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np

from hvc.envs.fast_env import FastEnv


@dataclass(frozen=True)
class EpisodeStats:
    completion: float
    mean_reward: float
    steps: int
    fell: bool


def policy_observation(obs: dict) -> np.ndarray:
    """What a low-level expert sees: proprioception then the time input."""
    return np.concatenate([obs["proprio"], obs["task"]])


def open_loop_action(obs: dict, logic) -> np.ndarray:
    target = logic.reference.joints[min(logic.t + 1, logic.reference.num_steps - 1)]
    return np.clip(logic.pose_to_actuation(target), -1, 1)


def run_episode(env: FastEnv, act: Callable[[dict, object], np.ndarray]) -> EpisodeStats:
    obs = env.reset()
    logic = env.layout.logic
    rewards = []
    while True:
        obs, reward, _, done = env.step(act(obs, logic))
        rewards.append(reward)
        if done:
            break
    return EpisodeStats(logic.completion, float(np.mean(rewards)), len(rewards), bool(logic.failure))


def evaluate(env: FastEnv, act: Callable[[dict, object], np.ndarray], episodes: int,
             prefix: str = "") -> dict[str, float]:
    stats = [run_episode(env, act) for _ in range(episodes)]
    return {f"{prefix}completion": float(np.mean([s.completion for s in stats])),
            f"{prefix}reward": float(np.mean([s.mean_reward for s in stats])),
            f"{prefix}fall_rate": float(np.mean([s.fell for s in stats])),
            f"{prefix}steps": float(np.mean([s.steps for s in stats]))}


def evaluate_open_loop(env: FastEnv, episodes: int) -> dict[str, float]:
    return evaluate(env, open_loop_action, episodes, prefix="openloop_")
