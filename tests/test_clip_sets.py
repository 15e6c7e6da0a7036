import math

import numpy as np
import pytest

from hvc.config import compose
from hvc.mocap.clip_sets import ClipEntry, entries_of, fragment_keys, fragments, select_entry
from hvc.mocap.reference import Reference


def test_fragments_cut_each_clip_into_ceil_n_over_t():
    entries = [ClipEntry("CMU_A", "stand", 0, 10), ClipEntry("CMU_B", "run", 5, 12), ClipEntry("CMU_C", "run",
                                                                                                 cyclic=True, steps=7)]
    frags = fragments(entries, 3)
    assert len(frags) == math.ceil(10 / 3) + math.ceil(7 / 3) + math.ceil(7 / 3)
    first = [f for f in frags if f.clip == 0]
    assert [f.start for f in first] == [0, 3, 6, 9] and [f.length for f in first] == [3, 3, 3, 1]
    assert len(fragments(entries, 1)) == 24 and len(fragments(entries, 100)) == 3
    with pytest.raises(ValueError, match="fragment_len"):
        fragments(entries, 0)


@pytest.mark.parametrize("clip_set,expected", [("go_to_target", 105), ("gaps", 359)])
def test_paper_fragment_counts_at_length_three(clip_set, expected):
    """Table A.2: the configured ranges reproduce the paper's fragment counts."""
    entries = entries_of(compose([f"clips={clip_set}"]).clips)
    assert len(fragments(entries, 3)) == expected


def test_clip_sets_name_ids_ranges_behaviours():
    for name in ("go_to_target", "forage", "heterogeneous_forage", "gaps", "go_to_target_x2", "go_to_target_x4",
                 "locomotion_8", "go_to_target_extraneous"):
        entries = entries_of(compose([f"clips={name}"]).clips)
        assert entries and all(e.id.startswith("CMU_") and e.behaviour for e in entries)
        assert all(e.num_steps > 0 for e in entries)
    base = entries_of(compose(["clips=go_to_target"]).clips)
    assert [e.behaviour for e in base] == ["stand", "run", "left_turn", "right_turn"]
    assert entries_of(compose(["clips=go_to_target_x2"]).clips) == base * 2
    assert entries_of(compose(["clips=go_to_target_x4"]).clips) == base * 4


def test_select_entry_by_id_behaviour_or_any_clip():
    clips = compose(["clips=go_to_target"]).clips
    assert select_entry(clips, None).behaviour == "stand"
    run = select_entry(clips, "run")
    assert run.cyclic and select_entry(clips, run.id) == run
    assert select_entry(clips, "CMU_999_01") == ClipEntry("CMU_999_01", "clip")


def test_fragment_keys_are_start_and_end_features():
    n = 12
    rng = np.random.default_rng(0)
    quats = np.tile([1.0, 0, 0, 0], (n, 1))
    ref = Reference("x", 0.03, False, np.zeros((n, 56)), np.zeros((n, 56)), np.zeros((n, 3)), quats,
                    rng.normal(size=(n, 3)), np.zeros((n, 3)), rng.normal(size=(n, 4, 3)), np.linspace(0, 1, n))
    keys = fragment_keys(ref, [0, 3, 9], 3)
    assert keys.shape == (3, 2 * (3 + 3 + 12))
    np.testing.assert_allclose(keys[1, :3], ref.velocity[3])          # identity orientation: world = root frame
    np.testing.assert_allclose(keys[1, 3:6], [0, 0, 1])               # gravity direction when upright
    np.testing.assert_allclose(keys[1, 18:21], ref.velocity[6])       # end state = start + length
    np.testing.assert_allclose(keys[2, 24:36], ref.end_effectors[11].ravel())  # clamped at the clip's end


def _turned_reference(quats, velocity, seed=0):
    n = len(quats)
    rng = np.random.default_rng(seed)
    return Reference("x", 0.03, False, np.zeros((n, 56)), np.zeros((n, 56)), np.zeros((n, 3)), np.asarray(quats),
                     np.asarray(velocity, float), np.zeros((n, 3)), rng.normal(size=(n, 4, 3)), np.linspace(0, 1, n))


def test_fragment_keys_give_the_velocity_in_the_root_frame_of_a_turned_body():
    """Keys describe a fragment from the body's point of view (Appendix A.4): running east
    while facing north is moving to the body's right, -y in its frame; a rotation applied the
    wrong way (world to root instead of root to world) gives +y, and only a turned root shows it."""
    yaw90 = [np.cos(np.pi / 4), 0, 0, np.sin(np.pi / 4)]  # the root's x axis along world +y
    ref = _turned_reference([yaw90] * 4, [[2.0, 0.0, 0.5]] * 4)
    keys = fragment_keys(ref, [0], 3)
    np.testing.assert_allclose(keys[0, :3], [0.0, -2.0, 0.5], atol=1e-12)
    np.testing.assert_allclose(keys[0, 3:6], [0, 0, 1], atol=1e-12)  # a pure turn leaves gravity along z


def test_fragment_keys_match_an_independent_rotation_and_ignore_the_world_heading():
    """Any root orientation: velocity and up direction rotated into the root frame as dm_control's
    transformations do it; and a whole clip turned about the vertical has the same keys (a query
    names a movement, not a compass direction)."""
    from dm_control.utils import transformations as tr

    rng = np.random.default_rng(3)
    n = 8
    quats = rng.normal(size=(n, 4))
    quats /= np.linalg.norm(quats, axis=1, keepdims=True)
    velocity = rng.normal(size=(n, 3))
    ref = _turned_reference(quats, velocity)
    keys = fragment_keys(ref, [0, 2, 5], 2)
    for row, s in enumerate([0, 2, 5]):
        for offset, t in ((0, s), (18, min(s + 2, n - 1))):
            inv = tr.quat_inv(quats[t])
            np.testing.assert_allclose(keys[row, offset:offset + 3], tr.quat_rotate(inv, velocity[t]), atol=1e-9)
            np.testing.assert_allclose(keys[row, offset + 3:offset + 6], tr.quat_rotate(inv, np.array([0., 0, 1])),
                                       atol=1e-9)
    yaw = np.array([np.cos(0.6), 0, 0, np.sin(0.6)])  # the whole clip turned 69 degrees about z
    turned = _turned_reference([tr.quat_mul(yaw, q) for q in quats], [tr.quat_rotate(yaw, v) for v in velocity])
    np.testing.assert_allclose(fragment_keys(turned, [0, 2, 5], 2), keys, atol=1e-9)


def test_includes_are_expanded_where_the_config_is_composed_not_read_by_mocap():
    """Composition lists the whole set once; clip_sets reads no config file and refuses a set
    whose includes nobody expanded (it would silently drop the included clips)."""
    from hvc.config import expand_clip_set, group_config

    raw = group_config("clips", "go_to_target_x2")
    with pytest.raises(ValueError, match="expand it first"):
        entries_of(raw)
    expand_clip_set(raw)
    composed = compose(["clips=go_to_target_x2"]).clips
    assert entries_of(raw) == entries_of(composed) == entries_of(compose(["clips=go_to_target"]).clips) * 2
    assert list(composed.included) == ["go_to_target", "go_to_target"] and not composed.include
    expand_clip_set(composed)  # twice: no change
    assert len(entries_of(composed)) == 2 * len(entries_of(compose(["clips=go_to_target"]).clips))


def test_a_clip_entry_survives_its_dict_form():
    """Library metadata stores entries as dicts; every field comes back."""
    entry = ClipEntry("CMU_016_22", "run", 3, 40, cyclic=True, steps=37, steer=True)
    assert entry.as_dict() == {"id": "CMU_016_22", "behaviour": "run", "start": 3, "end": 40, "cyclic": True,
                               "steps": 37, "steer": True}
    assert ClipEntry(**entry.as_dict()) == entry


def test_bad_clip_sets_fail_naming_the_set_the_keys_and_what_is_allowed():
    with pytest.raises(ValueError, match=r"clip set 'mine': unknown entry keys \['speed', 'stop'\]; allowed: "
                                         r"behaviour, cyclic, end, id, start, steer, steps$"):
        entries_of({"name": "mine", "entries": [{"id": "CMU_1", "behaviour": "run", "stop": 3, "speed": 1}]})
    with pytest.raises(ValueError, match=r"clip set 'mine' still lists include=\['gaps'\]"):
        entries_of({"name": "mine", "include": ["gaps"], "entries": []})
    with pytest.raises(ValueError, match=r"clip set 'empty' is empty; pass clip=<CMU id>"):
        select_entry({"name": "empty", "entries": []}, None)
    assert entries_of({"name": "none"}) == []


def test_resolve_fills_open_ranges_and_rejects_what_the_mocap_file_lacks(monkeypatch):
    import hvc.mocap.source
    from hvc.mocap.clip_sets import resolve
    from hvc.mocap.clips import ClipNotFoundError

    files = {"file.h5": {"CMU_A": 50, "CMU_B": 20}, "many.h5": {f"CMU_{i}": 9 for i in range(7)}, "empty.h5": {}}
    monkeypatch.setattr(hvc.mocap.source, "clip_lengths", lambda path: files[path])
    open_ended = ClipEntry("CMU_A", "run", 5, None, cyclic=True, steps=30, steer=True)
    resolved = resolve([open_ended, ClipEntry("CMU_B", "stand", 0, 20)], "file.h5")
    assert resolved == [ClipEntry("CMU_A", "run", 5, 50, True, 30, True), ClipEntry("CMU_B", "stand", 0, 20)]
    with pytest.raises(ClipNotFoundError, match=r"clip CMU_C \(jump\) is not in file.h5; it has 2 clips, "
                                                r"e.g. CMU_A, CMU_B"):
        resolve([ClipEntry("CMU_C", "jump")], "file.h5")
    with pytest.raises(ClipNotFoundError, match=r"it has 7 clips, e.g. CMU_0, CMU_1, CMU_2, CMU_3, CMU_4$"):
        resolve([ClipEntry("CMU_C", "jump")], "many.h5")
    with pytest.raises(ClipNotFoundError, match=r"is not in empty.h5; it has 0 clips$"):
        resolve([ClipEntry("CMU_C", "jump")], "empty.h5")
    for start, end in ((0, 21), (-1, 10), (20, None), (7, 7)):
        with pytest.raises(ValueError, match=r"clip CMU_B: steps \[.*\) outside its 20 steps"):
            resolve([ClipEntry("CMU_B", "stand", start, end)], "file.h5")
    assert resolve([ClipEntry("CMU_B", "stand", 19, 20)], "file.h5")[0].num_steps == 1
