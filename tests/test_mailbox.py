"""The shared-memory mailbox between VectorEnv and its env workers (hvc.envs.mailbox)."""
import multiprocessing as mp
import time

import numpy as np
import pytest

from hvc.envs.mailbox import Mailbox, action_layout, observation_layout
from hvc.envs.spaces import ActionSpace

OBS = observation_layout({"proprio": 5, "task": 0, "image": (4, 3, 3)})


@pytest.fixture
def pair():
    """The parent's mailbox and a worker's view of the same block (one process is enough)."""
    semaphores = tuple(mp.get_context("spawn").Semaphore(0) for _ in range(2))
    actions = action_layout(ActionSpace(discrete=False, size=2, low=-1.0, high=1.0))
    parent = Mailbox(actions, OBS, semaphores)
    worker = Mailbox(actions, OBS, semaphores, parent.name)
    yield parent, worker
    worker.close()
    parent.close()


def _obs(rng):
    return {"proprio": rng.normal(size=5).astype(np.float32), "task": np.zeros(0, np.float32),
            "image": rng.integers(0, 255, (4, 3, 3)).astype(np.uint8)}


def test_a_step_crosses_both_ways_with_arrays_in_their_slots(pair):
    parent, worker = pair
    rng = np.random.default_rng(0)
    action = np.array([0.25, -0.5], np.float32)
    parent.post("step", arrays={"action": action})
    command, payload, arrays = worker.wait_command(lambda: True, 0.1)
    assert command == "step" and payload is None
    np.testing.assert_array_equal(arrays["action"], action)
    assert arrays["action"].dtype == np.float32
    obs = _obs(rng)
    worker.reply("ok", (0.5, 1.0, False, {"new_action": True}), arrays=obs)
    status, rest, got = parent.wait_reply(lambda: True, 0.1)
    assert status == "ok" and rest == (0.5, 1.0, False, {"new_action": True})
    for key in obs:
        np.testing.assert_array_equal(got[key], obs[key])
        assert got[key].dtype == obs[key].dtype
    # what the parent got is its own copy, not a view the next reply overwrites
    worker.reply("ok", None, arrays=_obs(rng))
    parent.wait_reply(lambda: True, 0.1)
    np.testing.assert_array_equal(got["proprio"], obs["proprio"])


def test_arrays_that_do_not_fit_their_slots_are_pickled_not_cut(pair):
    parent, worker = pair
    odd = {"proprio": np.arange(7, dtype=np.float64), "extra": np.ones(3)}  # wrong shape, dtype and keys
    worker.reply("ok", None, arrays=odd)
    _, _, got = parent.wait_reply(lambda: True, 0.1)
    assert got.keys() == odd.keys()
    np.testing.assert_array_equal(got["proprio"], odd["proprio"])
    assert got["proprio"].dtype == np.float64
    parent.post("step", arrays={"action": np.array(3)})  # an int where float32 x 2 is laid out
    _, _, arrays = worker.wait_command(lambda: True, 0.1)
    assert arrays["action"] == 3 and arrays["action"].dtype.kind == "i"


def test_a_message_too_large_is_an_error_naming_sizes(pair):
    parent, _ = pair
    with pytest.raises(ValueError, match="exceeds the mailbox"):
        parent.post("step", "x" * (1 << 19))


def test_a_dead_peer_ends_the_wait_instead_of_hanging(pair):
    parent, worker = pair
    t0 = time.perf_counter()
    with pytest.raises(EOFError):
        parent.wait_reply(lambda: False, 0.05)
    with pytest.raises(EOFError):
        worker.wait_command(lambda: False, 0.05)
    assert time.perf_counter() - t0 < 5


def test_layouts_follow_the_env_spec():
    assert observation_layout({"proprio": 136, "task": 3, "image": (64, 64, 3)}) == {
        "proprio": ((136,), "float32"), "task": ((3,), "float32"), "image": ((64, 64, 3), "uint8")}
    assert action_layout(ActionSpace(discrete=True, n=12)) == {"action": ((), "int64")}
