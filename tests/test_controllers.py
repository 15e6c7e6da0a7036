"""Controllers drive the body: fragments run the right expert at the right time index."""
import numpy as np
import pytest
import torch

from conftest import plain_cfg
from hvc.agents.mlp import GaussianPolicy, NumpyPolicy
from hvc.controllers.base import ControlledEnv
from hvc.controllers.end_to_end import EndToEndController
from hvc.controllers.factory import ControllerUnavailable, build_controller
from hvc.controllers.fragments import FragmentsController
from hvc.controllers.query import QueryController
from hvc.envs.fast_env import FastEnv
from hvc.lowlevel.library import Expert, ExpertLibrary
from hvc.mocap.clip_sets import Fragment
from hvc.mocap.reference import Reference
from hvc.skills import Skills


def _reference(n, seed):
    rng = np.random.default_rng(seed)
    quat = np.tile([1.0, 0, 0, 0], (n, 1))
    return Reference(f"CMU_00{seed}_01", 0.03, False, rng.normal(size=(n, 56)), rng.normal(size=(n, 56)),
                     rng.normal(size=(n, 3)), quat, rng.normal(size=(n, 3)), rng.normal(size=(n, 3)),
                     rng.normal(size=(n, 4, 3)), np.linspace(0, 1, n))


@pytest.fixture(scope="module")
def library():
    experts = []
    for seed, n in ((1, 7), (2, 4)):
        torch.manual_seed(seed)
        policy = NumpyPolicy.from_torch(GaussianPolicy(137, 56, [32], 0.1))
        experts.append(Expert({"id": f"CMU_00{seed}_01", "behaviour": f"b{seed}", "start": 0, "end": n}, policy,
                              _reference(n, seed)))
    return ExpertLibrary(experts, {})


@pytest.fixture(scope="module")
def env():
    task, body, render = plain_cfg("task=go_to_target")
    made = FastEnv.build(task, body, render, seed=0)
    yield made
    made.close()


def test_fragments_run_each_expert_from_its_start_for_t_steps(library, env):
    controller = FragmentsController(Skills.from_library(library, 3))
    assert controller.action_space.n == 3 + 2  # ceil(7/3) + ceil(4/3)
    wrapped = ControlledEnv(env, controller)
    obs = wrapped.reset()
    assert wrapped.needs_action
    fragment = 1  # clip 0, start 3
    news = []
    for i in range(3):
        expert = library.experts[0]
        expected = expert.act(np.concatenate([obs["proprio"], [expert.reference.phase[3 + i]]]))
        obs, _, _, done, info = wrapped.step(fragment if wrapped.needs_action else None)
        np.testing.assert_allclose(env.data.ctrl[env.layout.actuators], np.clip(expected, -1, 1), atol=1e-6)
        news.append(info["new_action"])
    assert news == [True, False, False] and wrapped.needs_action
    # the last fragment of clip 1 (start 3, one step long)
    wrapped.step(4)
    assert controller.fragment_index == (1, 3) and wrapped.needs_action
    with pytest.raises(ValueError, match="needs a new high-level action"):
        wrapped.step(None)
    with pytest.raises(ValueError, match="outside"):
        controller.set_action(5)


@pytest.mark.parametrize("fragment_len,expected", [(1, 11), (2, 6), (10, 2)])
def test_fragment_count_follows_fragment_len(library, fragment_len, expected):
    assert FragmentsController(Skills.from_library(library, fragment_len)).action_space.n == expected


def test_query_selects_the_nearest_key(library, env):
    controller = QueryController(Skills.from_library(library, 3, "query"), k_nearest=2)
    assert controller.keys.shape == (5, 36) and controller.action_space.size == 36
    target = controller.keys[2] + 0.01
    nearest = controller.nearest(target)
    assert len(nearest) == 2 and 2 in nearest
    controller.set_action(target)
    assert controller.current == controller.fragments[2]


def test_end_to_end_passes_the_action_every_step(env):
    controller = EndToEndController(env.action_low, env.action_high)
    wrapped = ControlledEnv(env, controller)
    wrapped.reset()
    action = np.full(env.action_size, 2.0)
    _, _, _, _, info = wrapped.step(action)
    assert info["new_action"] and wrapped.needs_action
    np.testing.assert_allclose(env.data.ctrl[env.layout.actuators], env.action_high)  # clipped


def test_controllers_with_skills_say_what_they_need(env):
    for name in ("steerable", "switching", "fragments", "query"):
        with pytest.raises(ControllerUnavailable, match=f"controller={name} needs skills"):
            build_controller({"name": name}, env, None)


def _cyclic_expert(obs_size, n=12, cycle=4):
    torch.manual_seed(0)
    ref = _reference(n, 3)
    ref = Reference(ref.clip_id, ref.dt, True, *(getattr(ref, f) for f in (
        "joints", "joints_velocity", "position", "quaternion", "velocity", "angular_velocity", "end_effectors")),
        np.tile(np.arange(cycle) / cycle, n // cycle))
    return Expert({"id": ref.clip_id, "behaviour": "run"}, NumpyPolicy.from_torch(GaussianPolicy(obs_size, 56, [16], 0.1)),
                  ref)


def test_steerable_holds_a_rate_for_one_gait_cycle_from_the_matching_phase(env):
    from hvc.controllers.steerable import SteerableController

    expert = _cyclic_expert(136 + 2)
    controller = SteerableController(expert, (-1.5, 1.5))
    wrapped = ControlledEnv(env, controller)
    obs = wrapped.reset()
    body = obs["proprio"][:56]
    cycle_joints = expert.reference.joints[:4, controller.actuator_order]
    entry = int(np.argmin(np.abs(cycle_joints - body).mean(1)))  # the cycle step nearest the start pose
    news = []
    for step in range(8):
        phase = expert.reference.phase[(entry + step) % 4]
        expected = expert.act(np.concatenate([obs["proprio"], [phase, 1.5]]))
        obs, _, _, done, info = wrapped.step(np.array([3.0]) if wrapped.needs_action else None)  # clipped to 1.5
        np.testing.assert_allclose(env.data.ctrl[env.layout.actuators], np.clip(expected, -1, 1), atol=1e-6)
        news.append(info["new_action"])
    assert news == [True, False, False, False] * 2


def test_switching_enters_a_behaviour_at_the_best_matching_pose(env):
    from hvc.controllers.switching import SwitchingController

    expert = _cyclic_expert(136 + 1 + 2)
    behaviours = [_reference(6, 4), _reference(9, 5)]
    controller = SwitchingController(expert, behaviours, hold_steps=3)
    wrapped = ControlledEnv(env, controller)
    obs = wrapped.reset()
    joints = obs["proprio"][:56]
    order = controller.actuator_order
    entry = int(np.argmin(np.abs(behaviours[1].joints[:, order] - joints).mean(1)))
    expected = expert.act(np.concatenate([obs["proprio"], [behaviours[1].phase[entry]], [0.0, 1.0]]))
    wrapped.step(1)
    np.testing.assert_allclose(env.data.ctrl[env.layout.actuators], np.clip(expected, -1, 1), atol=1e-6)
    assert controller.current == 1 and controller.t == entry + 1
    wrapped.step(None), wrapped.step(None)
    assert wrapped.needs_action


def test_switching_holds_each_choice_one_gait_cycle_by_default():
    from dataclasses import replace

    from hvc.controllers.switching import SwitchingController

    stand = _reference(6, 4)
    run = replace(_reference(12, 5), cyclic=True, phase=np.tile(np.arange(5) / 5, 3)[:12])  # 5-step cycle
    assert SwitchingController(_cyclic_expert(136 + 1 + 2), [stand, run]).hold == 5
    assert SwitchingController(_cyclic_expert(136 + 1 + 2), [stand, run], hold_steps=3).hold == 3
    with pytest.raises(ValueError, match="controller.hold_steps"):
        SwitchingController(_cyclic_expert(136 + 1 + 2), [stand, stand])


def test_query_keys_are_normalised_per_dimension_and_the_query_space_is_bounded(library):
    """Queries live in the keys' standardised space (zero mean, unit spread per dimension) with
    the range the learner clips to; the fragments' own discrete space is kept for indices."""
    from hvc.envs.spaces import ActionSpace

    skills = Skills.from_library(library, 3, "query")
    controller = QueryController(skills, k_nearest=2)
    np.testing.assert_allclose(controller.keys.mean(0), 0.0, atol=1e-5)
    np.testing.assert_allclose(controller.keys.std(0)[skills.keys.std(0) > 1e-3], 1.0, atol=1e-3)
    np.testing.assert_allclose(controller.keys * controller.key_std + controller.key_mean, skills.keys, atol=1e-5)
    assert controller.action_space == ActionSpace(discrete=False, size=skills.keys.shape[1], low=-3.0, high=3.0)
    assert controller.selection_space == ActionSpace(discrete=True, n=len(controller.fragments))
    assert QueryController.from_config({"k_nearest": 4}, None, skills).k == 4


@pytest.mark.parametrize("k", [1, 2, 7, 40, 200, 300])
def test_query_candidates_are_exactly_the_k_nearest_keys(library, k):
    """Against a brute-force sort, among 200 random keys, for queries anywhere; k at or above
    the key count: all of them."""
    controller = QueryController(Skills.from_library(library, 3, "query"), k_nearest=k)
    rng = np.random.default_rng(k)
    controller.keys = rng.normal(size=(200, 8)).astype(np.float32)
    controller.k = min(k, 200)
    for _ in range(50):
        query = rng.normal(size=8).astype(np.float32)
        order = np.argsort(((controller.keys - query) ** 2).sum(1))
        assert sorted(controller.nearest(query)) == sorted(order[:controller.k])


def test_a_query_runs_its_nearest_fragment_and_an_index_runs_its_own(library):
    """Among the k candidates, the fragment whose key is nearest the query (20000 random keys
    standing in for the five fragments' own: numpy then leaves the candidates unsorted, so
    their order says nothing)."""
    controller = QueryController(Skills.from_library(library, 3, "query"), k_nearest=3)
    rng = np.random.default_rng(0)
    for _ in range(30):
        query = rng.normal(size=controller.keys.shape[1]).astype(np.float32) * 2
        controller.set_action(query)
        nearest = int(np.argmin(((controller.keys - query) ** 2).sum(1)))
        assert controller.current == controller.fragments[nearest]
    controller.keys, controller.k = rng.normal(size=(20000, 6)).astype(np.float32), 300
    controller.fragments = [Fragment(0, i, 1) for i in range(20000)]
    for _ in range(10):
        query = rng.normal(size=6).astype(np.float32)
        controller.set_action(query)
        assert controller.current.start == int(np.argmin(((controller.keys - query) ** 2).sum(1)))
    for index in (4, 0, 3):
        controller.set_action(np.int64(index))
        assert controller.current == controller.fragments[index]


def test_fragments_controller_states_before_during_and_after_a_fragment(library):
    """Before any choice (and after reset): nothing runs, an action is needed, records say -1;
    fragment 0 is a valid choice, and the indices past either end are refused by name."""
    from hvc.envs.spaces import ActionSpace

    skills = Skills.from_library(library, 3)
    controller = FragmentsController.from_config({}, None, skills)
    assert controller.action_space == ActionSpace(discrete=True, n=5)
    for _ in range(2):
        assert controller.current is None and controller.fragment_index is None
        assert controller.needs_action() and controller.record == -1.0
        controller.set_action(0)
        assert controller.fragment_index == (0, 0) and controller.record == 0.0 and not controller.needs_action()
        controller.reset()
    for bad in (-1, 5):
        with pytest.raises(ValueError, match=rf"^fragment {bad} outside 0\.\.4$"):
            controller.set_action(bad)


def test_a_clips_last_fragment_runs_to_the_references_last_phase(library, monkeypatch):
    """The expert's time input walks the fragment's steps, up to the clip's last step."""
    import hvc.controllers.fragments as fragments_module

    seen = []
    real = fragments_module.policy_observation
    monkeypatch.setattr(fragments_module, "policy_observation",
                        lambda obs: seen.append(float(obs["task"][0])) or real(obs))
    controller = FragmentsController(Skills.from_library(library, 3))
    last = max(i for i, f in enumerate(controller.fragments) if f.clip == 0)  # clip 0: 7 steps, last fragment [6, 7)
    fragment = controller.fragments[last]
    controller.set_action(last)
    phase = library.experts[0].reference.phase
    for _ in range(fragment.length):
        controller.body_action({"proprio": np.zeros(137 - 1, np.float32)})
    assert seen == [float(phase[t]) for t in range(fragment.start, fragment.start + fragment.length)]
    assert fragment.start + fragment.length == library.experts[0].reference.num_steps
