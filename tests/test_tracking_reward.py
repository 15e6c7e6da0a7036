"""The paper's tracking reward against hand-computed values."""
import numpy as np
import pytest

from hvc.config import compose
from hvc.envs.tracking_reward import TrackingFeatures, TrackingReward, energies, quat_log_norm

PAPER = dict(compose([]).reward)


def _features(**overrides):
    base = dict(joints=np.zeros(56), joints_velocity=np.zeros(56), quaternion=np.array([1.0, 0, 0, 0]),
                end_effectors=np.zeros((4, 3)), velocity=np.zeros(3), gyro=np.zeros(3))
    base.update(overrides)
    return TrackingFeatures(**base)


def test_paper_weights_are_configured():
    assert (PAPER["w_qpos"], PAPER["w_qvel"], PAPER["w_ori"], PAPER["w_ee"], PAPER["w_vel"], PAPER["w_gyro"],
            PAPER["beta"]) == (5, 1, 20, 2, 1, 1, 10)


def test_perfect_tracking_gives_one():
    rng = np.random.default_rng(0)
    q = rng.normal(size=4)
    ref = _features(joints=rng.normal(size=56), joints_velocity=rng.normal(size=56), quaternion=q / np.linalg.norm(q),
                    end_effectors=rng.normal(size=(4, 3)), velocity=rng.normal(size=3), gyro=rng.normal(size=3))
    reward, terms = TrackingReward(PAPER)(ref, ref)
    assert reward == pytest.approx(1.0) and all(v == pytest.approx(0.0, abs=1e-12) for v in terms.values())
    # q and -q are the same orientation
    flipped = _features(**{**ref.__dict__, "quaternion": -ref.quaternion})
    assert TrackingReward(PAPER)(flipped, ref)[0] == pytest.approx(1.0)


def test_joint_angle_error_alone():
    body = _features(joints=np.full(56, 0.1))
    reward, terms = TrackingReward(PAPER)(body, _features())
    assert terms["qpos"] == pytest.approx(0.1)
    assert reward == pytest.approx(np.exp(-10 * 5 * 0.1 / 30))


def test_orientation_error_is_half_the_rotation_angle():
    angle = 0.4  # rad about z
    body = _features(quaternion=np.array([np.cos(angle / 2), 0, 0, np.sin(angle / 2)]))
    reward, terms = TrackingReward(PAPER)(body, _features())
    assert terms["ori"] == pytest.approx(angle / 2)
    assert reward == pytest.approx(np.exp(-10 * 20 * (angle / 2) / 30))
    assert quat_log_norm(np.array([0.0, 1.0, 0, 0])) == pytest.approx(np.pi / 2)


def test_end_effector_velocity_and_gyro_terms():
    body = _features(end_effectors=np.array([[0.3, 0.4, 0.0], [0, 0, 0], [0, 0, 0], [0, 0, 1.0]]),
                     velocity=np.array([1.0, -2.0, 0.0]), gyro=np.array([3.0, 4.0, 0.0]),
                     joints_velocity=np.full(56, 2.0))
    terms = energies(body, _features(), PAPER["vel_scale"], PAPER["gyro_scale"])
    assert terms["ee"] == pytest.approx((0.5 + 1.0) / 4)
    assert terms["vel"] == pytest.approx(0.1 * 1.0)     # 0.1 * mean(|1|, |-2|, |0|)
    assert terms["gyro"] == pytest.approx(0.1 * 5.0)    # 0.1 * ||(3, 4, 0)||
    assert terms["qvel"] == pytest.approx(2.0)
    total = 2 * terms["ee"] + 1 * terms["vel"] + 1 * terms["gyro"] + 1 * terms["qvel"]
    assert TrackingReward(PAPER)(body, _features())[0] == pytest.approx(np.exp(-10 * total / 30))


def test_other_weightings_are_other_reward_files():
    only_joints = {**PAPER, "w_qvel": 0, "w_ori": 0, "w_ee": 0, "w_vel": 0, "w_gyro": 0}
    reward, _ = TrackingReward(only_joints)(_features(joints=np.full(56, 0.2), gyro=np.ones(3)), _features())
    assert reward == pytest.approx(np.exp(-10 * 0.2))


def test_velocity_and_gyro_scales_come_from_the_reward_file():
    body = _features(velocity=np.array([1.0, -2.0, 0.0]), gyro=np.array([3.0, 4.0, 0.0]))
    _, terms = TrackingReward({**PAPER, "vel_scale": 0.5, "gyro_scale": 0.2})(body, _features())
    assert (terms["vel"], terms["gyro"]) == (pytest.approx(0.5 * 1.0), pytest.approx(0.2 * 5.0))
    with pytest.raises(KeyError):  # one declaration of the scales: the reward file's
        TrackingReward({k: v for k, v in PAPER.items() if k != "gyro_scale"})


def test_end_effectors_flattened_or_not_give_the_same_error():
    ee = np.random.default_rng(1).normal(size=(4, 3))
    stacked = energies(_features(end_effectors=ee), _features(), 0.1, 0.1)["ee"]
    flat = energies(_features(end_effectors=ee.ravel()), _features(end_effectors=np.zeros(12)), 0.1, 0.1)["ee"]
    assert flat == pytest.approx(stacked) and stacked == pytest.approx(np.linalg.norm(ee, axis=1).mean())


def test_orientation_error_ignores_the_quaternions_scale():
    q = np.array([np.cos(0.3), 0, np.sin(0.3), 0])
    assert quat_log_norm(3.7 * q) == pytest.approx(quat_log_norm(q)) == pytest.approx(0.3)


def test_weights_must_sum_to_a_positive_number():
    zero = {**PAPER, **{f"w_{t}": 0.0 for t in ("qpos", "qvel", "ori", "ee", "vel", "gyro")}}
    with pytest.raises(ValueError, match="reward weights must sum to a positive number"):
        TrackingReward(zero)
    unit = {**zero, "w_qpos": 0.5, "w_ori": 0.5}  # weights summing to one are fine
    reward, _ = TrackingReward(unit)(_features(joints=np.full(56, 0.1)), _features())
    assert reward == pytest.approx(np.exp(-10 * 0.5 * 0.1))
