"""Each job resolves the skills of its own clip set and controller (hvc.skills)."""
import json

import pytest

from hvc.config import compose, group_options
from hvc.errors import ControllerUnavailable
from hvc.lowlevel.library import SHIPPED_DIR, ExpertLibrary
from hvc.skills import resolve_skills, skills_for_job


@pytest.mark.parametrize("clips,fragments", [("go_to_target", 105), ("go_to_target_x2", 210),
                                             ("go_to_target_x4", 420)])
def test_scaling_sets_assemble_from_the_shipped_experts(clips, fragments):
    skills = resolve_skills(compose([f"clips={clips}"]))
    assert len(skills.fragments) == fragments
    shipped = ExpertLibrary.load(SHIPPED_DIR / "experts_go_to_target.npz")
    # the copies are the shipped experts themselves, under the set's own behaviour names
    for i, expert in enumerate(skills.library.experts):
        assert expert.policy is skills.library.experts[i % 4].policy
        assert expert.reference.num_steps == shipped.experts[i % 4].reference.num_steps
    assert [e.entry["behaviour"] for e in skills.library.experts[:4]] == ["stand", "run", "left_turn", "right_turn"]


UNTRAINED = ["clips=go_to_target_x2", "clips.entries=[{id:CMU_131_14,behaviour:stand_c,start:42,end:84}]"]


def test_a_set_without_experts_names_the_missing_clips_and_the_command():
    """A set with a range no library has an expert of (go_to_target_x2 plus CMU_131_14 [42, 84),
    whatever ships): its 4 base behaviours have experts, the extra range has none."""
    with pytest.raises(ControllerUnavailable) as error:
        resolve_skills(compose([*UNTRAINED, "controller=fragments"]))
    message = str(error.value)
    assert "\n" not in message
    assert "clips=go_to_target_x2" in message and "CMU_131_14 [42, 84) (stand_c)" in message
    assert "CMU_131_09" not in message and "CMU_009_06" not in message  # stand and run: experts exist
    assert "hvc-run stage=lowlevel clips=go_to_target_x2" in message
    assert "libraries.go_to_target_x2=" in message


def test_entries_overridden_on_a_set_with_a_shipped_library_get_their_own_experts():
    """`clips.entries=` on go_to_target must not be served the 4 shipped experts: the two
    entries kept get their experts (34 + 36 fragments); a range no library has is refused."""
    kept = ("clips.entries=[{id:CMU_131_09,behaviour:stand,start:0,end:102},"
            "{id:CMU_009_06,behaviour:run,start:0,end:38,cyclic:true,steps:108}]")
    skills = resolve_skills(compose(["clips=go_to_target", kept]))
    assert [e.entry["id"] for e in skills.library.experts] == ["CMU_131_09", "CMU_009_06"]
    assert len(skills.fragments) == 34 + 36 and skills.source.startswith("assembled")
    with pytest.raises(ControllerUnavailable, match=r"CMU_131_14 \[42, 84\)"):
        resolve_skills(compose(["clips=go_to_target",
                                "clips.entries=[{id:CMU_131_14,behaviour:stand_c,start:42,end:84}]"]))


def test_evaluate_scores_the_experts_of_the_entries_it_is_given():
    """stage=evaluate without library= scores the set's skills as a job resolves them: the
    shipped four for go_to_target, the two kept entries' experts for an override of it."""
    from hvc.runtime.evaluate_stage import evaluated_library

    library, source = evaluated_library(compose(["stage=evaluate", "clips=go_to_target"]))
    assert len(library) == 4 and source == "shipped experts_go_to_target.npz"
    kept = ("clips.entries=[{id:CMU_131_09,behaviour:stand,start:0,end:102},"
            "{id:CMU_009_06,behaviour:run,start:0,end:38,cyclic:true,steps:108}]")
    library, source = evaluated_library(compose(["stage=evaluate", "clips=go_to_target", kept]))
    assert [e.entry["id"] for e in library.experts] == ["CMU_131_09", "CMU_009_06"]
    assert source.startswith("assembled")
    library, _ = evaluated_library(compose(["stage=evaluate", "clips=steerable"]))
    assert library.experts[0].entry.get("steer")


def test_a_switching_library_is_played_per_behaviour_by_fragments_and_query_only():
    """library=<switching npz> for fragments, query and stage=evaluate of a clip set: its four
    behaviours as experts (the policy with each code held); for the switching controller and
    clips=switching: the policy as it is."""
    from hvc.runtime.evaluate_stage import evaluated_library

    path = SHIPPED_DIR / "experts_switching.npz"
    switching = ExpertLibrary.load(path)
    for controller in ("fragments", "query"):
        skills = resolve_skills(compose([f"controller={controller}", f"library={path}"]))
        assert [e.entry for e in skills.library.experts] == switching.meta["switching_entries"]
        assert skills.library.meta["provenance"]["env_steps"] == switching.meta["provenance"]["env_steps"] * 4
        assert "switching" not in skills.library.meta and len(skills.fragments) == 105
    assert resolve_skills(compose(["controller=switching", f"library={path}"])).library.experts[0].entry["id"] == "switching"
    library, _ = evaluated_library(compose(["stage=evaluate", "clips=go_to_target", f"library={path}"]))
    assert [e.entry["behaviour"] for e in library.experts] == ["stand", "run", "left_turn", "right_turn"]
    library, _ = evaluated_library(compose(["stage=evaluate", "clips=switching", f"library={path}"]))
    assert len(library) == 1 and library.behaviours


def test_library_shipped_names_the_sets_shipped_library_in_every_stage():
    """`library=shipped` (what `-m library=shipped,<file>` compares a new library against) is the
    set's shipped file: for stage=evaluate, for a job's skills, and for a per-set library; a set
    that ships none fails in one line naming those that do."""
    from hvc.runtime.evaluate_stage import evaluated_library
    from hvc.runtime.inputs import check_inputs

    for clips in ("go_to_target", "gaps", "switching"):
        library, source = evaluated_library(compose(["stage=evaluate", f"clips={clips}", "library=shipped"]))
        assert source == str(SHIPPED_DIR / f"experts_{clips}.npz")
        assert len(library) == len(ExpertLibrary.load(SHIPPED_DIR / f"experts_{clips}.npz"))
    skills = resolve_skills(compose(["task=gaps", "library=shipped"]))
    assert skills.source == str(SHIPPED_DIR / "experts_gaps.npz") and len(skills.library) == 12
    steerable = compose(["controller=steerable", "libraries.steerable=shipped"])
    check_inputs(steerable)  # the up-front file check lets the name through, as for library=
    assert resolve_skills(steerable).source == str(SHIPPED_DIR / "experts_steerable.npz")
    # a set assembled from another set's library named so (x2 repeats go_to_target's clips)
    x2 = resolve_skills(compose(["clips=go_to_target_x2", "libraries.go_to_target=shipped"]))
    assert len(x2.library) == 8 and x2.source.startswith("assembled")
    with pytest.raises(ControllerUnavailable, match=r"no library ships for clips=go_to_target_x2; shipped: .*gaps"):
        evaluated_library(compose(["stage=evaluate", "clips=go_to_target_x2", "library=shipped"]))


def test_a_set_assembles_from_a_library_named_for_another_set(tmp_path):
    """An extra clip, trained elsewhere and passed as another set's library, joins the shipped
    go_to_target experts (the untrained set above, whatever ships)."""
    shipped = ExpertLibrary.load(SHIPPED_DIR / "experts_go_to_target.npz")
    from hvc.mocap.clip_sets import entries_of

    extra = [e for e in entries_of(compose(UNTRAINED).clips) if e.behaviour == "stand_c"]
    fake = ExpertLibrary([type(shipped.experts[0])(e.as_dict(), shipped.experts[0].policy,
                                                   shipped.experts[0].reference) for e in extra], {})
    path = fake.save(tmp_path / "extra.npz")
    skills = resolve_skills(compose([*UNTRAINED, f"libraries.forage={path}"]))
    assert len(skills.library) == 9  # the 4 base experts twice, and the extra clip
    assert skills.assembled_from["stand_c (CMU_131_14)"] == "extra.npz"
    assert skills.assembled_from["stand (CMU_131_09)"] == "experts_go_to_target.npz"


def test_a_library_named_for_the_set_wins_over_the_shipped_one(tmp_path):
    shipped = ExpertLibrary.load(SHIPPED_DIR / "experts_go_to_target.npz")
    path = shipped.subset([0, 1]).save(tmp_path / "experts_go_to_target.npz")
    skills = resolve_skills(compose([f"libraries.go_to_target={path}"]))
    assert len(skills.library) == 2 and skills.source == str(path)
    # a stage=lowlevel run dir holding one assembled library works as well
    assert len(resolve_skills(compose([f"libraries.go_to_target={tmp_path}"])).library) == 2


def test_steerable_and_switching_load_their_own_policies_never_the_clip_sets():
    for name in ("steerable", "switching"):
        skills = resolve_skills(compose([f"controller={name}"]))
        assert skills.clip_set == name and skills.source == f"shipped experts_{name}.npz"
        assert skills.fragments == []
    assert resolve_skills(compose(["controller=end_to_end"])) is None


def test_a_missing_named_library_fails_in_one_line(tmp_path):
    with pytest.raises(ControllerUnavailable, match="does not exist"):
        resolve_skills(compose([f"libraries.steerable={tmp_path / 'missing.npz'}", "controller=steerable"]))


def test_skills_are_resolved_once_per_job(monkeypatch, tmp_path):
    import hvc.skills as skills_module

    calls = []
    real = skills_module.resolve_skills
    monkeypatch.setattr(skills_module, "resolve_skills", lambda cfg: calls.append(1) or real(cfg))
    cfg = compose(["fragment_len=10"])
    first = skills_for_job(cfg)
    assert skills_for_job(compose(["fragment_len=10"])) is first and len(calls) == 1
    assert len(skills_for_job(compose(["fragment_len=1"])).fragments) == 102 + 108 + 43 + 58  # a new job: its own
    assert len(calls) == 2
    first.write(tmp_path)
    assert json.loads((tmp_path / "skills.json").read_text())["fragments"] == 11 + 11 + 5 + 6


def test_every_clip_set_has_a_libraries_key():
    cfg = compose([])
    assert set(group_options("clips")) <= set(cfg.libraries)


def test_one_library_for_a_sweep_over_clip_sets_is_refused_before_any_job(tmp_path):
    from hvc.config import ConfigError
    from hvc.skills import check_sweep_library

    sweep_file = ["--config-dir", "sweeps", "--config-name", "fragment_count", "-m"]
    with pytest.raises(ConfigError, match="differ in clips.*libraries.<set>=<file>"):
        check_sweep_library([*sweep_file, "library=x.npz"])
    with pytest.raises(ConfigError, match="differ in controller"):
        check_sweep_library(["-m", "controller=fragments,steerable", "library=x.npz"])
    check_sweep_library(["-m", "fragment_len=1,3,10", "library=x.npz"])  # one set: one library serves
    check_sweep_library([*sweep_file, "libraries.go_to_target_x2=x.npz"])
    check_sweep_library(["controller=steerable", "library=x.npz"])  # not a sweep
    check_sweep_library(["-m", "controller=fragments,steerable", "library=shipped"])  # each arm its own


def test_the_saved_config_of_a_run_older_than_per_set_libraries_resolves_its_skills():
    """stage=record replays runs whose config_resolved.yaml has no `libraries` key."""
    from omegaconf import OmegaConf

    saved = OmegaConf.to_container(compose(["controller=fragments"]), resolve=True)
    del saved["libraries"]
    assert len(skills_for_job(OmegaConf.create(saved)).fragments) == 105
