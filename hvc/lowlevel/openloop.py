"""The open-loop sanity baseline: play the reference's next pose as the action.

Position control makes the reference pose itself an action, so this needs no
learning; how long the body stays up and the reward it earns show that the tracking
task, reward and termination are wired correctly, and give the bar experts must beat.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from hvc.envs.fast_env import FastEnv


@dataclass(frozen=True)
class EpisodeStats:
    completion: float      # fraction of the remaining clip tracked before termination
    mean_reward: float     # per step
    steps: int
    fell: bool


def open_loop_episode(env: FastEnv) -> EpisodeStats:
    env.reset()
    logic = env.layout.logic
    rewards = []
    while True:
        target = logic.reference.joints[min(logic.t + 1, logic.reference.num_steps - 1)]
        _, reward, _, done = env.step(np.clip(logic.pose_to_actuation(target), -1, 1))
        rewards.append(reward)
        if done:
            break
    return EpisodeStats(logic.completion, float(np.mean(rewards)), len(rewards), bool(logic.failure))


def evaluate_open_loop(env: FastEnv, episodes: int) -> dict[str, float]:
    stats = [open_loop_episode(env) for _ in range(episodes)]
    return {"openloop_completion": float(np.mean([s.completion for s in stats])),
            "openloop_reward": float(np.mean([s.mean_reward for s in stats])),
            "openloop_fall_rate": float(np.mean([s.fell for s in stats])),
            "openloop_steps": float(np.mean([s.steps for s in stats]))}
