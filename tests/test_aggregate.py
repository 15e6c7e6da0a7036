"""Aggregation over seeds on hand-made run dirs with known numbers: means, standard errors,
IQM, unequal lengths, a failed job, a missing seed, resumed runs, and the one command."""
import json
import math
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import yaml

from hvc.analysis import curves, final_scores, iqm_table, load_runs
from hvc.analysis.runs import last_timeline, run_status

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "analysis"))


def make_run(root: Path, name: str, options: dict, ret, steps: int = 1000, every: int = 10,
             status: str = "finished", random: float = 0.5) -> Path:
    """A run dir as hvc-run writes it: overrides.yaml, config_resolved.yaml, metrics.csv
    (one episode ending every `every` env steps with return `ret(env_steps)`), summary.json
    when finished, failed.json when failed."""
    run = root / name
    run.mkdir(parents=True)
    (run / "overrides.yaml").write_text(yaml.safe_dump([f"{k}={v}" for k, v in options.items()]))
    (run / "config_resolved.yaml").write_text(yaml.safe_dump(
        {"controller": {"name": options.get("controller", "fragments")}, "task": {"name": "go_to_target"},
         "seed": options.get("seed", 0), "fragment_len": 3}))
    rows = [(0, 0, 0.0, "random_return", random)]
    for i, t in enumerate(range(every, steps + 1, every)):
        rows += [(t, 4 * t, float(t), "episodes", i + 1), (t, 4 * t, float(t), "episode_return", ret(t)),
                 (t, 4 * t, float(t), "loss", 7.0)]
    pd.DataFrame(rows, columns=["env_steps", "learner_steps", "wall_time", "key", "value"]).to_csv(
        run / "metrics.csv", index=False)
    if status == "finished":
        (run / "summary.json").write_text(json.dumps({"env_steps": steps}))
    if status == "failed":
        (run / "failed.json").write_text(json.dumps({"error": "bad value", "kind": "error"}))
    return run


@pytest.fixture
def sweep(tmp_path):
    """Arm fragment_len=1: seeds return 1, 2, 3 throughout; arm 3: seeds return 10 and 20,
    seed 1 stopped at half the budget; seed 2 of arm 3 failed before any episode."""
    for seed, value in enumerate((1.0, 2.0, 3.0)):
        make_run(tmp_path, f"fl1_s{seed}", {"fragment_len": 1, "seed": seed}, lambda t, v=value: v)
    make_run(tmp_path, "fl3_s0", {"fragment_len": 3, "seed": 0}, lambda t: 10.0)
    make_run(tmp_path, "fl3_s1", {"fragment_len": 3, "seed": 1}, lambda t: 20.0, steps=500, status="stopped")
    failed = tmp_path / "fl3_s2"
    failed.mkdir()
    (failed / "overrides.yaml").write_text(yaml.safe_dump(["fragment_len=3", "seed=2"]))
    (failed / "failed.json").write_text(json.dumps({"error": "no skills", "kind": "error"}))
    return tmp_path


def test_load_runs_gives_each_run_its_swept_values_and_status(sweep):
    frame = load_runs([sweep])
    runs = frame.groupby("run").first()
    assert sorted(frame.attrs["factors"]) == ["fragment_len", "seed"]
    assert runs.loc[str(sweep / "fl1_s2"), "fragment_len"] == 1 and runs.loc[str(sweep / "fl1_s2"), "seed"] == 2
    assert runs.status.value_counts().to_dict() == {"finished": 4, "stopped": 1, "failed": 1}
    assert runs.loc[str(sweep / "fl3_s2"), "status"] == "failed"   # shows, with no metrics rows
    assert set(frame.key.dropna()) == {"random_return", "episodes", "episode_return", "loss"}


def test_an_arm_that_kept_the_default_gets_its_configs_value(tmp_path):
    """A comparison against a default (library=<file> against the shipped library, a swept
    key the baseline never set) has two arms, not one arm and a gap."""
    make_run(tmp_path, "shipped_s0", {"seed": 0}, lambda t: 1.0)
    make_run(tmp_path, "new_s0", {"seed": 0, "library": "new.npz", "lowlevel.sigma": 0.2}, lambda t: 2.0)
    config = tmp_path / "shipped_s0" / "config_resolved.yaml"
    cfg = yaml.safe_load(config.read_text())
    config.write_text(yaml.safe_dump({**cfg, "library": None, "lowlevel": {"sigma": 0.1}}))
    runs = load_runs([tmp_path]).groupby("run").first()
    assert runs.loc[str(tmp_path / "shipped_s0"), "library"] == "default"
    assert runs.loc[str(tmp_path / "shipped_s0"), "lowlevel.sigma"] == 0.1
    assert runs.loc[str(tmp_path / "new_s0"), "library"] == "new.npz"
    frame = load_runs([tmp_path])
    assert sorted(frame.attrs["factors"]) == ["library", "lowlevel.sigma"]  # with gaps, neither was one
    table = iqm_table(final_scores(frame), ["library", "lowlevel.sigma"])
    assert sorted(zip(table.library, table["lowlevel.sigma"], table.iqm)) == [("default", 0.1, 1.0), ("new.npz", 0.2, 2.0)]
    with pytest.raises(ValueError, match="lowlevel.sigma"):  # the two arms differ in sigma too
        curves(frame, ["library"])


def test_factor_levels_come_from_each_runs_config_whatever_was_typed(tmp_path):
    """`1e-3` typed is the 0.001 another run kept; a section given by name is its name; a key
    one run deleted is `absent`, not a gap that would average two arms; execution options
    (device, ray.*) never split arms."""
    for name, options, config in [
            ("typed", {"seed": 0, "lowlevel.bc_lr": "1e-3", "device": "cpu", "ray.address": "h:1"},
             {"lowlevel": {"bc_lr": 0.001, "sigma": 0.1}, "render": {"name": "fast"}}),
            ("kept", {"seed": 1, "render": "default"},
             {"lowlevel": {"bc_lr": 0.001, "sigma": 0.1}, "render": {"name": "default"}}),
            ("deleted", {"seed": 2, "~lowlevel.sigma": ""},
             {"lowlevel": {"bc_lr": 0.001}, "render": {"name": "fast"}})]:
        run = make_run(tmp_path, name, options, lambda t: 1.0)
        path = run / "config_resolved.yaml"
        path.write_text(yaml.safe_dump({**yaml.safe_load(path.read_text()), **config}))
    frame = load_runs([tmp_path])
    runs = frame.groupby("run").first()
    assert set(runs["lowlevel.bc_lr"]) == {0.001}
    assert runs["render"].to_dict() == {str(tmp_path / n): v for n, v in
                                        (("typed", "fast"), ("kept", "default"), ("deleted", "fast"))}
    assert runs.loc[str(tmp_path / "deleted"), "lowlevel.sigma"] == "absent"
    assert sorted(frame.attrs["factors"]) == ["lowlevel.sigma", "render", "seed"]


def test_curves_average_seeds_with_standard_errors(sweep):
    c = curves(load_runs([sweep]), ["fragment_len"], x="env_steps", points=10)
    one = c[c.fragment_len == 1]
    assert len(one) == 10 and (one.n_seeds == 3).all()
    np.testing.assert_allclose(one["mean"], 2.0)
    np.testing.assert_allclose(one.se, 1 / math.sqrt(3))          # std (ddof 1) of 1, 2, 3 over sqrt(3)
    assert one.env_steps.max() == 1000


def test_a_shorter_seed_is_never_averaged_silently(sweep):
    frame = load_runs([sweep])
    three = curves(frame, ["fragment_len"], x="env_steps", points=10).query("fragment_len == 3")
    assert (three.n_runs == 2).all() and (three.n_seeds == 2).all()   # the failed seed is not a run here
    assert three.env_steps.max() == 500                                # where both seeds reach
    np.testing.assert_allclose(three["mean"], 15.0)
    partial = curves(frame, ["fragment_len"], x="env_steps", points=10, complete=False).query("fragment_len == 3")
    late = partial[partial.env_steps > 500]
    assert (late.n_seeds == 1).all() and late.se.isna().all()
    np.testing.assert_allclose(late["mean"], 10.0)


def test_curves_refuse_to_average_arms_that_differ_in_more_than_the_seed(sweep):
    with pytest.raises(ValueError, match="fragment_len"):
        curves(load_runs([sweep]), [])


def test_final_iqm_with_bootstrap_interval_counts_statuses(sweep, tmp_path):
    make_run(sweep, "fl1_s3", {"fragment_len": 1, "seed": 3}, lambda t: 100.0)   # an outlier seed
    scores = final_scores(load_runs([sweep]))
    table = iqm_table(scores, ["fragment_len"]).set_index("fragment_len")
    assert table.loc[1, "iqm"] == pytest.approx(2.5)          # middle half of 1, 2, 3, 100
    assert table.loc[1, "ci_low"] <= 2.5 <= table.loc[1, "ci_high"] and table.loc[1, "ci_high"] <= 100
    assert table.loc[1, "random"] == pytest.approx(0.5)
    three = table.loc[3]
    assert (three.n_runs, three.n_finished, three.n_stopped, three.n_failed) == (1, 1, 1, 1)
    assert three.iqm == pytest.approx(10.0)                   # the stopped and failed seeds are not zeros


def test_an_arms_interval_is_the_same_on_every_call_and_beside_any_other_arm():
    """Committed CIs must not change when a notebook reruns or an arm is added to its table."""
    def scores(arms):
        return pd.DataFrame([{"arm": arm, "status": "finished", "score": float(v), "env_steps": 100, "random": 0.0}
                             for arm, values in arms.items() for v in values])

    a = {"a": [1.0, 4.0, 9.0, 16.0, 25.0, 36.0]}
    first = iqm_table(scores(a), ["arm"]).set_index("arm")
    np.random.seed(123)  # whatever the global RNG holds before, and it is left as it was
    before = np.random.get_state()[1].copy()
    again = iqm_table(scores({**a, "b": [2.0, 3.0, 50.0]}), ["arm"]).set_index("arm")
    np.testing.assert_array_equal(np.random.get_state()[1], before)
    assert first.loc["a", "ci_low"] < first.loc["a", "iqm"] < first.loc["a", "ci_high"]
    assert (again.loc["a", ["iqm", "ci_low", "ci_high"]] == first.loc["a", ["iqm", "ci_low", "ci_high"]]).all()


def test_final_score_is_the_mean_per_episode_over_the_last_tenth(tmp_path):
    make_run(tmp_path, "r", {"seed": 0}, lambda t: 0.0 if t <= 900 else t / 10.0)
    score = final_scores(load_runs([tmp_path])).score.iloc[0]
    assert score == pytest.approx(np.mean([t / 10.0 for t in range(910, 1001, 10)]))


def test_a_resumed_run_is_read_from_its_last_timeline(tmp_path):
    run = make_run(tmp_path, "r", {"seed": 0}, lambda t: 1.0, steps=100)
    later = pd.DataFrame([(t, t, 1000.0 + t, k, v) for t in (60, 70, 80, 90, 100)
                          for k, v in (("episodes", t / 10 + 1), ("episode_return", 5.0))],
                         columns=["env_steps", "learner_steps", "wall_time", "key", "value"])
    later.to_csv(run / "metrics.csv", mode="a", header=False, index=False)   # resumed at 50
    frame = load_runs([tmp_path], keys=["episodes", "episode_return"])
    assert frame.env_steps.is_monotonic_increasing
    assert (frame[frame.env_steps > 50].value[frame.key == "episode_return"] == 5.0).all()


def test_a_locked_run_dir_is_running(tmp_path):
    import fcntl

    run = make_run(tmp_path, "r", {"seed": 0}, lambda t: 1.0, status="stopped")
    assert run_status(run) == "stopped"
    with open(run / ".lock", "w") as f:
        fcntl.flock(f, fcntl.LOCK_EX)
        assert run_status(run) == "running"


def test_arm_labels_name_files_by_their_last_parts_and_keep_the_key_of_defaults():
    from hvc.analysis.plots import _label

    assert _label(["controller", "fragment_len"], ("fragments", 3)) == "fragments, fragment_len=3"
    assert _label(["library"], "default") == "library=default"
    assert (_label(["library"], "docs/results/skills/go_to_target_switch_starts/experts_go_to_target.npz")
            == "library=go_to_target_switch_starts/experts_go_to_target.npz")


def test_plot_sweep_scores_the_whole_run_with_last_1(tmp_path, capsys):
    """--last 1 is how fast an arm learned: a run at 0 for its first half and 10 after scores 10
    over its last 10% and 5 over all of it (each episode weighted once); outside (0, 1] is refused."""
    import plot_sweep

    for seed in (0, 1):
        make_run(tmp_path / "runs", f"s{seed}", {"seed": seed}, lambda t: 0.0 if t <= 500 else 10.0)
    rows = {}
    for last in ("0.1", "1"):
        plot_sweep.main([str(tmp_path / "runs"), "--last", last, "-o", str(tmp_path / f"{last}.png")])
        table = capsys.readouterr().out.splitlines()
        rows[last] = dict(zip(table[0].split(), table[1].split()))
    assert float(rows["0.1"]["iqm"]) == 10 and float(rows["1"]["iqm"]) == 5
    with pytest.raises(SystemExit):
        plot_sweep.main([str(tmp_path / "runs"), "--last", "0", "-o", str(tmp_path / "x.png")])


def test_arms_whose_files_end_alike_get_labels_that_tell_them_apart():
    from hvc.analysis.plots import _labels

    a, b = ("runs/a/skills/experts_go_to_target.npz",), ("runs/b/skills/experts_go_to_target.npz",)
    assert _labels(["library"], [a, b]) == ["library=a/skills/experts_go_to_target.npz",
                                            "library=b/skills/experts_go_to_target.npz"]
    c = ("other/experts_go_to_target.npz",)
    assert _labels(["library"], [a, c, a])[0] == "library=skills/experts_go_to_target.npz"  # two parts suffice
    assert _labels(["library"], [("a/b.npz",), ("./a/b.npz",)]) == ["library=a/b.npz", "library=./a/b.npz"]
    assert _labels(["fragment_len"], [(float("nan"),), (3.0,)]) == ["fragment_len=nan", "fragment_len=3.0"]


def test_a_figure_of_several_dirs_is_titled_by_their_common_folder(tmp_path):
    import plot_sweep

    a, b = tmp_path / "figs" / "a" / "runs", tmp_path / "figs" / "b"
    assert plot_sweep._title([a]) == str(a)
    title = plot_sweep._title([a, b])
    assert title.endswith("figs (2 dirs)") and "runs" not in title


def test_plot_sweep_draws_one_curve_per_arm_with_bands(sweep, tmp_path, capsys):
    import matplotlib.pyplot as plt
    import plot_sweep

    out = plot_sweep.main([str(sweep), "--by", "fragment_len", "-o", str(tmp_path / "fig.png")])
    assert out.stat().st_size > 5000
    fig = plt.gcf()
    legend = [t.get_text() for t in fig.legends[0].get_texts()]
    assert legend == ["fragment_len=1 (3 seeds)", "random policy (dashed)", "fragment_len=3 (2 seeds)"]
    assert len(fig.axes[0].collections) == 2                        # one standard-error band per arm
    table = capsys.readouterr().out
    assert "n_failed" in table and "iqm" in table
    with pytest.raises(SystemExit):
        plot_sweep.main([str(sweep), "--by", "controler", "-o", str(tmp_path / "x.png")])


def make_evaluation(root: Path, name: str, library: str | None, rewards: dict, survival: tuple | None) -> Path:
    """An evaluate run dir as hvc-run writes it: each clip's scores, then the composability
    measures, all at step 0 and one wall time after another."""
    run = root / name
    run.mkdir(parents=True)
    (run / "overrides.yaml").write_text(yaml.safe_dump(["stage=evaluate"] + ([f"library={library}"] if library else [])))
    (run / "config_resolved.yaml").write_text(yaml.safe_dump({"stage": "evaluate", "library": library}))
    rows = []
    for i, (clip, reward) in enumerate(rewards.items()):
        rows += [(0, 0, 10.0 * (i + 1), f"reward/{clip}", reward), (0, 0, 10.0 * (i + 1), f"completion/{clip}", 1.0)]
    if survival:
        keys = ("compose_mean_steps", "compose_median_steps", "compose_fall_rate")
        rows += [(0, 0, 100.0, k, v) for k, v in zip(keys, (*survival, 1.0))]
        rows += [(0, 0, 200.0, "compose_held_mean_steps", 2 * survival[0]),
                 (0, 0, 200.0, "compose_held_median_steps", 2 * survival[1])]
    pd.DataFrame(rows, columns=["env_steps", "learner_steps", "wall_time", "key", "value"]).to_csv(
        run / "metrics.csv", index=False)
    (run / "summary.json").write_text("{}")
    return run


def test_an_evaluate_runs_rows_all_at_step_0_are_all_read(tmp_path):
    """Each clip's scores are logged at step 0 one after another: none supersedes another (a
    resume is a step or the wall time going back), and a final evaluation logged at a training
    run's last step keeps that step's training rows."""
    make_evaluation(tmp_path / "ev", "a", None, {"CMU_1": 0.5, "CMU_2": 0.25}, (30.0, 28.0))
    assert len(load_runs([tmp_path / "ev"])) == 9
    run = make_run(tmp_path / "tr", "r", {"seed": 0}, lambda t: 1.0, steps=100)
    pd.DataFrame([(100, 400, 150.0, "eval_reward", 0.4)]).to_csv(run / "metrics.csv", mode="a", header=False, index=False)
    last = load_runs([tmp_path / "tr"]).query("env_steps == 100")
    assert sorted(last.key) == ["episode_return", "episodes", "eval_reward", "loss"]


def test_a_step_logged_again_supersedes_the_first_time_even_at_a_later_wall_time(tmp_path):
    """A run resumed from its step-0 checkpoint (wall time carried on) that logged its random
    return again, and an old file's resume whose wall time went back: the later rows count."""
    rows = [(0, 0, 1.0, "random_return", 1.1), (0, 0, 9.0, "random_return", 2.25), (10, 40, 12.0, "episodes", 1),
            (10, 40, 12.0, "episode_return", 3.0), (20, 80, 20.0, "episodes", 2), (20, 80, 20.0, "episode_return", 4.0),
            (20, 80, 15.0, "episodes", 2), (20, 80, 15.0, "episode_return", 5.0)]
    frame = pd.DataFrame(rows, columns=["env_steps", "learner_steps", "wall_time", "key", "value"])
    kept = last_timeline(frame)
    assert kept[kept.key == "random_return"].value.tolist() == [2.25]
    assert kept[kept.key == "episode_return"].value.tolist() == [3.0, 5.0]


def test_compare_libraries_puts_each_librarys_clip_scores_and_survival_in_a_row(tmp_path, capsys):
    import compare_libraries

    from hvc.analysis.evaluations import evaluation_table

    make_evaluation(tmp_path, "0", None, {"CMU_131_09": 0.66, "CMU_009_06": 0.47}, (27.9, 26.0))
    make_evaluation(tmp_path, "1", "x/cut_ins.npz", {"CMU_131_09": 0.55, "CMU_009_06": 0.27}, (33.7, 34.0))
    make_evaluation(tmp_path, "2", "y/other_set.npz", {"CMU_016_24": 0.36}, None)
    table = evaluation_table(load_runs([tmp_path]))
    assert list(table.columns) == ["library", "CMU_131_09", "CMU_009_06", "CMU_016_24", "compose_mean_steps",
                                   "compose_median_steps", "compose_held_mean_steps", "compose_held_median_steps"]
    assert table.library.tolist() == ["default", "x/cut_ins.npz", "y/other_set.npz"]
    assert table.CMU_009_06.tolist()[:2] == [0.47, 0.27] and math.isnan(table.CMU_009_06[2])
    assert table.compose_held_median_steps.tolist()[:2] == [52.0, 68.0] and math.isnan(table.compose_mean_steps[2])
    completion = evaluation_table(load_runs([tmp_path]), score="completion")
    assert completion.CMU_131_09.tolist()[:2] == [1.0, 1.0]

    compare_libraries.main([str(tmp_path)])
    lines = capsys.readouterr().out.splitlines()
    assert lines[0].startswith("| library | CMU_131_09 |") and lines[1].count("---") == 8
    assert lines[3] == "| x/cut_ins.npz | 0.55 | 0.27 |  | 33.7 | 34 | 67.4 | 68 |"
    with pytest.raises(SystemExit):
        compare_libraries.main([str(tmp_path), "--score", "speed"])    # no speed/<clip> rows
    with pytest.raises(SystemExit):
        compare_libraries.main([str(tmp_path), "--by", "fragment_len"])  # not an option of these runs


def test_compare_libraries_leaves_out_options_that_are_whole_sections(tmp_path, capsys):
    """Libraries evaluated on different `clips.entries` (a list of sections) are told apart by
    the options that read as values; the lists would print as JSON blobs."""
    import compare_libraries

    for name, library, clip in (("a", "a.npz", "CMU_009_06"), ("b", "b.npz", "CMU_131_09")):
        run = make_evaluation(tmp_path, name, library, {clip: 0.4}, (30.0, 28.5))
        entries = [{"id": clip, "behaviour": "run", "start": 0, "end": 38}]
        (run / "overrides.yaml").write_text(yaml.safe_dump(
            ["stage=evaluate", f"library={library}", f"clips.entries=[{{id:{clip},behaviour:run,start:0,end:38}}]"]))
        (run / "config_resolved.yaml").write_text(yaml.safe_dump(
            {"stage": "evaluate", "library": library, "clips": {"name": "go_to_target", "entries": entries}}))
    frame = load_runs([tmp_path])
    assert frame.attrs["factors"] == ["library", "clips.entries"] and frame.attrs["sections"] == ["clips.entries"]
    compare_libraries.main([str(tmp_path)])
    lines = capsys.readouterr().out.splitlines()
    assert lines[0].startswith("| library | CMU_009_06 | CMU_131_09 |")
    assert lines[2] == "| a.npz | 0.40 |  | 30 | 28.5 | 60 | 57 |"


def test_a_survival_median_prints_with_its_interval_where_one_was_logged(tmp_path):
    """Evaluations since 2026-12-06 log each median's bootstrap interval; older ones do not."""
    from hvc.analysis.evaluations import evaluation_table, markdown

    make_evaluation(tmp_path, "0", "old.npz", {"CMU_1": 0.5}, (27.9, 26.0))
    run = make_evaluation(tmp_path, "1", "new.npz", {"CMU_1": 0.5}, (30.8, 30.0))
    pd.DataFrame([(0, 0, 300.0, "compose_median_ci95_low", 27.0), (0, 0, 300.0, "compose_median_ci95_high", 33.5)]).to_csv(
        run / "metrics.csv", mode="a", header=False, index=False)
    table = evaluation_table(load_runs([tmp_path]))
    assert table.compose_median_ci95_high.tolist()[1] == 33.5 and math.isnan(table.compose_median_ci95_low[0])
    lines = markdown(table).splitlines()
    assert lines[0] == ("| library | CMU_1 | compose_mean_steps | compose_median_steps | compose_held_mean_steps "
                        "| compose_held_median_steps |")
    assert lines[2] == "| old.npz | 0.50 | 27.9 | 26 | 55.8 | 52 |"
    assert lines[3] == "| new.npz | 0.50 | 30.8 | 30 [27, 33.5] | 61.6 | 60 |"


def test_evaluation_rows_keep_the_sweeps_order_and_are_told_apart_when_labelled_alike(tmp_path):
    from hvc.analysis.evaluations import evaluation_table, markdown

    for job, library in ((0, "a.npz"), (2, "b.npz"), (10, "a.npz")):
        make_evaluation(tmp_path, str(job), library, {"CMU_1": job / 10}, (20.0, 20.0))
    (tmp_path / "10" / "summary.json").unlink()   # killed before the end
    for job, library in (("0", "a.npz"), ("2", "b.npz"), ("10", "a.npz")):  # a float option: shown as given
        (tmp_path / job / "overrides.yaml").write_text(
            yaml.safe_dump(["stage=evaluate", f"library={library}", "lowlevel.lr=0.0001"]))
    table = evaluation_table(load_runs([tmp_path]), by=["library", "lowlevel.lr"])
    assert [Path(r).name for r in table.run] == ["0", "2", "10"]
    assert table.status.tolist() == ["finished", "finished", "stopped"] and table.CMU_1.tolist() == [0.0, 0.2, 1.0]
    assert markdown(table).splitlines()[2].endswith("| a.npz | 0.0001 | finished | 0.00 | 20 | 20 | 40 | 40 |")


def test_window_scores_read_every_run_on_the_longest_runs_grid(tmp_path, capsys):
    """Each span weighs its own episodes once; a run stopped at half the budget has no second
    span (NaN, not its last value), and a run ending a log short of the budget keeps its last."""
    from hvc.analysis import window_scores
    import plot_sweep

    make_run(tmp_path, "a_s0", {"seed": 0, "fragment_len": 1}, lambda t: 0.0 if t <= 500 else 10.0)
    make_run(tmp_path, "a_s1", {"seed": 1, "fragment_len": 1}, lambda t: 4.0, steps=990)
    make_run(tmp_path, "b_s0", {"seed": 0, "fragment_len": 3}, lambda t: t / 100.0, steps=500, status="stopped")
    spans = window_scores(load_runs([tmp_path]), 2, ["fragment_len"]).set_index(["fragment_len", "seed"])
    assert list(spans.columns) == ["status", "<=500", "<=1k", "whole"]
    assert spans.loc[(1, 0), ["<=500", "<=1k", "whole"]].tolist() == [0.0, 10.0, 5.0]
    assert spans.loc[(1, 1), "<=1k"] == 4.0
    assert spans.loc[(3, 0), "<=500"] == pytest.approx(np.mean([t / 100.0 for t in range(10, 501, 10)]))
    assert math.isnan(spans.loc[(3, 0), "<=1k"])
    with pytest.raises(ValueError, match="windows must be at least 1, got 0"):
        window_scores(load_runs([tmp_path]), 0)
    with pytest.raises(ValueError, match="of='steps': allowed return, length"):
        window_scores(load_runs([tmp_path]), 2, of="steps")
    plot_sweep.main([str(tmp_path), "--by", "fragment_len", "--windows", "2", "-o", str(tmp_path / "w.png")])
    out = capsys.readouterr().out
    assert "mean episode return per span" in out and "mean episode length per span" in out


def test_episode_length_is_env_steps_per_episode_ended_in_each_span(tmp_path):
    """One episode ends every 10 env steps, then from 500 on every 25 (rows logged every 25):
    lengths 10 and 25, and 1000 env steps over 50 + 20 episodes for the whole run."""
    from hvc.analysis import window_scores

    run = make_run(tmp_path, "r", {"seed": 0}, lambda t: 1.0, steps=500)
    rows = [(t, t, float(t), k, v) for i, t in enumerate(range(525, 1001, 25))
            for k, v in (("episodes", 51 + i), ("episode_return", 1.0))]
    pd.DataFrame(rows).to_csv(run / "metrics.csv", mode="a", header=False, index=False)
    spans = window_scores(load_runs([tmp_path]), 2, of="length").iloc[0]
    assert spans["<=500"] == pytest.approx(10.0) and spans["<=1k"] == pytest.approx(25.0)
    assert spans["whole"] == pytest.approx(1000 / 70)
