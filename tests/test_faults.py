"""Runs and sweeps that survive faults: hard kills, failing sweep jobs, two writers, bad
files, a full disk, budgets, progress without a terminal. Tiny budgets, as a user runs them."""
import errno
import json
import fcntl
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import torch

BALL = ["stage=train", "body=rolling_ball", "controller=end_to_end", "task=go_to_target", "num_envs=1",
        "hl.min_replay_unrolls=2", "algorithm.batch_size=2", "log_every=10"]


def _hvc(*args, cwd, check=None):
    result = subprocess.run([sys.executable, "-m", "hvc.cli", *args], capture_output=True, text=True, cwd=cwd,
                            timeout=600)
    if check is not None:
        assert result.returncode == check, (result.stdout[-2000:], result.stderr[-3000:])
    return result


def _error_lines(result) -> list[str]:
    """What a user reads on stderr (library log noise aside)."""
    return [line for line in result.stderr.splitlines() if line.strip() and "absl" not in line]


def _strictly_increasing(metrics: pd.DataFrame) -> bool:
    return all(group.env_steps.is_monotonic_increasing and not group.env_steps.duplicated().any()
               for _, group in metrics.groupby("key"))


def test_a_hard_kill_loses_at_most_the_rows_after_the_last_checkpoint(tmp_path):
    proc = subprocess.Popen([sys.executable, "-m", "hvc.cli", *BALL, "total_steps=100000000", "hl.random_episodes=1",
                             "hl.checkpoint_seconds=1", "hydra.run.dir=run"], cwd=tmp_path,
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    run = tmp_path / "run"
    deadline = time.monotonic() + 300
    while time.monotonic() < deadline:  # a few checkpoints in, and rows past the last one
        time.sleep(1)
        if (run / "checkpoint.pt").exists() and (run / "metrics.csv").exists() \
                and pd.read_csv(run / "metrics.csv").env_steps.max() > 1500:
            break
    proc.send_signal(signal.SIGKILL)
    proc.wait(timeout=60)
    saved = torch.load(run / "checkpoint.pt", weights_only=True)["counters"]["env_steps"]
    assert saved > 0
    before = pd.read_csv(run / "metrics.csv")
    kept = before[before.env_steps <= saved]
    total = saved + 500
    result = _hvc(f"resume={run}", f"total_steps={total}", cwd=tmp_path, check=0)
    assert f"at env step {saved}" in result.stdout
    after = pd.read_csv(run / "metrics.csv")
    assert _strictly_increasing(after)
    pd.testing.assert_frame_equal(after.iloc[:len(kept)], kept.reset_index(drop=True))  # nothing lost
    assert after.env_steps.max() == total and after.wall_time.is_monotonic_increasing  # time goes on
    assert after.loc[after.key == "random_return"].shape[0] == 1


def test_a_run_killed_before_any_checkpoint_says_so_and_starts_clean(tmp_path):
    run = tmp_path / "run"
    _hvc(*BALL, "total_steps=40", "hl.random_episodes=0", "hydra.run.dir=run", cwd=tmp_path, check=0)
    (run / "checkpoint.pt").unlink()  # as if killed before its first checkpoint, its rows on disk
    result = _hvc(f"resume={run}", "total_steps=60", cwd=tmp_path, check=0)
    assert "has no checkpoint" in result.stdout
    metrics = pd.read_csv(run / "metrics.csv")
    assert _strictly_increasing(metrics) and metrics.env_steps.max() == 60


def test_the_first_checkpoint_comes_right_after_the_random_episodes(tmp_path):
    """Not after hl.checkpoint_seconds: a kill in a run's first minutes loses no more than that."""
    proc = subprocess.Popen([sys.executable, "-m", "hvc.cli", *BALL, "total_steps=100000000", "hl.random_episodes=1",
                             "hydra.run.dir=run"], cwd=tmp_path, stdout=subprocess.DEVNULL,
                            stderr=subprocess.DEVNULL)
    checkpoint = tmp_path / "run" / "checkpoint.pt"
    deadline = time.monotonic() + 300
    while time.monotonic() < deadline and not checkpoint.exists():
        time.sleep(0.5)
    proc.kill()
    proc.wait(timeout=60)
    assert torch.load(checkpoint, weights_only=True)["counters"]["env_steps"] == 0  # hl.checkpoint_seconds is 300


def test_a_sweep_goes_on_past_failed_jobs_and_reports_them(tmp_path):
    result = _hvc("-m", "stage=rollout", "total_steps=20", "fragment_len=1,0,3", cwd=tmp_path, check=1)
    [sweep] = (tmp_path / "outputs" / "sweeps").glob("*/*")
    jobs = sorted(p for p in sweep.iterdir() if p.is_dir())
    assert [(j / "summary.json").exists() for j in jobs] == [True, False, True]
    assert (jobs[1] / "failed.json").exists()
    assert "1 of 3 jobs failed" in result.stderr and "fragment_len=0 must be a positive integer" in result.stderr


def test_a_sweep_job_with_a_missing_file_fails_alone(tmp_path):
    lib = "hvc/data/experts_go_to_target.npz"
    shipped = Path(__file__).resolve().parents[1] / lib
    result = _hvc("-m", "stage=rollout", "total_steps=20", f"library={shipped},/nonexistent.npz,{shipped}",
                  cwd=tmp_path, check=1)
    [sweep] = (tmp_path / "outputs" / "sweeps").glob("*/*")
    done = sorted(p.parent.name[0] for p in sweep.glob("*/summary.json"))
    assert done == ["0", "2"] and "library=/nonexistent.npz does not exist" in result.stderr


def test_a_sweep_job_dir_resumes_as_written(tmp_path):
    _hvc("-m", *BALL, "total_steps=20", "hl.random_episodes=0", "seed=0,1", cwd=tmp_path, check=0)
    [sweep] = (tmp_path / "outputs" / "sweeps").glob("*/*")
    job = sorted(p for p in sweep.iterdir() if p.is_dir())[1]
    assert "=" not in job.name and "," not in job.name
    _hvc(f"resume={job}", "total_steps=40", cwd=tmp_path, check=0)
    assert torch.load(job / "checkpoint.pt", weights_only=True)["counters"]["env_steps"] == 40


def test_a_second_writer_on_a_run_dir_fails_in_one_line(tmp_path):
    run = tmp_path / "run"
    _hvc(*BALL, "total_steps=20", "hl.random_episodes=0", "hydra.run.dir=run", cwd=tmp_path, check=0)
    with open(run / ".lock", "a+") as held:  # what a running hvc-run holds
        fcntl.flock(held, fcntl.LOCK_EX | fcntl.LOCK_NB)
        held.truncate(0)
        held.write("4242\n")
        held.flush()
        result = _hvc(f"resume={run}", "total_steps=40", cwd=tmp_path, check=2)
    lines = _error_lines(result)
    assert len(lines) == 1 and "in use by another hvc-run (pid 4242)" in lines[0], lines
    assert torch.load(run / "checkpoint.pt", weights_only=True)["counters"]["env_steps"] == 20  # untouched


def test_resume_true_skips_a_run_in_use(tmp_path):
    from hvc.runtime.lock import locked
    from hvc.runtime.run_dirs import latest_run_dir

    root = tmp_path / "runs"
    for name in ("10-00-00_a", "11-00-00_a"):
        run = root / "2026-12-04" / name
        run.mkdir(parents=True)
        (run / "config_resolved.yaml").write_text("stage: train\nseed: 0\n")
        (run / "checkpoint.pt").write_bytes(b"")
    newest = root / "2026-12-04" / "11-00-00_a"
    assert latest_run_dir({"stage": "train", "seed": 0}, tmp_path / "new", root) == newest
    with locked(newest):
        assert latest_run_dir({"stage": "train", "seed": 0}, tmp_path / "new", root).name == "10-00-00_a"


def _bad_files(tmp_path: Path) -> dict[str, tuple[str, str]]:
    """option -> (the bad value, what the one line must say)."""
    shipped = Path(__file__).resolve().parents[1] / "hvc" / "data" / "experts_go_to_target.npz"
    (tmp_path / "random.npz").write_bytes(np.random.default_rng(0).bytes(3000))
    (tmp_path / "truncated.npz").write_bytes(shipped.read_bytes()[:200_000])
    np.savez(tmp_path / "other.npz", a=np.zeros(3))
    (tmp_path / "random.h5").write_bytes(np.random.default_rng(1).bytes(3000))
    run = tmp_path / "bad_run"
    run.mkdir()
    (run / "config_resolved.yaml").write_text("stage: train\n")
    (run / "checkpoint.pt").write_bytes(b"PK\x03\x04" + bytes(100))
    return {"random bytes as a library": (f"library={tmp_path / 'random.npz'}", "is not an .npz archive"),
            "a truncated library": (f"library={tmp_path / 'truncated.npz'}", "truncated or corrupt"),
            "an npz that is not a library": (f"library={tmp_path / 'other.npz'}", "not an expert library"),
            "random bytes as a mocap file": (f"mocap_file={tmp_path / 'random.h5'}", "not a readable HDF5 file"),
            "a truncated checkpoint": (f"from_run={run}", "truncated or corrupt"),
            "a dir that is not a run": (f"from_run={tmp_path}", "not a run dir")}


@pytest.mark.parametrize("kind", ["random bytes as a library", "a truncated library", "an npz that is not a library",
                                  "random bytes as a mocap file", "a truncated checkpoint", "a dir that is not a run"])
def test_each_bad_file_kind_gets_one_line_naming_it(tmp_path, kind):
    value, says = _bad_files(tmp_path)[kind]
    stage = "stage=record" if value.startswith("from_run=") else "stage=rollout"
    result = _hvc(stage, value, "total_steps=20", cwd=tmp_path, check=2)
    lines = _error_lines(result)
    assert len(lines) == 1 and says in lines[0] and value.partition("=")[2] in lines[0], lines
    assert "pickle" not in result.stderr
    assert not list(tmp_path.glob("outputs/runs/*/*"))  # no stub run dir left behind


def test_a_full_disk_keeps_the_previous_checkpoint(tmp_path, monkeypatch):
    import os

    from hvc.io.checkpoint import DiskFull, save_checkpoint

    path = tmp_path / "checkpoint.pt"
    save_checkpoint({"step": 1}, path)

    def full(fd):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(os, "fsync", full)
    with pytest.raises(DiskFull, match=f"no space left on {tmp_path}: checkpoint.pt not written; the previous one"):
        save_checkpoint({"step": 2}, path)
    assert torch.load(path, weights_only=True) == {"step": 1}
    assert sorted(p.name for p in tmp_path.iterdir()) == ["checkpoint.pt"]  # no temp file


def test_a_complete_run_says_so_on_resume(tmp_path):
    run = tmp_path / "run"
    _hvc(*BALL, "total_steps=40", "hl.random_episodes=0", "hydra.run.dir=run", cwd=tmp_path, check=0)
    result = _hvc(f"resume={run}", cwd=tmp_path, check=0)
    assert "is complete: 40 env steps done of total_steps=40" in result.stdout


def test_counts_accept_integral_floats_and_refuse_fractions():
    from hvc.config import ConfigError, compose, validate

    cfg = compose(["total_steps=1e6"])
    validate(cfg)
    assert cfg.total_steps == 1_000_000 and isinstance(cfg.total_steps, int)
    with pytest.raises(ConfigError, match="total_steps"):
        validate(compose(["total_steps=1.5"]))


def test_progress_without_a_terminal_logs_lines_and_a_closing_one(tmp_path):
    result = _hvc(*BALL, "total_steps=200", "hl.random_episodes=1", "progress_seconds=0", cwd=tmp_path, check=0)
    lines = [line for line in result.stdout.splitlines() if "hvc.runtime.progress" in line]
    assert len(lines) >= 2 and "env_steps=" in lines[0] and "steps_per_second=" in lines[0]
    assert "hl train finished: env_steps=200/200" in lines[-1]


def test_progress_of_a_clip_restarted_from_an_older_checkpoint_counts_from_there(caplog, monkeypatch):
    """A killed clip worker reported more steps than its last checkpoint held: its speed and eta
    count from where it restarted, never negative."""
    from hvc.runtime import progress as progress_module

    now = [0.0]
    monkeypatch.setattr(progress_module.time, "monotonic", lambda: now[0])
    bar = progress_module.Progress("run CMU_001", total=1000, done=400, seconds=0)
    bar.lines = True
    with caplog.at_level("INFO", logger="hvc.runtime.progress"):
        now[0] = 10.0
        bar.update(200)  # restarted from its checkpoint at 200
        now[0] = 20.0
        bar.update(300)  # 100 steps in 10 s
    assert "env_steps=300/1000 steps_per_second=10 " in caplog.messages[-1]
    assert "eta=1m10s" in caplog.messages[-1]


def test_progress_of_a_clip_that_waited_for_a_worker_counts_from_its_start(caplog, monkeypatch, tmp_path):
    """lowlevel.workers=1: every clip's bar exists from the stage's start, but the second clip's
    speed and eta count from when its worker started, not from the wait before it."""
    from hvc.runtime import lowlevel_stage
    from hvc.runtime import progress as progress_module

    now = [0.0]
    monkeypatch.setattr(progress_module.time, "monotonic", lambda: now[0])
    bar = progress_module.Progress("left_turn CMU_016_41", total=1000, seconds=0)
    bar.lines = True
    now[0] = 3600.0  # an hour queued behind the first clip
    bar.restart()
    (tmp_path / "progress.json").write_text(json.dumps({"env_steps": 500}))
    now[0] = 3610.0
    with caplog.at_level("INFO", logger="hvc.runtime.progress"):
        lowlevel_stage._report(bar, tmp_path)
    assert caplog.messages[-1].endswith("env_steps=500/1000 steps_per_second=50 eta=0m10s")


def test_a_typo_in_a_key_gets_a_suggestion_and_leaves_no_run_dir(tmp_path):
    result = _hvc("fragmnt_len=3", cwd=tmp_path, check=2)
    lines = _error_lines(result)
    assert len(lines) == 1 and "did you mean fragment_len" in lines[0], lines
    assert not (tmp_path / "outputs").exists()


def test_a_resume_goes_on_with_the_optimiser_state_and_counters_it_saved(tmp_path):
    """Adam's moments and step count continue (a fresh optimiser would restart its bias
    correction), and the counters go on from the checkpoint's rather than from zero."""
    run = tmp_path / "run"
    _hvc(*BALL, "total_steps=60", "hl.random_episodes=0", "task.time_limit=0.3", "hydra.run.dir=run", cwd=tmp_path,
         check=0)
    first = torch.load(run / "checkpoint.pt", weights_only=True)
    _hvc(f"resume={run}", "total_steps=120", cwd=tmp_path, check=0)
    second = torch.load(run / "checkpoint.pt", weights_only=True)
    updates = second["counters"]["updates"] - first["counters"]["updates"]
    assert first["counters"]["updates"] > 0 and updates > 0
    adam_step = lambda state: int(state["optimizer"]["state"][0]["step"])  # noqa: E731
    assert adam_step(second) == adam_step(first) + updates
    assert second["counters"]["env_steps"] == 120 and second["counters"]["episodes"] > first["counters"]["episodes"] > 0


def test_a_branch_whose_copy_fails_leaves_only_bookkeeping(tmp_path, monkeypatch):
    """A copy that fails part way (disk full, a file gone) leaves the new dir as it was, so the
    same branch_from= can run again; the source's ending records and temp files are not copied."""
    import shutil

    from hvc.runtime import run_dirs

    source, target = tmp_path / "src", tmp_path / "new"
    (source / "experts/0_run").mkdir(parents=True)
    for name in ("experts/0_run/checkpoint.pt", "experts/0_run/metrics.csv", "commands.log", "summary.json",
                 "failed.json", "checkpoint.pt.tmp", "cli.log"):
        (source / name).write_text(name)
    target.mkdir()
    (target / "cli.log").write_text("this job's log")
    copies = []

    def copy_then_fail(src, dst, **kwargs):
        if copies:
            raise OSError(28, "No space left on device")
        copies.append(dst)
        return shutil.copy2(src, dst)

    monkeypatch.setattr(run_dirs.shutil, "copy2", copy_then_fail)
    with pytest.raises(OSError):
        run_dirs.branch_run(source, target, "cli.log")
    assert copies and sorted(p.name for p in target.iterdir()) == ["cli.log"]
    monkeypatch.undo()
    run_dirs.branch_run(source, target, "cli.log")
    assert sorted(p.name for p in target.iterdir()) == ["cli.log", "commands.log", "experts"]
    assert (target / "cli.log").read_text() == "this job's log"
