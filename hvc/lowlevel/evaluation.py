"""Tracking evaluation: completion and reward per episode, for an expert or open loop.

Completion is the fraction of the clip remaining at the (random) start that was tracked
before termination; reward is the mean per-step tracking reward; `energy_<term>` is each
term's weighted energy (w_term * E_term) per step, which shows what holds the reward down. The open-loop
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
    energy: dict[str, float]  # mean weighted energy per reward term (empty if the task has none)


def open_loop_action(obs: dict, logic) -> np.ndarray:
    target = logic.reference.joints[min(logic.t + 1, logic.reference.num_steps - 1)]
    return np.clip(logic.pose_to_actuation(target), -1, 1)


def run_episode(env: FastEnv, act: Callable[[dict, object], np.ndarray]) -> EpisodeStats:
    obs = env.reset()
    logic = env.layout.logic
    weights = logic.reward_fn.weights
    rewards, energy = [], {term: 0.0 for term in weights}
    while True:
        obs, reward, _, done = env.step(act(obs, logic))
        rewards.append(reward)
        for term, value in logic.last_terms.items():
            energy[term] += weights[term] * value
        if done:
            break
    return EpisodeStats(logic.completion, float(np.mean(rewards)), len(rewards), bool(logic.failure),
                        {term: total / len(rewards) for term, total in energy.items()})


def evaluate(env: FastEnv, act: Callable[[dict, object], np.ndarray], episodes: int,
             prefix: str = "") -> dict[str, float]:
    stats = [run_episode(env, act) for _ in range(episodes)]
    return {f"{prefix}completion": float(np.mean([s.completion for s in stats])),
            f"{prefix}reward": float(np.mean([s.mean_reward for s in stats])),
            f"{prefix}fall_rate": float(np.mean([s.fell for s in stats])),
            f"{prefix}steps": float(np.mean([s.steps for s in stats])),
            **{f"{prefix}energy_{term}": float(np.mean([s.energy[term] for s in stats])) for term in stats[0].energy}}


def evaluate_open_loop(env: FastEnv, episodes: int) -> dict[str, float]:
    return evaluate(env, open_loop_action, episodes, prefix="openloop_")


def steering_response(env: FastEnv, act: Callable[[dict, object], np.ndarray], rates, episodes_per_rate: int,
                      cycles: int = 8, settle_steps: int = 10) -> list[dict[str, float]]:
    """Commanded vs achieved turning rate of the steerable policy (Sec. 2.2 evaluation).

    Each episode starts at a random step of the steered reference's first gait cycle (the
    mean action from one start would repeat one episode) and holds the commanded rate for
    `cycles` more; the achieved rate is the slope of the body's unwrapped heading after
    `settle_steps` (a linear fit spans the gait's own sway). Episodes too short after
    settling (early falls) give no rate but still count for completion and falls.
    """
    from hvc.mocap.clips import root_heading

    logics = [layout.logic for layout in env.layouts]
    saved = [(logic.cycles, logic.random_start, logic.start_window) for logic in logics]
    rows = []
    try:
        for logic in logics:
            logic.cycles, logic.random_start, logic.start_window = int(cycles) + 1, True, logic.cycle.num_steps
        for rate in rates:
            for logic in logics:
                logic.held_rate = float(rate)
            achieved, completion, fell = [], [], []
            for _ in range(episodes_per_rate):
                obs = env.reset()
                logic = env.layout.logic
                quats = []
                while True:
                    obs, _, _, done = env.step(act(obs, logic))
                    quats.append(env.data.qpos[logic.root_qpos + 3:logic.root_qpos + 7].copy())
                    if done:
                        break
                heading = root_heading(np.asarray(quats))[settle_steps:]
                if len(heading) >= 2 * settle_steps:
                    achieved.append(float(np.polyfit(np.arange(len(heading)) * env.control_timestep, heading, 1)[0]))
                completion.append(logic.completion)
                fell.append(logic.failure)
            rows.append({"commanded_rate": float(rate),
                         "achieved_rate": float(np.mean(achieved)) if achieved else float("nan"),
                         "completion": float(np.mean(completion)), "fall_rate": float(np.mean(fell))})
    finally:
        for logic, (n, random_start, window) in zip(logics, saved):
            logic.held_rate, logic.cycles, logic.random_start, logic.start_window = None, n, random_start, window
    return rows


def switching_transitions(env: FastEnv, act: Callable[[dict, object], np.ndarray], episodes: int,
                          hold_steps: int) -> dict[str, float]:
    """Behaviour switches of the switching policy completed without falling (Sec. 2.2).

    A switch of the reference's Markov walk is attempted when the body reaches its step;
    it is completed when the body then keeps going for `hold_steps` (one gait cycle) or
    until the walk ends, without a fall. Also per kind of switch, `attempted/<a>-><b>` and
    `completed/<a>-><b>` (behaviour indices): which transitions are hard.
    """
    attempted: dict[tuple[int, int], int] = {}
    completed: dict[tuple[int, int], int] = {}
    for _ in range(episodes):
        obs = env.reset()
        logic = env.layout.logic
        labels, start = logic.labels.copy(), logic.start
        while True:
            obs, _, _, done = env.step(act(obs, logic))
            if done:
                break
        end, fell = logic.t, logic.failure
        for switch in np.flatnonzero(np.diff(labels)) + 1:
            if start < switch <= end:
                kind = (int(labels[switch - 1]), int(labels[switch]))
                attempted[kind] = attempted.get(kind, 0) + 1
                completed[kind] = completed.get(kind, 0) + int(switch + hold_steps <= end or not fell)
    total = sum(attempted.values())
    per_kind = {}
    for (a, b), n in sorted(attempted.items()):
        per_kind[f"attempted/{a}->{b}"] = float(n)
        per_kind[f"completed/{a}->{b}"] = completed[(a, b)] / n
    return {"transitions_attempted": float(total),
            "transitions_completed": sum(completed.values()) / total if total else float("nan"), **per_kind}
