"""Sweeps on Hydra's launcher plugins (conf/hydra/launcher/, issue 19 item 2): jobs really run
under joblib and submitit's local executor, a failed job is still reported with them, a job
takes its share of the cores, and a submitit job that is signalled for requeue goes on from its
checkpoint in its own job dir."""
from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from omegaconf import OmegaConf

from hvc.config import CONF_DIR, ConfigError, job_cores

# The plugins are in the test extra (hvc[cluster], hvc[ray]): a missing one fails these tests, none is skipped.

ROLLOUT = ["stage=rollout", "total_steps=20"]  # the humanoid: num_envs=auto follows the job's cores
CORES = len(os.sched_getaffinity(0))


def _sweep(tmp_path: Path, *args: str, timeout: float = 300) -> subprocess.CompletedProcess:
    """hvc-run -m ... into tmp_path/sweep; output read as it comes (a full pipe would stall the jobs)."""
    return subprocess.run([sys.executable, "-m", "hvc.cli", "-m", *args, f"hydra.sweep.dir={tmp_path / 'sweep'}"],
                          capture_output=True, text=True, cwd=tmp_path, timeout=timeout)


def _jobs(tmp_path: Path) -> list[Path]:
    return sorted(p for p in (tmp_path / "sweep").iterdir() if p.is_dir() and not p.name.startswith("."))


def _resolved(job: Path) -> dict:
    return OmegaConf.to_container(OmegaConf.load(job / "config_resolved.yaml"))


@pytest.mark.parametrize("launcher", ["joblib", "submitit_local"])
def test_a_two_job_sweep_runs_every_job(tmp_path, launcher):
    result = _sweep(tmp_path, f"hydra/launcher={launcher}", *ROLLOUT, "seed=0,1")
    assert result.returncode == 0, result.stderr[-2000:]
    jobs = _jobs(tmp_path)
    assert [j.name.split("_")[0] for j in jobs] == ["0", "1"]
    for job, seed in zip(jobs, (0, 1)):
        assert json.loads((job / "summary.json").read_text())["env_steps"] == 20
        resolved = _resolved(job)
        assert resolved["seed"] == seed
        # the job's share of the cores: the humanoid's num_envs=auto is one env per core of it
        # (joblib n_jobs=2: cores // 2; submitit_local cpus_per_task=1), against CORES for a job alone
        assert resolved["num_envs"] == (max(1, CORES // 2) if launcher == "joblib" else 1)
        assert resolved["in_process_envs"] == 1
    # the launcher's Hydra record is the one of the preset (not the basic launcher's)
    target = OmegaConf.load(tmp_path / "sweep" / "multirun.yaml").hydra.launcher._target_
    assert target.endswith({"joblib": "JoblibLauncher", "submitit_local": "LocalLauncher"}[launcher])
    assert "ConfigStore schema" not in result.stderr  # Hydra's warning about the presets' names is not shown


def test_joblib_jobs_with_env_worker_processes(tmp_path):
    """A job inside joblib's (loky) worker starts env worker processes of its own (hvc.cli sets the
    standard start method for them; under loky's they died at start and the job hung)."""
    result = _sweep(tmp_path, "hydra/launcher=joblib", *ROLLOUT, "num_envs=2", "in_process_envs=1", "seed=0,1",
                    timeout=150)
    assert result.returncode == 0, result.stderr[-2000:]
    for job in _jobs(tmp_path):
        assert json.loads((job / "summary.json").read_text())["env_steps"] >= 20
        assert _resolved(job)["num_envs"] == 2  # an explicit number is kept


def test_a_failed_job_is_reported_under_joblib(tmp_path):
    result = _sweep(tmp_path, "hydra/launcher=joblib", *ROLLOUT, "fragment_len=1,0")
    assert result.returncode == 1, result.stderr[-2000:]
    assert "1 of 2 jobs failed" in result.stderr
    assert "fragment_len=0 must be a positive integer" in result.stderr
    good, bad = _jobs(tmp_path)
    assert (good / "summary.json").exists() and not (good / "failed.json").exists()
    assert json.loads((bad / "failed.json").read_text())["kind"] == "error"


def test_a_failed_job_is_reported_under_submitit_local(tmp_path):
    result = _sweep(tmp_path, "hydra/launcher=submitit_local", *ROLLOUT, "fragment_len=0,1")
    assert result.returncode == 1, result.stderr[-2000:]
    assert "1 of 2 jobs failed" in result.stderr and "fragment_len=0 must be a positive integer" in result.stderr
    bad, good = _jobs(tmp_path)
    assert (bad / "failed.json").exists() and (good / "summary.json").exists()


def test_a_ray_sweep_runs_a_job_and_reports_a_failed_one(tmp_path):
    """On a local Ray started for the sweep (one CPU per job): one job runs, one fails in one line."""
    result = _sweep(tmp_path, "hydra/launcher=ray", *ROLLOUT, "fragment_len=1,0")
    assert result.returncode == 1, result.stderr[-2000:]
    assert "1 of 2 jobs failed" in result.stderr and "fragment_len=0 must be a positive integer" in result.stderr
    good, bad = _jobs(tmp_path)
    assert json.loads((good / "summary.json").read_text())["env_steps"] == 20
    assert _resolved(good)["num_envs"] == 1  # ray.remote.num_cpus=1: the humanoid's num_envs=auto is 1
    assert (bad / "failed.json").exists()
    assert OmegaConf.load(tmp_path / "sweep" / "multirun.yaml").hydra.launcher._target_.endswith("RayLauncher")


class _FakeHydra:
    """HydraConfig of a job under a given launcher config (a sweep's, or a single run's)."""

    def __init__(self, monkeypatch, launcher: dict, mode: str = "MULTIRUN"):
        from hydra.core.hydra_config import HydraConfig
        from hydra.types import RunMode

        self.mode, self.node = getattr(RunMode, mode), OmegaConf.create({"launcher": launcher})
        monkeypatch.setattr(HydraConfig, "initialized", staticmethod(lambda: True))
        monkeypatch.setattr(HydraConfig, "get", staticmethod(lambda: self))

    def get(self, key):
        return self.node.get(key)


@pytest.mark.parametrize("launcher, cores, expected", [
    ({"n_jobs": 2}, 2, 1), ({"n_jobs": 2}, 8, 4), ({"n_jobs": 3}, 8, 2), ({"n_jobs": 4}, 2, 1),
    ({"n_jobs": -1}, 8, 1), ({"n_jobs": -2}, 8, 1), ({"n_jobs": -5}, 8, 2),  # joblib: -k leaves k-1 cores out
    ({"cpus_per_task": 1}, 8, 1), ({"cpus_per_task": 16}, 8, 8), ({"cpus_per_task": None}, 8, 8),
    ({"ray": {"remote": {"num_cpus": 2}}}, 8, 2), ({"ray": {"remote": {}}}, 8, 8),
    ({}, 8, 8),  # the basic launcher: one job at a time
])
def test_job_cores_follow_the_launcher(monkeypatch, launcher, cores, expected):
    monkeypatch.setattr("hvc.config._cores", lambda: cores)
    monkeypatch.delenv("HVC_CPUS", raising=False)
    _FakeHydra(monkeypatch, launcher)
    assert job_cores() == expected


def test_job_cores_outside_a_sweep_and_the_user_cap(monkeypatch):
    monkeypatch.setattr("hvc.config._cores", lambda: 8)
    monkeypatch.delenv("HVC_CPUS", raising=False)
    _FakeHydra(monkeypatch, {"n_jobs": 2}, mode="RUN")  # hvc-run hydra/launcher=joblib without -m: one job
    assert job_cores() == 8
    monkeypatch.setenv("HVC_CPUS", "3")
    assert job_cores() == 3
    monkeypatch.setenv("HVC_CPUS", "0")
    with pytest.raises(ConfigError, match="HVC_CPUS='0' must be a positive integer"):
        job_cores()


@pytest.mark.filterwarnings(r"ignore:\s*'hydra/launcher/\w+' is validated against ConfigStore schema")  # pytest
# resets hvc.config's filter for each test
def test_presets_select_the_plugins_with_one_flag():
    from hydra import compose, initialize_config_dir

    expected = {"joblib": "JoblibLauncher", "submitit_local": "LocalLauncher", "submitit_slurm": "SlurmLauncher"}
    if (CONF_DIR / "hydra" / "launcher" / "ray.yaml").exists():
        expected["ray"] = "RayLauncher"
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        for name, cls in expected.items():
            launcher = compose("config", overrides=[f"hydra/launcher={name}"], return_hydra_config=True).hydra.launcher
            assert launcher._target_.endswith(cls)
            if name == "submitit_slurm":  # the keys: partition, time, cpus, gpus, memory; requeue on
                for key in ("partition", "timeout_min", "cpus_per_task", "gpus_per_node", "mem_gb"):
                    assert key in launcher
                assert launcher.max_num_timeout > 0 and launcher.signal_delay_s > 0  # time limits


def _wait_for(predicate, timeout: float, what: str, proc: subprocess.Popen) -> None:
    deadline = time.monotonic() + timeout
    while not predicate():
        if proc.poll() is not None:
            raise AssertionError(f"the sweep ended (rc {proc.returncode}) before {what}")
        if time.monotonic() > deadline:
            raise AssertionError(f"no {what} after {timeout} s")
        time.sleep(0.1)


def _metrics_rows(job: Path) -> list[tuple[int, str]]:
    """(env step, key) of each row of metrics.csv."""
    path = job / "metrics.csv"
    if not path.exists():
        return []
    rows = [line.split(",") for line in path.read_text().splitlines()[1:] if line]
    return [(int(row[0]), row[3]) for row in rows if len(row) == 5]


def test_a_submitit_job_signalled_for_requeue_goes_on_from_its_checkpoint(tmp_path):
    """SIGUSR2 is what SLURM sends before a time limit, to every process of the job step: submitit
    checkpoints the launcher's call and starts the same job again (the local executor restarts it
    itself; SLURM requeues it); hl_train saves on the way out and the new start finds checkpoint.pt
    in its own job dir. Here the signal goes to the job's main process and its children (two env
    worker processes) at once, as SLURM sends it."""
    total = 3000
    log = (tmp_path / "sweep.log").open("w")
    proc = subprocess.Popen([sys.executable, "-m", "hvc.cli", "-m", "hydra/launcher=submitit_local",
                             "body=rolling_ball", "controller=end_to_end", "stage=train", f"total_steps={total}",
                             "num_envs=2", "in_process_envs=0", "log_every=20", "seed=0", f"hydra.sweep.dir={tmp_path / 'sweep'}"],
                            stdout=log, stderr=subprocess.STDOUT, cwd=tmp_path)
    try:
        job = tmp_path / "sweep" / f"0_body-rolling_ball_controller-end_to_end_in_process_envs-0_log_every-20_" \
                                    f"num_envs-2_seed-0_stage-train_total_steps-{total}"
        _wait_for(lambda: any(s >= 300 for s, _ in _metrics_rows(job)), 120, "300 env steps", proc)
        first_pid = int((job / ".lock").read_text())
        children = [int(c) for c in Path(f"/proc/{first_pid}/task/{first_pid}/children").read_text().split()]
        assert len(children) >= 2  # the env workers (and multiprocessing's resource tracker)
        for pid in (first_pid, *children):
            os.kill(pid, signal.SIGUSR2)
        assert proc.wait(timeout=240) == 0, (tmp_path / "sweep.log").read_text()[-3000:]
    finally:
        if proc.poll() is None:
            proc.kill()
        log.close()
    assert int((job / ".lock").read_text()) != first_pid  # a second process wrote the dir
    summary = json.loads((job / "summary.json").read_text())
    resolved = _resolved(job)
    round_steps = resolved["task"]["agent"]["unroll"] * resolved["num_envs"]
    assert total <= summary["env_steps"] < total + round_steps  # a resume mid-unroll ends within one round past it
    text = (job / "cli.log").read_text()
    resumed = [line for line in text.splitlines() if "resumed from" in line and "checkpoint.pt" in line]
    assert len(resumed) == 1, text[-3000:]
    at = int(resumed[0].rsplit("env step ", 1)[1].split()[0])
    assert 300 <= at < total  # from the checkpoint saved at the signal, not from the start
    rows = _metrics_rows(job)
    assert len(rows) == len(set(rows)) and rows == sorted(rows, key=lambda r: r[0])  # cut back: no row twice
    assert max(s for s, _ in rows) >= total - 20  # log_every=20: the last rows are at the end
    assert len((job / "commands.log").read_text().splitlines()) == 2
    assert not (job / "failed.json").exists()
