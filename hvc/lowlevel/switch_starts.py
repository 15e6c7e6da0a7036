"""Switch starts: training episodes that begin where other skills' fragments left the body.

Under the fragments controller an expert is cut into at a random step from whatever state the
previous fragment, of any clip, left the body in; experts trained only from their own
reference's states fall within a second of such cold switches (docs/results/composability).
Before its RL phase, an expert's trainer plays chains of 1 to `max_fragments` random fragments
of a library's experts (their mean actions, each expert seeing its own clip's phase, as the
fragments controller plays them) from random reference states of those experts, keeps the
states of the chains that did not fall, and starts `lowlevel.switch_starts` of its training
episodes from them, placed at the place and heading of a random step of its own reference
(hvc.envs.tracking.TrackingLogic.place_switch_state).
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


def collect_switch_states(env: FastEnv, experts: list[Expert], count: int, fragment_len: int,
                          rng: np.random.Generator, max_fragments: int = 4) -> SwitchStates:
    """`count` heading-free states reached by random fragment chains that stayed up."""
    logic, layout = env.layout.logic, env.layout
    data = env.data
    states = []
    while len(states) < count:
        mujoco.mj_resetData(env.model, data)  # not env.reset(): the env's own random stream stays untouched
        first = experts[int(rng.integers(len(experts)))]
        logic.set_reference_state(data, int(rng.integers(first.reference.num_steps - 1)), first.reference)
        mujoco.mj_forward(env.model, data)
        fell = False
        for _ in range(int(rng.integers(1, max_fragments + 1))):
            expert = experts[int(rng.integers(len(experts)))]
            start = int(rng.integers(max(1, expert.reference.num_steps - fragment_len)))
            for t in range(start, min(start + fragment_len, expert.reference.num_steps)):
                obs = {"proprio": layout.proprio(data), "task": expert.reference.phase[t:t + 1]}
                env.advance(expert.act(policy_observation(obs)))
                fell = logic.contact_failure(data)
                if fell:
                    break
            if fell:
                break
        if not fell:
            states.append(logic.heading_free_state(data))
    qpos, qvel, act = (np.stack(parts) for parts in zip(*states))
    return SwitchStates(qpos, qvel, act)


def switch_states_for(env: FastEnv, cfg: Mapping, seed: int) -> SwitchStates:
    """The switch states of `cfg`'s `switch_from` library ("shipped" or a file), drawn with
    their own stream so that the training's random streams are the same with or without them."""
    source = cfg.get("switch_from", "shipped")
    library = ExpertLibrary.load(shipped_library() if source == "shipped" else Path(source))
    return collect_switch_states(env, library.experts, int(cfg["switch_states"]), int(cfg["switch_fragment_len"]),
                                 np.random.default_rng([seed, 23]))


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
