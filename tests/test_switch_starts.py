"""Switch starts (issue 23): experts train from states other skills' fragments leave the body in."""
import numpy as np
import pytest

from hvc.config import compose
from hvc.mocap.source import SHARED_CLIPS

pytestmark = pytest.mark.skipif(not SHARED_CLIPS.is_dir(), reason="offline CMU clips not found")


@pytest.fixture(scope="module")
def run_env():
    from hvc.envs.fast_env import FastEnv
    from hvc.lowlevel.library import ExpertLibrary, shipped_library
    from hvc.runtime.env_config import env_dicts

    task, body, render = env_dicts(compose(["stage=lowlevel", "clip=run"]), tracking=True)
    env = FastEnv.build(task, body, render, seed=0, render=False)
    yield env, ExpertLibrary.load(shipped_library())
    env.close()


def _heading(quaternion):
    from hvc.mocap.clips import root_heading

    return float(root_heading(np.asarray(quaternion)[None])[0])


def test_switch_states_stay_up_and_are_placed_at_the_references_place_and_heading(run_env):
    import mujoco

    from hvc.lowlevel.switch_starts import collect_switch_states

    env, library = run_env
    logic = env.layout.logic
    before = env.rng.bit_generator.state
    states = collect_switch_states(env, library.experts, 30, 3, np.random.default_rng(0))
    assert env.rng.bit_generator.state == before  # the training's streams are untouched
    root, dof = logic.root_qpos, logic.root_dof
    assert len(states) == 30 and np.allclose(states.qpos[:, root:root + 2], 0.0)
    assert np.allclose([_heading(q) for q in states.qpos[:, root + 3:root + 7]], 0.0, atol=1e-6)
    # not 30 copies of one reference pose: the chains moved the body
    assert np.ptp(states.qpos[:, logic.joint_qpos], axis=0).max() > 0.3
    ref = logic.reference
    logic.switch_states = states
    for i, t in [(0, 5), (7, 20), (29, ref.num_steps - 2)]:
        logic.place_state(env.data, states[i], t)
        mujoco.mj_forward(env.model, env.data)
        qpos, qvel = env.data.qpos, env.data.qvel
        np.testing.assert_allclose(qpos[root:root + 2], ref.position[t][:2])
        assert abs(np.angle(np.exp(1j * (_heading(qpos[root + 3:root + 7]) - _heading(ref.quaternion[t]))))) < 1e-6
        np.testing.assert_allclose(qpos[logic.joint_qpos], states.qpos[i, logic.joint_qpos])
        assert qpos[root + 2] == pytest.approx(states.qpos[i, root + 2])  # its own height
        assert np.linalg.norm(qvel[dof:dof + 3]) == pytest.approx(np.linalg.norm(states.qvel[i, dof:dof + 3]))
        np.testing.assert_allclose(qvel[dof + 3:dof + 6], states.qvel[i, dof + 3:dof + 6])  # local frame
        # the velocity turned with the body: the same in the body's own frame
        from hvc.rotations import quat_to_mat

        local = quat_to_mat(qpos[root + 3:root + 7]).T @ qvel[dof:dof + 3]
        stored = quat_to_mat(states.qpos[i, root + 3:root + 7]).T @ states.qvel[i, dof:dof + 3]
        np.testing.assert_allclose(local, stored, atol=1e-9)
        assert not logic.contact_failure(env.data)
    logic.switch_states = None


def test_resets_start_from_switch_states_at_the_configured_share(run_env):
    from hvc.lowlevel.switch_starts import collect_switch_states, switch_starts

    env, library = run_env
    logic = env.layout.logic
    states = collect_switch_states(env, library.experts, 10, 3, np.random.default_rng(1))
    bank = {tuple(np.round(q[logic.joint_qpos], 9)) for q in states.qpos}
    logic.switch_states = states

    def from_bank():
        env.reset()
        return tuple(np.round(env.data.qpos[logic.joint_qpos], 9)) in bank

    try:
        with switch_starts(env, 1.0):
            assert all(from_bank() for _ in range(10))
        with switch_starts(env, 0.0):
            assert not any(from_bank() for _ in range(10))
            np.testing.assert_allclose(env.data.qpos[logic.joint_qpos], logic.reference.joints[logic.t])
        with switch_starts(env, 0.5):
            share = np.mean([from_bank() for _ in range(200)])
        assert 0.38 < share < 0.62
        assert logic.switch_probability == 0.0  # restored after the block
    finally:
        logic.switch_states = None


def test_a_cut_in_starts_the_next_episode_where_another_skills_fragment_left_the_body(run_env):
    """The fragment played from where the body is, then one new episode from its end (placed at
    a random step of the reference); later resets start from the reference again."""
    import copy

    import mujoco

    from hvc.lowlevel.switch_starts import cut_in, play_fragment

    env, library = run_env
    logic, root = env.layout.logic, env.layout.logic.root_qpos
    env.reset()
    for _ in range(5):
        env.step(logic.pose_to_actuation(logic.reference.joints[logic.t + 1]))
    spec = mujoco.mjtState.mjSTATE_INTEGRATION
    saved = np.empty(mujoco.mj_stateSize(env.model, spec))
    mujoco.mj_getState(env.model, env.data, saved, spec)
    rng = np.random.default_rng(4)
    assert not play_fragment(env, library.experts, 3, copy.deepcopy(rng))
    expected = logic.heading_free_state(env.data)
    mujoco.mj_setState(env.model, env.data, saved, spec)
    mujoco.mj_forward(env.model, env.data)
    obs = cut_in(env, library.experts, 3, rng)
    t, ref = logic.t, logic.reference
    assert obs is not None and logic.next_start is None
    np.testing.assert_allclose(env.data.qpos[logic.joint_qpos], expected[0][logic.joint_qpos])
    np.testing.assert_allclose(env.data.qpos[root:root + 2], ref.position[t][:2])
    assert abs(np.angle(np.exp(1j * (_heading(env.data.qpos[root + 3:root + 7]) - _heading(ref.quaternion[t]))))) < 1e-6
    np.testing.assert_allclose(obs["task"], ref.phase[t:t + 1])
    env.reset()
    np.testing.assert_allclose(env.data.qpos[logic.joint_qpos], logic.reference.joints[logic.t])

    env.data.qpos[root + 2] = 0.05  # the body in the ground: the fragment falls at once
    mujoco.mj_forward(env.model, env.data)
    assert cut_in(env, library.experts, 3, rng) is None


def _train_stand(out, option: str, log_every: int, total_steps: int):
    """A tiny training of the stand expert, warm-started from the shipped one, with one extra
    lowlevel option; (its final evaluation, its metrics)."""
    import pandas as pd
    from omegaconf import OmegaConf

    from hvc.lowlevel.library import ExpertLibrary, shipped_library
    from hvc.lowlevel.train import train_expert
    from hvc.runtime.env_config import env_dicts

    stand = ExpertLibrary.load(shipped_library()).experts[0]
    assert stand.entry["behaviour"] == "stand"
    cfg = compose(["stage=lowlevel", "task=tracking", "clip=stand", "lowlevel.bc_steps=20",
                   "lowlevel.bc_rollouts=2", "lowlevel.min_replay_unrolls=5", "lowlevel.eval_episodes=3",
                   f"lowlevel.log_every={log_every}", "lowlevel.batch_size=4", f"lowlevel.{option}",
                   "lowlevel.switch_states=20", "lowlevel.warm_start_critic_steps=1000"])
    task, body, render = env_dicts(cfg)
    result = train_expert(task, body, render, OmegaConf.to_container(cfg.lowlevel), out, total_steps=total_steps,
                          warm_start=stand.policy)
    return result, pd.read_csv(out / "metrics.csv")


def test_an_expert_trained_with_switch_starts_is_scored_from_both_kinds_of_start(tmp_path):
    """Its training episodes start away from the reference (a lower step reward than the same
    run, warm-started from the shipped stand expert, without switch starts); its final
    evaluation scores both kinds of start."""
    rewards = {}
    for share in (0.0, 1.0):
        result, metrics = _train_stand(tmp_path / str(share), f"switch_starts={share}", 50, 150)
        assert ("eval_switch_completion" in result) == (share > 0) and "eval_completion" in result
        rewards[share] = metrics.query("key == 'step_reward'").value.mean()
    assert rewards[1.0] < 0.9 * rewards[0.0]


@pytest.mark.parametrize("clips", ["steerable", "switching"])
def test_the_structured_policies_tasks_start_from_switch_states_on_each_episodes_own_reference(run_env, clips):
    """The steerable and switching tasks draw a new reference at each reset (rates, a behaviour
    walk); a switch start is placed on that new reference, not on the previous episode's."""
    from omegaconf import OmegaConf

    from hvc.envs.fast_env import FastEnv
    from hvc.envs.switching_tracking import switching_clip
    from hvc.lowlevel.switch_starts import collect_switch_states, switch_starts
    from hvc.mocap.clip_sets import entries_of, resolve
    from hvc.mocap.source import find_mocap_file
    from hvc.runtime.env_config import env_dicts

    cfg = compose(["stage=lowlevel", "task=tracking", f"clips={clips}"])
    entries = resolve(entries_of(cfg.clips), str(find_mocap_file(None, "2019")))
    task, body, render = env_dicts(cfg, entries[0], tracking=True)
    if clips == "switching":
        task["clip"] = switching_clip(entries, OmegaConf.to_container(cfg.clips.switching, resolve=True))
    env = FastEnv.build(task, body, render, seed=0, render=False)
    try:
        logic = env.layout.logic
        root = logic.root_qpos
        logic.switch_states = collect_switch_states(env, run_env[1].experts, 8, 3, np.random.default_rng(2))
        bank = {tuple(np.round(q[logic.joint_qpos], 9)) for q in logic.switch_states.qpos}
        references = []
        with switch_starts(env, 1.0):
            for _ in range(4):
                env.reset()
                t, ref = logic.t, logic.reference
                references.append(ref.position.copy())
                assert tuple(np.round(env.data.qpos[logic.joint_qpos], 9)) in bank
                np.testing.assert_allclose(env.data.qpos[root:root + 2], ref.position[t][:2])
                turned = _heading(env.data.qpos[root + 3:root + 7]) - _heading(ref.quaternion[t])
                assert abs(np.angle(np.exp(1j * turned))) < 1e-6
        assert any(not np.array_equal(references[0], r) for r in references[1:])  # a new reference each time
    finally:
        env.close()


def test_an_expert_trained_with_cut_ins_hands_over_at_its_fragment_ends(tmp_path):
    """With cut_ins=1 every fragment of the expert's own ends in a cut-in unless its episode
    ended: about one per 3 env steps; they are logged with the share whose fragment fell, and
    the expert is scored from switch states too. Without cut-ins none are logged."""
    rows = {}
    for share in (0.0, 1.0):
        result, rows[share] = _train_stand(tmp_path / str(share), f"cut_ins={share}", 60, 180)
        assert ("eval_switch_completion" in result) == (share > 0)
    assert "cut_ins" not in set(rows[0.0].key)
    cuts = rows[1.0].query("key == 'cut_ins'").value
    falls = rows[1.0].query("key == 'cut_in_falls'").value
    assert len(cuts) == 3 and (cuts > 0.6 * 60 / 3).all() and (cuts <= 60 / 3).all()
    assert ((falls >= 0) & (falls <= 1)).all()


def test_a_push_moves_the_root_its_way_for_its_steps_and_ends_with_the_episode(run_env):
    """A push acts for exactly push_steps control steps: the root's velocity gains the push's
    impulse in its direction against the same steps without it; the force is gone afterwards,
    after stop() and in a new episode; a fall within a second of the push is laid to it."""
    from hvc.lowlevel.pushes import Pushes

    env, library = run_env
    logic = env.layout.logic
    run = next(e for e in library.experts if e.entry["behaviour"] == "run")

    def velocities(probability):
        env.rng = np.random.default_rng(3)
        pushes = Pushes(probability, 400.0, 3, logic.root, np.random.default_rng(0), fall_window=33)
        from hvc.lowlevel.library import policy_observation

        obs, out, forces = env.reset(), [], []
        for _ in range(5):
            started = pushes.before_step(env)
            if started:
                pushes.probability = 0.0  # one push only
            forces.append(env.data.xfrc_applied[logic.root, :3].copy())
            obs, _, _, _ = env.step(run.act(policy_observation(obs)))
            out.append(env.data.qvel[logic.root_dof:logic.root_dof + 3].copy())
        assert pushes.fall_follows_push() == (probability > 0)
        pushes.stop(env.data)
        assert not env.data.xfrc_applied.any() and not pushes.fall_follows_push()
        # a push under way when the episode ends does not carry into the next one
        pushes.probability = probability
        pushes.before_step(env)
        env.step(run.act(policy_observation(env.observation())))
        env.reset()
        pushes.probability = 0.0
        pushes.before_step(env)
        assert not env.data.xfrc_applied.any() and not pushes.fall_follows_push()
        return np.array(out), np.array(forces)

    still, no_force = velocities(0.0)
    pushed, forces = velocities(1.0)
    assert not no_force.any()
    assert (np.linalg.norm(forces[:3], axis=1) == pytest.approx(400.0)) and not forces[3:].any()
    direction = forces[0] / 400.0
    assert forces[0][2] == 0 and (forces[:3] == forces[0]).all()
    gained = (pushed[2] - still[2]) @ direction  # after the 3 pushed steps (0.09 s)
    impulse = 400.0 * 3 * env.control_timestep / env.model.body_subtreemass[logic.root]
    assert 0.5 * impulse < gained < 1.5 * impulse


def test_an_expert_trained_with_pushes_logs_them_and_without_none(tmp_path):
    """pushes=1 starts a push whenever none acts (one per push_steps env steps), logged with the
    share followed by a fall; the final evaluation does not push (its keys are the usual ones)."""
    rows = {}
    for share in (0.0, 1.0):
        result, rows[share] = _train_stand(tmp_path / str(share), f"pushes={share}", 60, 240)
        assert "eval_switch_completion" not in result and "eval_completion" in result
    assert "pushes" not in set(rows[0.0].key)
    counts = rows[1.0].query("key == 'pushes'").value
    falls = rows[1.0].query("key == 'push_falls'").value
    # about one push per push_steps (3) env steps of each logged window (windows end at unroll ends, past 60; a
    # push cut short by a fall is followed by a new one)
    windows = np.diff(rows[1.0].query("key == 'pushes'").env_steps.to_numpy())
    assert len(counts) >= 3 and (windows >= 60).all()
    assert (counts.to_numpy()[1:] >= windows / 3 - 2).all() and (counts.to_numpy()[1:] <= windows / 3 + 2).all()
    assert ((falls >= 0) & (falls <= 1)).all()
    # pushed hard every step, the stand falls more: lower step reward than unpushed
    assert rows[1.0].query("key == 'step_reward'").value.mean() < rows[0.0].query("key == 'step_reward'").value.mean()
