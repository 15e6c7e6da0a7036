import mujoco
import numpy as np
import pytest

from conftest import ENV_TASKS, plain_cfg
from hvc.envs.fast_env import FastEnv


@pytest.fixture(scope="module")
def envs():
    made = {}
    for task_name in ENV_TASKS:
        task, body, render = plain_cfg(f"task={task_name}", f"task.layout_pool={2 if task_name in ('walls', 'forage') else 1}")
        made[task_name] = FastEnv.build(task, body, render, seed=1)
    yield made
    for env in made.values():
        env.close()


@pytest.mark.parametrize("task_name", ENV_TASKS)
def test_reset_reuses_compiled_models_and_randomises(task_name, envs):
    env = envs[task_name]
    models = [id(layout.model) for layout in env.layouts]
    starts, layouts_used = [], set()
    for _ in range(6):
        obs = env.reset()
        layouts_used.add(id(env.model))
        assert np.isfinite(obs["proprio"]).all()
        root = env.layout.logic.placement.free_adr
        starts.append(env.data.qpos[root:root + 7].copy())
        assert env.data.time == 0.0 and not env.layout.logic.failure
    assert [id(layout.model) for layout in env.layouts] == models  # nothing recompiled
    assert layouts_used <= set(models)
    if task_name in ("walls", "forage"):
        assert len(layouts_used) == 2  # the pool is cycled
    if task_name in ("go_to_target", "forage"):
        assert len({tuple(np.round(s, 6)) for s in starts}) > 1  # spawn poses differ
    # the upright pose: standing on the floor, not inside it
    assert all(0.5 < start[2] < 1.5 for start in starts)


def test_go_to_target_moves_the_target_between_resets(envs):
    env = envs["go_to_target"]
    targets = set()
    for _ in range(4):
        obs = env.reset()
        site = env.layout.logic.site
        targets.add(tuple(np.round(env.model.site_pos[site], 6)))
        assert obs["task"].shape == (3,)
        assert np.all(np.abs(env.model.site_pos[site][:2]) <= 4.0)
    assert len(targets) == 4


def test_heterogeneous_forage_assigns_colour_rewards_at_random(envs):
    env = envs["heterogeneous_forage"]
    assignments = set()
    for _ in range(12):
        env.reset()
        assignments.add(tuple(env.layout.logic.reward_of_type))
    assert assignments == {(30.0, -10.0), (-10.0, 30.0)}


@pytest.mark.parametrize("task_name", ["gaps", "heterogeneous_forage"])
def test_camera_renders_a_meaningful_image(task_name, envs):
    env = envs[task_name]
    obs = env.reset()
    image = obs["image"]
    assert image.shape == (64, 64, 3) and image.dtype == np.uint8
    assert image.std() > 5 and len(np.unique(image.reshape(-1, 3), axis=0)) > 20  # not blank
    for _ in range(3):
        later = env.step(np.zeros(env.action_size))[0]["image"]
    assert not np.array_equal(image, later)  # the camera moves with the body


def test_heterogeneous_forage_balls_are_red_and_green_in_the_image():
    """Textures stay on in the fast settings: the colour cue must reach the agent."""
    task, body, render = plain_cfg("task=heterogeneous_forage", "body.camera=egocentric")
    env = FastEnv.build(task, body, render, seed=0)
    seen = np.zeros(2, bool)
    for _ in range(4):
        env.reset()
        placement = env.layout.logic.placement
        xy = env.data.qpos[placement.free_adr:placement.free_adr + 2].copy()
        for yaw in np.linspace(0, 2 * np.pi, 12, endpoint=False):  # look all around the room
            placement.place(env.data.qpos, xy, yaw)
            mujoco.mj_forward(env.model, env.data)
            img = env.render().astype(int)
            r, g, b = img[..., 0], img[..., 1], img[..., 2]
            seen[0] |= np.sum((r > 2 * g + 20) & (r > 2 * b + 20)) > 5
            seen[1] |= np.sum((g > 2 * r + 20) & (g > 2 * b + 20)) > 5
    env.close()
    assert seen.all(), f"red seen={seen[0]}, green seen={seen[1]}"


def test_rolling_ball_on_go_to_target():
    task, body, render = plain_cfg("task=go_to_target", "body=rolling_ball", "controller=end_to_end")
    env = FastEnv.build(task, body, render, seed=0)
    obs = env.reset()
    assert env.action_size == 2 and obs["task"].shape == (3,)
    for _ in range(20):
        obs, reward, discount, done = env.step(env.random_action())
    assert np.isfinite(obs["proprio"]).all() and reward in (0.0, 1.0)


def _starts(reset, env, placement, n=8):
    from hvc.mocap.clips import root_heading

    bank, headings, matched = placement.pose_bank, [], 0
    for _ in range(n):
        reset()
        joints = env.data.qpos[placement.joint_qpos]
        matched += bool(np.isclose(bank.joints, joints, atol=1e-9).all(axis=1).any())
        headings.append(root_heading(env.data.qpos[3:7][None])[0])
        assert 0.5 < env.data.qpos[2] < 1.3
    return matched, headings


@pytest.mark.parametrize("task_name", ["walls", "forage"])
def test_controlled_episodes_start_from_poses_of_the_controllers_skills(task_name):
    """The shipped library's references are the pose bank: no mocap file needed."""
    from hvc.config import compose
    from hvc.controllers.base import ControlledEnv
    from hvc.controllers.factory import build_controller
    from hvc.runtime.env_config import env_dicts
    from hvc.skills import skills_for_job

    cfg = compose([f"task={task_name}", "task.layout_pool=1", "clips=go_to_target"])  # a set with skills
    task, body, render = env_dicts(cfg)
    assert "init_clips" not in task  # the controller, not the mocap file, supplies the poses
    env = FastEnv.build(task, body, render, seed=0, render=False)
    controller = build_controller(dict(cfg.controller), env, skills_for_job(cfg))
    driven = ControlledEnv(env, controller)
    placement = env.layout.logic.placement
    assert len(placement.pose_bank) == sum(e.reference.num_steps for e in controller.library.experts)
    matched, headings = _starts(driven.reset, env, placement)
    env.close()
    assert matched == 8  # every start is a pose the experts track
    if task_name == "walls":
        np.testing.assert_allclose(headings, 0.0, atol=1e-9)  # facing down the corridor
    else:
        assert np.ptp(headings) > 1.0  # the maze spawns with random headings


@pytest.mark.skipif(not __import__("hvc.mocap.source", fromlist=["x"]).SHARED_CLIPS.is_dir(),
                    reason="offline CMU clips not found")
def test_end_to_end_episodes_start_from_poses_of_the_clip_set():
    from hvc.config import compose
    from hvc.runtime.env_config import env_dicts

    task, body, render = env_dicts(compose(["task=forage", "task.layout_pool=1", "controller=end_to_end"]))
    assert task["init_clips"] and task["mocap_file"]
    env = FastEnv.build(task, body, render, seed=0, render=False)
    matched, _ = _starts(env.reset, env, env.layout.logic.placement)
    env.close()
    assert matched == 8
