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


class PlayingEnvs:
    """One env that plays the fragments it is given, 3 steps each, and falls at `fall_step`;
    its random choices are scripted (each taken once), so the driver's own choices show."""

    controller, num_envs = "fragments", 1

    def __init__(self, randoms, fall_step):
        experts = [SimpleNamespace(entry={"behaviour": "a"}), SimpleNamespace(entry={"behaviour": "b"})]
        fragments = ([SimpleNamespace(clip=0, start=s, length=3) for s in (0, 3, 6)]          # a: 0, 1, 2
                     + [SimpleNamespace(clip=1, start=s, length=3) for s in range(0, 30, 3)])  # b: 3..12
        self.skills = SimpleNamespace(library=SimpleNamespace(experts=experts), fragments=fragments)
        self.randoms, self.fall_step, self.taken, self.t = list(randoms), fall_step, [], 0

    def reset(self):
        return {}

    def random_actions(self, rng):
        return [self.randoms[0]]

    def step(self, actions):
        new = self.t % 3 == 0
        if new:
            self.taken.append(int(actions[0]))
            if self.taken[-1] == self.randoms[0]:
                self.randoms.pop(0)
        self.t += 1
        done = self.t == self.fall_step
        info = {"new_action": new, "hl_action": self.taken[-1], **({"episode_length": self.t} if done else {})}
        return {}, np.zeros(1), np.array([0.0 if done else 1.0]), np.array([done]), [info]

    def close(self):
        pass


def test_held_switches_play_their_clip_on_and_are_scored_alone(monkeypatch):
    from hvc.runtime import composability, env_config

    envs = PlayingEnvs(randoms=[0, 3, 2, 3, 12], fall_step=18)
    monkeypatch.setattr(env_config, "vector_env", lambda cfg, seed: envs)
    monkeypatch.setattr(composability, "HORIZON_SECONDS", 0.18)  # 6 steps: two fragments per hold
    cfg = OmegaConf.create({"controller": {"name": "fragments"}, "task": {"time_limit": 30.0, "control_timestep": 0.03}})
    scores = composability.cold_switching(cfg, episodes=1, hold=True)
    # a (random) and its next fragment; a->b and b's next; b->a at a's last fragment, which has no next,
    # so a->b again at once; then the fall two steps into that hold
    assert envs.taken == [0, 1, 3, 4, 2, 3]
    assert scores["switches"] == {"a->b": {"survived": 0.5, "of": 2}, "b->a": {"survived": 1.0, "of": 1}}
    assert scores["hold"] and scores["mean_steps"] == 18 and scores["fall_rate"] == 1.0


def test_a_fall_on_a_switch_step_is_the_new_switchs_and_episodes_start_afresh(monkeypatch):
    from hvc.runtime import composability, env_config

    class Resetting(PlayingEnvs):  # a new episode after each fall, as the vector env auto-resets
        def step(self, actions):
            out = super().step(actions)
            if out[3][0]:
                self.t, self.fall_step = 0, 7
            return out

    envs = Resetting(randoms=[0, 3, 5, 9, 12], fall_step=13)
    monkeypatch.setattr(env_config, "vector_env", lambda cfg, seed: envs)
    monkeypatch.setattr(composability, "HORIZON_SECONDS", 0.18)
    cfg = OmegaConf.create({"controller": {"name": "fragments"}, "task": {"time_limit": 3.0, "control_timestep": 0.03}})
    scores = composability.cold_switching(cfg, episodes=2, hold=True)
    # episode 1: a, a's next, a->b at step 7 held through step 12, b->b at step 13 falls at once;
    # episode 2 starts with a random choice (9), not the successor (6) of the fragment that fell,
    # plays it on (10), and falls on its switch b->b at step 7
    assert envs.taken == [0, 1, 3, 4, 5, 9, 10, 12]
    assert scores["switches"] == {"a->b": {"survived": 1.0, "of": 1}, "b->b": {"survived": 0.0, "of": 2}}
    assert scores["episodes"] == 2 and scores["mean_steps"] == 10.0


def test_random_fragments_of_the_shipped_library_fall_within_seconds():
    from hvc.runtime.composability import cold_switching, composability_config

    scores = cold_switching(composability_config(compose(["stage=evaluate"]), "fragments"), episodes=5)
    assert scores["episodes"] == 5 and 0 < scores["median_steps"] < scores["cap"] == 1000
    behaviours = {"stand", "run", "left_turn", "right_turn"}
    assert scores["switches"] and all(set(pair.split("->")) <= behaviours for pair in scores["switches"])
    assert all(0.0 <= s["survived"] <= 1.0 and s["of"] > 0 for s in scores["switches"].values())

    held = cold_switching(composability_config(compose(["stage=evaluate"]), "fragments"), episodes=3, hold=True)
    assert held["hold"] and held["episodes"] == 3 and 0 < held["median_steps"] <= held["cap"]
    assert all(set(pair.split("->")) <= behaviours for pair in held["switches"])


def test_evaluate_prints_and_logs_both_drivers_for_fragments(tmp_path, capsys):
    import pandas as pd

    from hvc.io.metrics import MetricsLogger
    from hvc.runtime.evaluate_stage import composability

    with MetricsLogger(tmp_path / "metrics.csv") as metrics:
        scores = composability(compose(["stage=evaluate", "episodes=2"]), metrics)
    out = capsys.readouterr().out
    assert "compose controller=fragments clips=go_to_target episodes=2" in out
    assert "compose_held controller=fragments clips=go_to_target episodes=2" in out
    assert not scores["hold"] and scores["held"]["hold"] and scores["held"]["episodes"] == 2
    logged = pd.read_csv(tmp_path / "metrics.csv").set_index("key").value
    assert {"compose_median_steps", "compose_held_median_steps", "compose_held_fall_rate"} <= set(logged.index)


def test_evaluate_prints_a_median_between_two_lengths_as_logged(tmp_path, capsys, monkeypatch):
    import pandas as pd

    from hvc.io.metrics import MetricsLogger
    from hvc.runtime import composability as composability_module, evaluate_stage

    scores = {"episodes": 2, "mean_steps": 58.5, "median_steps": 58.5, "median_ci95": (57.0, 60.0), "fall_rate": 1.0,
              "cap": 1000, "horizon": 33, "switches": {}, "hold": False}
    monkeypatch.setattr(composability_module, "cold_switching", lambda *args, hold=False: dict(scores, hold=hold))
    with MetricsLogger(tmp_path / "metrics.csv") as metrics:
        evaluate_stage.composability(compose(["stage=evaluate", "episodes=2"]), metrics)
    out = capsys.readouterr().out
    assert "mean_steps=58.5 median_steps=58.5 median_ci95=57-60 " in out  # not rounded to the even 58
    logged = pd.read_csv(tmp_path / "metrics.csv").set_index("key").value
    assert logged["compose_median_steps"] == 58.5
    assert (logged["compose_median_ci95_low"], logged["compose_median_ci95_high"]) == (57.0, 60.0)


def test_the_survival_medians_interval_is_the_medians_not_the_means():
    from hvc.runtime.composability import median_interval

    skewed = np.array([10] * 70 + [1000] * 30)  # mean 307: an interval of the mean would lie far above 10
    assert median_interval(skewed) == (10.0, 10.0)
    low, high = median_interval(np.arange(1, 101))
    assert 40 < low < 50.5 < high < 61  # around the median, narrower than the data
    assert median_interval(np.arange(1, 101), seed=3) == median_interval(np.arange(1, 101), seed=3)
    assert median_interval(np.array([26])) == (26.0, 26.0)  # one episode: no resampling to do
