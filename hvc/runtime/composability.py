"""Composability of a set of skills: how long the body stays up when a high level that knows
nothing switches between them (issue 23's measure, the bar a high-level agent starts from).

The task's env (go_to_target unless the config names another non-tracking task) is driven by
the skills' controller with uniformly random high-level actions, from the task's own random
starts: steps until a fall (a terminating step; an episode that reaches the time limit counts
as its full length), and for the fragment controllers a clip-to-clip table: of the switches
from a fragment of clip a to one of clip b, the share after which the body stays up for the
next `horizon` control steps (about one gait cycle) or until the episode's time limit.

Under random actions those `horizon` steps hold about ten more random switches, so that table
scores chains, not the a -> b switch itself. With `hold`, each random switch is followed by
clip b's own next fragments, in order, for `horizon` steps or until clip b ends, as a high level
that plays a clip on would do: the table then scores each transition alone, and the steps
until a fall are those of a driver that switches at random at most once per gait cycle (sooner
where clip b ends).
"""
from __future__ import annotations

from collections import defaultdict

import numpy as np
from omegaconf import DictConfig, OmegaConf

from hvc.config import group_config

HORIZON_SECONDS = 1.0  # about one gait cycle of the run clips (0.4-1.2 s)


def composability_config(cfg: DictConfig, controller: str) -> DictConfig:
    """`cfg` with `controller` and one env on a task with random starts (tracking is not one)."""
    out = OmegaConf.create(OmegaConf.to_container(cfg, resolve=True))  # not struct: controllers differ in keys
    out.controller = group_config("controller", controller)
    out.num_envs = out.in_process_envs = 1
    if out.task.kind == "tracking":
        out.task = group_config("task", "go_to_target")
    return out


def cold_switching(cfg: DictConfig, episodes: int, seed: int = 0, hold: bool = False) -> dict:
    """Steps until a fall under random high-level actions over `episodes` episodes, and the
    clip-to-clip survival table for fragment controllers; with `hold` (fragment controllers
    only), each random switch is played on through clip b's next fragments (module docstring).
    `cfg` as composability_config gives."""
    from hvc.runtime.env_config import vector_env

    envs = vector_env(cfg, seed)
    try:
        if envs.controller is None:
            raise RuntimeError(envs.why_no_controller)
        cap = int(round(float(cfg.task.time_limit) / float(cfg.task.control_timestep)))
        horizon = int(round(HORIZON_SECONDS / float(cfg.task.control_timestep)))
        clip_of = _clip_of_fragment(envs)
        if hold and clip_of is None:
            raise ValueError(f"hold: only fragment controllers have clips to play on, not {cfg.controller.name}")
        successor = _next_fragment(envs) if hold else None
        rng = np.random.default_rng(seed)
        lengths, falls = [], 0
        tried, survived = defaultdict(int), defaultdict(int)
        pending: list[tuple[tuple[str, str], int]] = []  # (switch, step by which the body must still be up)
        previous, step = None, 0
        fragment, hold_until = None, 0  # with hold: the running fragment, and the step its clip is played to
        envs.reset()
        while len(lengths) < episodes:
            actions = envs.random_actions(rng)
            playing_on = hold and fragment is not None and step + 1 < hold_until and successor[fragment] >= 0
            if playing_on:  # taken only when the running fragment ends
                actions = [successor[fragment]]
            _, _, discounts, dones, infos = envs.step(actions)
            info, step = infos[0], step + 1
            if clip_of is not None and info.get("new_action"):  # chosen for this step: its fall counts
                fragment = int(info["hl_action"])
                current = clip_of[fragment]
                if not playing_on:  # a random choice: a switch
                    if hold:  # the transition played on so far stayed up through its whole hold; this
                        for pair, _ in pending:  # step is the new fragment's, and so is a fall in it
                            tried[pair] += 1
                            survived[pair] += 1
                        pending = []
                    if previous is not None:
                        pending.append(((previous, current), step + horizon))
                    hold_until = step + horizon
                previous = current
            fell = bool(dones[0]) and discounts[0] == 0.0
            still = []
            for pair, until in pending:
                if fell or dones[0] or step >= until:  # settled: a fall, or up to its horizon or the time limit
                    tried[pair] += 1
                    survived[pair] += not fell
                else:
                    still.append((pair, until))
            pending = still
            if dones[0]:
                lengths.append(min(int(info["episode_length"]), cap))
                falls += fell
                previous, step, fragment = None, 0, None
    finally:
        envs.close()
    lengths = np.asarray(lengths)
    return {"controller": str(cfg.controller.name), "hold": hold, "episodes": len(lengths), "cap": cap, "horizon": horizon,
            "mean_steps": float(lengths.mean()), "median_steps": float(np.median(lengths)),
            "median_ci95": median_interval(lengths, seed), "fall_rate": float(falls / len(lengths)),
            "switches": {f"{a}->{b}": {"survived": survived[(a, b)] / tried[(a, b)], "of": tried[(a, b)]}
                         for a, b in sorted(tried)}}


def median_interval(lengths: np.ndarray, seed: int = 0) -> tuple[float, float]:
    """95% percentile-bootstrap interval of the median episode length: the survival of two
    libraries differs by a few steps, and this says which differences 100 episodes resolve."""
    from scipy.stats import bootstrap

    if len(np.unique(lengths)) < 2:  # one episode, or all alike: nothing to resample
        return float(np.median(lengths)), float(np.median(lengths))
    interval = bootstrap((lengths,), np.median, confidence_level=0.95, method="percentile", n_resamples=2000,
                         random_state=np.random.default_rng(seed)).confidence_interval
    return round(float(interval.low), 1), round(float(interval.high), 1)  # percentiles interpolate between medians


def _clip_of_fragment(envs) -> list[str] | None:
    """Fragment index -> the behaviour of its clip, for the fragment controllers."""
    if envs.skills is None or not envs.skills.fragments:
        return None
    experts = envs.skills.library.experts
    return [f"{experts[f.clip].entry['behaviour']}" for f in envs.skills.fragments]


def _next_fragment(envs) -> list[int]:
    """Fragment index -> the index of the same clip's next fragment, -1 after its last."""
    fragments = envs.skills.fragments
    index = {(f.clip, f.start): i for i, f in enumerate(fragments)}
    return [index.get((f.clip, f.start + f.length), -1) for f in fragments]
