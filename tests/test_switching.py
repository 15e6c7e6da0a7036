"""Automatic cuts for the switching policy's reference sequences."""
import numpy as np
import pytest

from hvc.mocap.clips import root_heading
from hvc.mocap.source import SHARED_CLIPS
from hvc.mocap.switching import best_cut, markov_reference, splice

pytestmark = pytest.mark.skipif(not SHARED_CLIPS.is_dir(), reason=f"offline CMU clips not found at {SHARED_CLIPS}")


@pytest.fixture(scope="module")
def behaviours():
    from hvc.config import compose
    from hvc.mocap.reference import build_reference
    from hvc.mocap.clip_sets import entries_of, resolve
    from hvc.mocap.source import find_mocap_file

    mocap = str(find_mocap_file(None, "2019"))
    return [build_reference(e.as_dict(), mocap) for e in resolve(entries_of(compose([]).clips), mocap)]


def test_a_clip_cut_against_itself_matches_exactly(behaviours):
    run = behaviours[1]
    i, j, cost = best_cut(run, run, min_a=10)
    assert cost == pytest.approx(0.0, abs=1e-9) and i >= 10


def test_splice_continues_the_path_and_heading(behaviours):
    run, left = behaviours[1], behaviours[2]
    i, j, cost = best_cut(run, left, min_a=20)
    joined = splice(run, i, left, j)
    assert joined.num_steps == i + 1 + left.num_steps - j - 1
    step = np.linalg.norm(np.diff(joined.position[:, :2], axis=0), axis=1)
    assert step[i] < 3 * np.median(step)                       # no jump in the root path
    heading = root_heading(joined.quaternion)
    assert abs(heading[i + 1] - heading[i]) < 0.2               # nor in the heading
    joint_jump = np.abs(joined.joints[i + 1] - joined.joints[i]).mean()
    assert joint_jump <= cost + np.abs(np.diff(left.joints, axis=0)).mean(1).max()


def test_markov_walk_follows_the_transition_graph(behaviours):
    graph = {0: [1], 1: [2, 3, 0], 2: [1], 3: [1]}  # stand <-> run, run <-> turns
    ref, labels = markov_reference(behaviours, graph, steps=300, rng=np.random.default_rng(0), start=0)
    assert ref.num_steps == 300 == len(labels)
    changes = [(a, b) for a, b in zip(labels[:-1], labels[1:]) if a != b]
    assert changes and all(b in graph[a] for a, b in changes)
    assert np.all(np.isfinite(ref.position))


def test_a_walk_without_transitions_is_one_behaviour_as_its_clip_has_it(behaviours):
    """graph {b: []}: each episode one behaviour, to train one network as every behaviour's expert."""
    graph = {0: [], 1: [], 2: [], 3: []}
    rng = np.random.default_rng(0)
    seen = set()
    for _ in range(12):
        ref, labels = markov_reference(behaviours, graph, steps=300, rng=rng)
        b = int(labels[0])
        seen.add(b)
        assert np.all(labels == b) and ref.num_steps == len(labels) == behaviours[b].num_steps
        np.testing.assert_array_equal(ref.joints, behaviours[b].joints)
        np.testing.assert_array_equal(ref.phase, behaviours[b].phase)
    assert seen == {0, 1, 2, 3}
    # a walk stops at the first behaviour without next ones: run -> stand, then stand ends it
    ref, labels = markov_reference(behaviours, {0: [], 1: [0]}, steps=300, rng=rng, start=1)
    assert list(dict.fromkeys(labels)) == [1, 0] and ref.num_steps < 300


def test_spliced_references_keep_each_behaviours_time_input(behaviours):
    stand, run = behaviours[0], behaviours[1]
    i, j, _ = best_cut(stand, run, min_a=30)
    joined = splice(stand, i, run, j)
    np.testing.assert_allclose(joined.phase[:i + 1], stand.phase[:i + 1])
    np.testing.assert_allclose(joined.phase[i + 1:], run.phase[j + 1:])


def test_stand_to_run_ramps_the_speed_at_a_runners_acceleration(behaviours):
    """A cut from standing into a run must not ask for 3 m/s within one step."""
    stand, run = behaviours[0], behaviours[1]
    i, j, _ = best_cut(stand, run, min_a=30)
    max_accel = 4.0
    joined = splice(stand, i, run, j, max_accel=max_accel)
    own = max(np.abs(np.diff(r.velocity[:, :2], axis=0)).max() for r in (stand, run))
    dv = np.linalg.norm(np.diff(joined.velocity[:, :2], axis=0), axis=1)
    assert dv.max() <= max_accel * stand.dt + own
    assert np.linalg.norm(joined.velocity[-1, :2]) > 2.0        # ... and it does end up running
    # the root path is the integral of the stored velocity (no teleport at the ramp's end)
    step = np.diff(joined.position[:, :2], axis=0) / stand.dt
    np.testing.assert_allclose(step[i:i + 30], joined.velocity[i + 1:i + 31, :2], atol=0.3)
    with pytest.raises(ValueError, match="max_accel"):
        splice(stand, i, run, j, max_accel=0.0)


@pytest.fixture()
def switching_env():
    from omegaconf import OmegaConf

    from conftest import plain_cfg
    from hvc.config import compose
    from hvc.envs.fast_env import FastEnv
    from hvc.envs.switching_tracking import switching_clip
    from hvc.mocap.clip_sets import entries_of, resolve
    from hvc.mocap.source import find_mocap_file

    mocap = str(find_mocap_file(None, "2019"))
    overrides = ("stage=lowlevel", "task=tracking", "clips=switching")
    cfg = compose(list(overrides))
    task, body, render = plain_cfg(*overrides)
    task.update(clip=switching_clip(resolve(entries_of(cfg.clips), mocap),
                                    OmegaConf.to_container(cfg.clips.switching, resolve=True)), mocap_file=mocap)
    env = FastEnv.build(task, body, render, seed=0)
    yield env
    env.close()


def test_pretraining_labels_follow_each_episodes_own_walk(switching_env):
    """Each reset draws a new Markov walk: behaviour-cloning labels must come from it, not
    from the walk that was current when the dataset began (a 0.23 mean action error)."""
    from hvc.lowlevel.train import perturbed_dataset, reference_dataset

    env = switching_env
    logic, step, expected = env.layout.logic, env.step, []

    def watched_step(action):
        ref = logic.reference
        expected.append(np.clip(logic.pose_to_actuation(ref.joints[min(logic.t + 1, ref.num_steps - 1)]), -1, 1))
        return step(action)

    env.step = watched_step
    _, labels = perturbed_dataset(env, 4, 0.1, np.random.default_rng(0))
    np.testing.assert_allclose(labels, np.asarray(expected, np.float32), atol=1e-6)
    # the reference states come from several walks, each labelled with its own next poses
    obs, actions = reference_dataset(env, walks=3)
    assert len(obs) == 3 * (logic.reference.num_steps - 1)
    last = logic.reference  # the third walk's
    next_poses = np.stack([np.clip(logic.pose_to_actuation(q), -1, 1) for q in last.joints[-5:]])
    np.testing.assert_allclose(actions[-5:], next_poses, atol=1e-6)


def test_kickstarting_states_stop_at_each_walks_first_switch(switching_env):
    """The teachers' states for kickstarting come from their own behaviour only: a state at or
    after a walk's first cut would be labelled by an expert that never trained from there."""
    from hvc.agents.mlp import GaussianPolicy, NumpyPolicy
    from hvc.lowlevel.train import distillation_dataset

    env = switching_env
    logic, n = env.layout.logic, len(env.layout.logic.behaviours)
    size = env.layout.proprio.size + 1  # an expert sees proprioception and its phase
    experts = [NumpyPolicy.from_torch(GaussianPolicy(size, env.action_size, [8], 0.1)) for _ in range(n)]
    reset, step = env.reset, env.step

    def behaviours_per_walk(**kwargs) -> list[set[int]]:
        walks, steps = [], []
        env.reset = lambda: (walks.append(set()), reset())[1]
        env.step = lambda action: (walks[-1].add(int(logic.labels[logic.t])), steps.append(1), step(action))[2]
        obs, _ = distillation_dataset(env, experts, 8, 0.1, np.random.default_rng(0), **kwargs)
        assert len(obs) == len(steps) and len(walks) == 8  # one labelled state per step taken
        return walks

    assert all(len(w) == 1 for w in behaviours_per_walk(until_switch=True))
    assert any(len(w) > 1 for w in behaviours_per_walk())  # untruncated, these walks do switch


def test_each_behaviour_of_a_walk_starts_from_the_body_heading(switching_env):
    from hvc.envs.tracking_reward import quat_log_norm
    from hvc.mocap.clips import root_heading
    from hvc.rotations import quat_conj, quat_mul

    env = switching_env
    logic = env.layout.logic
    logic.random_start = False
    try:
        for _ in range(20):  # a walk whose first switch comes early enough to drive to
            env.reset()
            switches = np.flatnonzero(np.diff(logic.labels)) + 1
            if len(switches) and switches[0] < 60:
                break
        assert logic.anchors == frozenset(switches.tolist())
        first = int(switches[0])
        for t in range(first):  # open loop, drifting off the reference's heading on the way
            env.step(np.clip(logic.pose_to_actuation(logic.reference.joints[t + 1]), -1, 1) + 0.2)
        body_q = env.data.qpos[logic.root_qpos + 3:logic.root_qpos + 7]
        anchored = logic.reference.quaternion[first]
        gap = root_heading(body_q[None])[0] - root_heading(anchored[None])[0]
        assert abs((gap + np.pi) % (2 * np.pi) - np.pi) < 1e-6
        assert logic.t == first and logic.last_terms["ori"] == pytest.approx(  # this step's reward used it
            quat_log_norm(quat_mul(body_q, quat_conj(anchored))), abs=1e-9)
    finally:
        logic.random_start = True
