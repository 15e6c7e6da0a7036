"""Learning-curve statistics: returns averaged per episode, not per log row."""
import sys
from pathlib import Path

import pandas as pd
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "analysis"))
from hvc.analysis import mean_return  # noqa: E402
from plot_training import plot  # noqa: E402


def _metrics():
    rows = [(0, 0, 0.0, "random_return", 1.0)]  # logged first, as hl_train does
    # row at 100 env steps: 3 short episodes with nothing; at 200: one long episode scoring 100;
    # at 300: no episode ended (no return logged)
    for env_steps, episodes, ret in ((100, 3, 0.0), (200, 4, 100.0), (300, 4, None)):
        rows.append((env_steps, env_steps * 10, 1.0, "episodes", episodes))
        if ret is not None:
            rows.append((env_steps, env_steps * 10, 1.0, "episode_return", ret))
    return pd.DataFrame(rows, columns=["env_steps", "learner_steps", "wall_time", "key", "value"])


def test_mean_return_weights_each_episode_once():
    m = _metrics()
    assert mean_return(m) == pytest.approx(25.0)           # 100 / 4 episodes, not (0 + 100) / 2 rows
    assert mean_return(m, lo=150) == pytest.approx(100.0)


def test_plot_reads_a_gzipped_metrics_file(tmp_path):
    path = tmp_path / "metrics_run.csv.gz"
    _metrics().to_csv(path, index=False)
    assert plot(tmp_path / "c.png", [path]).stat().st_size > 1000


def test_plot_reads_an_exported_run_dir_and_names_one_without_metrics(tmp_path):
    """analysis/export_runs.py leaves only metrics.csv.gz in a run dir."""
    from plot_training import draw

    _metrics().to_csv(tmp_path / "metrics.csv.gz", index=False)
    assert list(draw([tmp_path]).axes[1].lines[0].get_xdata()) == [100, 200]
    import matplotlib.pyplot as plt

    plt.close("all")
    with pytest.raises(SystemExit, match="no metrics in"):
        draw([tmp_path, tmp_path / "missing"])
    assert not plt.get_fignums()  # the error left no figure open


def test_the_plotted_curve_is_the_return_per_episode_with_the_random_line(tmp_path):
    from plot_training import draw

    path = tmp_path / "metrics_run.csv"
    _metrics().to_csv(path, index=False)
    by_transitions, by_env_steps = draw([path]).axes
    curve, random = by_transitions.lines
    assert list(curve.get_xdata()) == [1000, 2000] and list(by_env_steps.lines[0].get_xdata()) == [100, 200]
    assert list(curve.get_ydata()) == pytest.approx([0.0, 25.0])  # 3 episodes of 0, then one of 100: 100 / 4
    assert list(random.get_ydata()) == [1.0, 1.0] and random.get_linestyle() == "--"
    assert curve.get_label() == "metrics_run"


def test_a_resumed_run_counts_each_episode_once():
    """A resumed run logs again from its checkpoint (here 100), superseding rows 200 and 300."""
    first = [(100, 3, 0.0), (200, 4, 100.0), (300, 6, 0.0)]
    resumed = [(200, 5, 10.0), (300, 7, 0.0)]  # the checkpoint was at 100 with 3 episodes
    rows = []
    for wall, (env_steps, episodes, ret) in enumerate(first + resumed):
        rows.append((env_steps, env_steps, float(wall), "episodes", episodes))
        rows.append((env_steps, env_steps, float(wall), "episode_return", ret))
    m = pd.DataFrame(rows, columns=["env_steps", "learner_steps", "wall_time", "key", "value"])
    # timeline kept: 100 (3 episodes, 0), 200 (2 episodes, 10 each), 300 (2 episodes, 0)
    assert mean_return(m) == pytest.approx(20.0 / 7)


def test_steering_plot_reads_the_evaluation_rows(tmp_path):
    from plot_lowlevel import plot_steering

    rows = [(0, 0, 1.0, f"{measure}/CMU_009_06/{rate:+.1f}", value)
            for rate in (-1.5, 0.0, 1.5) for measure, value in (("achieved_rate", rate / 2), ("completion", 0.5))]
    rows.append((0, 0, 1.0, "eval_reward/CMU_009_06", 0.3))
    pd.DataFrame(rows, columns=["env_steps", "learner_steps", "wall_time", "key", "value"]).to_csv(
        tmp_path / "metrics.csv", index=False)
    assert plot_steering(tmp_path, tmp_path / "s.png").stat().st_size > 1000
    (tmp_path / "metrics.csv").write_text("env_steps,learner_steps,wall_time,key,value\n0,0,1.0,eval_reward/x,0.3\n")
    with pytest.raises(SystemExit, match="no steering rows"):
        plot_steering(tmp_path, tmp_path / "t.png")


def _resumed_rows(first, resumed, key):
    """(env_steps, value) rows of one key, logged once, then again from a checkpoint."""
    rows = [(steps, steps, float(wall), key, value) for wall, (steps, value) in enumerate(first + resumed)]
    return pd.DataFrame(rows, columns=["env_steps", "learner_steps", "wall_time", "key", "value"])


def test_an_experts_curve_drops_the_rows_its_resume_superseded(tmp_path):
    from plot_lowlevel import load

    expert = tmp_path / "experts" / "0_run_CMU_009_06"
    expert.mkdir(parents=True)
    # logged to 20000, resumed from the 10000 checkpoint, logging on an offset grid
    _resumed_rows([(5000, 0.1), (10000, 0.2), (15000, 0.9), (20000, 0.9)], [(12500, 0.3), (17500, 0.4)],
                  "step_reward").to_csv(expert / "metrics.csv", index=False)
    table = load(tmp_path)["0_run_CMU_009_06"]
    assert list(table.index) == [5000, 10000, 12500, 17500]
    assert list(table.step_reward) == [0.1, 0.2, 0.3, 0.4]


def test_a_run_resumed_from_its_first_checkpoint_draws_its_last_random_return(tmp_path):
    from plot_training import draw

    m = pd.concat([_resumed_rows([(0, 5.0)], [(0, 2.0)], "random_return"),
                   _resumed_rows([(100, 1.0), (200, 1.0)], [], "episodes").assign(wall_time=[2.0, 3.0]),
                   _resumed_rows([(100, 3.0), (200, 4.0)], [], "episode_return").assign(wall_time=[2.0, 3.0])])
    m = m.sort_values(["wall_time", "key"], kind="stable")
    m.to_csv(tmp_path / "metrics.csv", index=False)
    random = draw([tmp_path]).axes[0].lines[1]
    assert list(random.get_ydata()) == [2.0, 2.0]


@pytest.mark.parametrize("script", ["export_runs", "fragment_transitions", "plot_lowlevel", "plot_training",
                                    "saliency", "steering_sensitivity"])
def test_each_analysis_script_answers_help_with_its_usage(script, capsys):
    """--help prints the usage and exits 0 (it once was read as a run dir)."""
    module = __import__(script)
    with pytest.raises(SystemExit) as exit_:
        module.main(["--help"])
    assert exit_.value.code == 0
    assert capsys.readouterr().out.startswith("usage:")


def test_the_lowlevel_plot_routes_each_mode_and_names_a_bad_call(monkeypatch, tmp_path):
    import plot_lowlevel

    calls = []
    monkeypatch.setattr(plot_lowlevel, "plot", lambda run, out: calls.append(("plot", run, out)))
    monkeypatch.setattr(plot_lowlevel, "plot_steering", lambda run, out: calls.append(("steering", run, out)))
    monkeypatch.setattr(plot_lowlevel, "plot_compare", lambda out, clip, runs: calls.append(("compare", out, clip, runs)))
    plot_lowlevel.main(["r"])
    plot_lowlevel.main(["--steering", "r", "s.png"])
    plot_lowlevel.main(["--compare", "c.png", "CMU_009_06", "a=x", "b=y=z"])
    assert calls == [("plot", Path("r"), Path("r/learning_curves.png")), ("steering", Path("r"), Path("s.png")),
                     ("compare", Path("c.png"), "CMU_009_06", {"a": Path("x"), "b": Path("y=z")})]
    for bad in (["--compare", "c.png", "CMU_009_06", "x"], ["r", "o.png", "extra"], ["--steering", "--compare", "r"]):
        with pytest.raises(SystemExit) as exit_:
            plot_lowlevel.main(bad)
        assert exit_.value.code == 2
