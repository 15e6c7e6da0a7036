"""Switch starts and cut-ins: training episodes that begin where other skills' fragments left the body.

Under the fragments controller an expert is cut into at a random step from whatever state the
previous fragment, of any clip, left the body in; experts trained only from their own
reference's states fall within a second of such cold switches (docs/results/composability).
Before its RL phase, an expert's trainer plays chains of 1 to `max_fragments` random fragments
of a library's experts (their mean actions, each expert seeing its own clip's phase, as the
fragments controller plays them) from random reference states of those experts, keeps the
states of the chains that did not fall, and starts `lowlevel.switch_starts` of its training
episodes from them, placed at the place and heading of a random step of its own reference
(hvc.envs.tracking.TrackingLogic.place_state).

Switch starts train from the ends of 1 to 4 fragments followed by a whole episode of one
expert, while under cold switching every expert hands over again after one fragment. Cut-ins
(`lowlevel.cut_ins`) train on such chains themselves: at each fragment boundary of its own,
the expert being trained hands over with that probability to one random fragment of the
library's experts, and its next episode starts where that fragment left the body, at a random
step of its reference; its episodes become chains of short segments of its own among other
skills' fragments, as the fragments controller plays them.
"""
from __future__ import annotations

from contextlib import contextmanager
from pathlib import Path
from typing import Mapping

import mujoco
import numpy as np

from hvc.envs.fast_env import FastEnv
from hvc.envs.tracking import SwitchStates
from hvc.lowlevel.library import Expert, ExpertLibrary, policy_observation, shipped_library


def play_fragment(env: FastEnv, experts: list[Expert], fragment_len: int, rng: np.random.Generator) -> bool:
    """One fragment of a random expert from where the body is, as the fragments controller
    plays it (the expert's mean action, seeing its own clip's phase from a random step);
    whether the body fell."""
    layout, data = env.layout, env.data
    expert = experts[int(rng.integers(len(experts)))]
    start = int(rng.integers(max(1, expert.reference.num_steps - fragment_len)))
    for t in range(start, min(start + fragment_len, expert.reference.num_steps)):
        obs = {"proprio": layout.proprio(data), "task": expert.reference.phase[t:t + 1]}
        env.advance(expert.act(policy_observation(obs)))
        if layout.logic.contact_failure(data):
            return True
    return False


def collect_switch_states(env: FastEnv, experts: list[Expert], count: int, fragment_len: int,
                          rng: np.random.Generator, max_fragments: int = 4) -> SwitchStates:
    """`count` heading-free states reached by random fragment chains that stayed up."""
    logic, data = env.layout.logic, env.data
    states = []
    while len(states) < count:
        mujoco.mj_resetData(env.model, data)  # not env.reset(): the env's own random stream stays untouched
        first = experts[int(rng.integers(len(experts)))]
        logic.set_reference_state(data, int(rng.integers(first.reference.num_steps - 1)), first.reference)
        mujoco.mj_forward(env.model, data)
        if not any(play_fragment(env, experts, fragment_len, rng)
                   for _ in range(int(rng.integers(1, max_fragments + 1)))):
            states.append(logic.heading_free_state(data))
    qpos, qvel, act = (np.stack(parts) for parts in zip(*states))
    return SwitchStates(qpos, qvel, act)


def switch_library(cfg: Mapping) -> ExpertLibrary:
    """`cfg`'s `switch_from` library ("shipped" or a file): whose fragments make the switches."""
    source = cfg.get("switch_from", "shipped")
    return ExpertLibrary.load(shipped_library() if source == "shipped" else Path(source))


def switch_states_for(env: FastEnv, experts: list[Expert], cfg: Mapping, seed: int) -> SwitchStates:
    """The switch states of `experts` as `cfg` sets them, drawn with their own stream so that
    the training's random streams are the same with or without them."""
    return collect_switch_states(env, experts, int(cfg["switch_states"]), int(cfg["switch_fragment_len"]),
                                 np.random.default_rng([seed, 23]))


def cut_in(env: FastEnv, experts: list[Expert], fragment_len: int,
           rng: np.random.Generator) -> dict[str, np.ndarray] | None:
    """A random fragment of `experts` from where the body is; if the body stays up, a new
    episode starts where the fragment left it (at a random step of the reference, placed at its
    place and heading) and its first observation is returned; None if the body fell."""
    if play_fragment(env, experts, fragment_len, rng):
        return None
    state = env.layout.logic.heading_free_state(env.data)
    logics = [layout.logic for layout in env.layouts]
    try:
        for logic in logics:  # whichever layout the reset draws
            logic.next_start = state
        return env.reset()
    finally:
        for logic in logics:
            logic.next_start = None


@contextmanager
def switch_starts(env: FastEnv, probability: float):
    """Every layout's episodes start from switch states with `probability` inside the block."""
    logics = [layout.logic for layout in env.layouts]
    saved = [logic.switch_probability for logic in logics]
    try:
        for logic in logics:
            logic.switch_probability = probability
        yield
    finally:
        for logic, p in zip(logics, saved):
            logic.switch_probability = p
