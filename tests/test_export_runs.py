"""Exporting run dirs into docs/results: what a figure needs, compressed, and nothing stale."""
import gzip
import json
import sys
from pathlib import Path

import pandas as pd

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "analysis"))
from export_runs import export  # noqa: E402


def _hl_run(root: Path) -> Path:
    run = root / "sweep" / "0"
    run.mkdir(parents=True)
    rows = [(0, 0, 0.0, "random_return", 1.0)]
    for env_steps in (500, 1000, 1500, 2000):
        rows.append((env_steps, 1, 1.0, "loss", 0.5))
        rows.append((env_steps, 1, 1.0, "episode_return", float(env_steps)))
    pd.DataFrame(rows, columns=["env_steps", "learner_steps", "wall_time", "key", "value"]).to_csv(
        run / "metrics.csv", index=False)
    (run / "overrides.yaml").write_text("- seed=0\n")
    (run / "checkpoint.pt").write_bytes(b"large")
    return run


def _lowlevel_run(root: Path, finished: bool) -> Path:
    run = root / "skills" / "switching_3m"
    expert = run / "experts" / "0_switching_switching"
    expert.mkdir(parents=True)
    (expert / "metrics.csv").write_text("env_steps,learner_steps,return\n0,0,1.0\n100,1,2.0\n")
    (expert / "checkpoint.pt").write_bytes(b"large")
    (run / "experts_switching.npz").write_bytes(b"library")
    (run / "commands.log").write_text("hvc-run stage=lowlevel\n")
    if finished:
        (expert / "result.json").write_text(json.dumps({"eval_completion": 0.8}))
        (run / "summary.json").write_text("{}")
    return run


def test_a_high_level_run_keeps_every_return_and_thins_the_rest(tmp_path):
    _hl_run(tmp_path / "out")
    [target] = export(tmp_path / "docs", [tmp_path / "out"])
    assert target == tmp_path / "docs" / "0"
    metrics = pd.read_csv(target / "metrics.csv.gz")
    assert list(metrics[metrics.key == "episode_return"].env_steps) == [500, 1000, 1500, 2000]
    assert list(metrics[metrics.key == "loss"].env_steps) == [1000, 2000]
    assert (target / "overrides.yaml").is_file() and not (target / "checkpoint.pt").exists()


def test_a_lowlevel_run_exports_each_expert_by_clip_and_its_library_once_finished(tmp_path):
    run = _lowlevel_run(tmp_path / "out", finished=False)
    [target] = export(tmp_path / "docs", [run])
    assert target.name == "switching_3m"  # the run, not its expert dirs
    with gzip.open(target / "metrics_switching_switching.csv.gz", "rt") as f:
        assert f.read() == (run / "experts" / "0_switching_switching" / "metrics.csv").read_text()
    assert not (target / "experts_switching.npz").exists()  # the branch source's library, not this run's
    assert not (target / "result_switching_switching.json").exists()
    assert (target / "commands.log").is_file() and not (target / "checkpoint.pt").exists()

    (run / "experts" / "0_switching_switching" / "result.json").write_text(json.dumps({"eval_completion": 0.8}))
    (run / "summary.json").write_text("{}")
    export(tmp_path / "docs", [tmp_path / "out"])  # found from a parent dir, too
    assert json.loads((target / "result_switching_switching.json").read_text()) == {"eval_completion": 0.8}
    assert (target / "experts_switching.npz").read_bytes() == b"library"
    assert (target / "summary.json").is_file()


def test_a_finished_lowlevel_run_that_goes_on_loses_its_stale_result_and_library(tmp_path):
    run = _lowlevel_run(tmp_path / "out", finished=True)
    [target] = export(tmp_path / "docs", [run])
    assert (target / "experts_switching.npz").is_file() and (target / "result_switching_switching.json").is_file()
    (run / "summary.json").unlink()
    (run / "experts" / "0_switching_switching" / "result.json").unlink()
    export(tmp_path / "docs", [run])
    assert not (target / "experts_switching.npz").exists()
    assert not (target / "result_switching_switching.json").exists()
    assert not (target / "summary.json").exists()
