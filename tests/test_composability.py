"""The composability measure (stage=evaluate): steps until a fall under random high-level
actions, and the clip-to-clip table of switches the body survives."""
from types import SimpleNamespace

import numpy as np
import pytest
from omegaconf import OmegaConf

from hvc.config import compose


class ScriptedEnvs:
    """One env whose steps follow a script: (new fragment or None, done, discount)."""

    controller, num_envs = "fragments", 1

    def __init__(self, script):
        self.script = iter(script)
        experts = [SimpleNamespace(entry={"behaviour": "a"}), SimpleNamespace(entry={"behaviour": "b"})]
        self.skills = SimpleNamespace(library=SimpleNamespace(experts=experts),
                                      fragments=[SimpleNamespace(clip=0), SimpleNamespace(clip=1)])
        self.length = 0

    def reset(self):
        return {}

    def random_actions(self, rng):
        return [0]

    def step(self, actions):
        fragment, done, discount = next(self.script)
        self.length += 1
        info = {"new_action": fragment is not None, "hl_action": -1 if fragment is None else fragment}
        if done:
            info["episode_length"], self.length = self.length, 0
        return {}, np.zeros(1), np.array([discount]), np.array([done]), [info]

    def close(self):
        pass


def test_falls_and_switches_are_counted_as_scripted(monkeypatch):
    from hvc.runtime import composability, env_config

    fall = [(0, False, 1.0), None, None, (1, False, 1.0), None, None, (0, False, 1.0), None, None, (1, True, 0.0)]
    fall = [s or (None, False, 1.0) for s in fall]  # switches a->b (step 4), b->a (7), a->b (10), then a fall
    limit = [(0, False, 1.0), (1, False, 1.0)] + [(None, False, 1.0)] * 37 + [(None, True, 1.0)]  # a->b, 40 steps up
    monkeypatch.setattr(env_config, "vector_env", lambda cfg, seed: ScriptedEnvs(fall + limit))
    cfg = OmegaConf.create({"controller": {"name": "fragments"}, "task": {"time_limit": 1.2, "control_timestep": 0.03}})
    scores = composability.cold_switching(cfg, episodes=2)
    assert scores["cap"] == 40 and scores["horizon"] == 33
    assert scores["mean_steps"] == 25.0 and scores["median_steps"] == 25.0 and scores["fall_rate"] == 0.5
    assert scores["switches"] == {"a->b": {"survived": pytest.approx(1 / 3), "of": 3}, "b->a": {"survived": 0.0, "of": 1}}


def test_random_fragments_of_the_shipped_library_fall_within_seconds():
    from hvc.runtime.composability import cold_switching, composability_config

    scores = cold_switching(composability_config(compose(["stage=evaluate"]), "fragments"), episodes=5)
    assert scores["episodes"] == 5 and 0 < scores["median_steps"] < scores["cap"] == 1000
    behaviours = {"stand", "run", "left_turn", "right_turn"}
    assert scores["switches"] and all(set(pair.split("->")) <= behaviours for pair in scores["switches"])
    assert all(0.0 <= s["survived"] <= 1.0 and s["of"] > 0 for s in scores["switches"].values())
