"""`hvc-run` end to end on tiny budgets, as a user runs it."""
import shutil
import subprocess
import sys
import tarfile
from pathlib import Path

import pandas as pd
import pytest
import yaml


def _run(*args, cwd):
    result = subprocess.run([sys.executable, "-m", "hvc.cli", *args], capture_output=True, text=True,
                            cwd=cwd, timeout=600)
    assert result.returncode == 0, result.stderr[-3000:]
    return result


def test_default_main_job_writes_the_run_directory(tmp_path):
    import torch

    _run("total_steps=120", "log_every=20", "seed=4", "hl.random_episodes=1", "hl.min_replay_unrolls=4", cwd=tmp_path)
    [run_dir] = list((tmp_path / "outputs" / "runs").glob("*/*"))
    metrics = pd.read_csv(run_dir / "metrics.csv")
    resolved = yaml.safe_load((run_dir / "config_resolved.yaml").read_text())
    envs = resolved["num_envs"]
    assert envs == len(__import__("os").sched_getaffinity(0))  # auto: one actor per core
    steps = -(-120 // (10 * envs)) * 10 * envs  # whole rounds of one 10-step unroll per env
    assert list(metrics.columns) == ["env_steps", "learner_steps", "wall_time", "key", "value"]
    assert {"random_return", "steps_per_second", "value_loss"} <= set(metrics.key)  # it trains
    assert metrics.env_steps.max() == steps and metrics.learner_steps.max() > 0
    assert torch.load(run_dir / "checkpoint.pt", weights_only=True)["counters"]["env_steps"] == steps
    assert resolved["seed"] == 4 and resolved["task"]["name"] == "go_to_target"
    assert resolved["fragment_len"] == 3 and "${" not in (run_dir / "config_resolved.yaml").read_text()  # resolved


def test_multirun_sweeps_fragment_len_into_one_sweep_dir(tmp_path):
    _run("-m", "stage=rollout", "fragment_len=1,3,10", "total_steps=30", cwd=tmp_path)
    [sweep] = list((tmp_path / "outputs" / "sweeps").glob("*/*"))
    jobs = sorted(p for p in sweep.iterdir() if p.is_dir())
    assert len(jobs) == 3
    resolved = [yaml.safe_load((j / "config_resolved.yaml").read_text()) for j in jobs]
    assert sorted(r["fragment_len"] for r in resolved) == [1, 3, 10]
    assert all((j / "metrics.csv").exists() for j in jobs)
    for j, r in zip(jobs, resolved):  # each job logs its own value, not the sweep's "1,3,10"
        [command] = (j / "commands.log").read_text().splitlines()
        assert command.endswith(f"hvc-run stage=rollout fragment_len={r['fragment_len']} total_steps=30")


@pytest.mark.parametrize("task", ["gaps", "heterogeneous_forage"])
def test_video_is_written_when_asked(tmp_path, task):
    _run("stage=rollout", f"task={task}", "task.layout_pool=1", "total_steps=20", "video=true", "video_steps=12",
         cwd=tmp_path)
    [run_dir] = list((tmp_path / "outputs" / "runs").glob("*/*"))
    videos = list(run_dir.glob("rollout.*"))
    assert videos and videos[0].stat().st_size > 1000
    import imageio.v2 as imageio
    frames = imageio.mimread(videos[0])
    assert len(frames) == 12 and frames[0].shape[1] > frames[0].shape[0]  # third person + the agent's view


def test_rolling_ball_end_to_end_with_two_env_workers(tmp_path):
    _run("stage=rollout", "body=rolling_ball", "controller=end_to_end", "num_envs=2", "in_process_envs=0",
         "total_steps=40", cwd=tmp_path)
    [run_dir] = list((tmp_path / "outputs" / "runs").glob("*/*"))
    assert "end_to_end" in run_dir.name
    assert pd.read_csv(run_dir / "metrics.csv").env_steps.max() == 40


@pytest.mark.skipif(not __import__("hvc.mocap.source", fromlist=["x"]).SHARED_CLIPS.is_dir(),
                    reason="offline CMU clips not found")
def test_mocap_stages_end_to_end(tmp_path):
    info = _run("stage=info", "clips=go_to_target", "fragment_len=3", cwd=tmp_path).stdout.strip().splitlines()
    assert info[-1] == "clips=4 fragments=105"
    assert sum(line.startswith("clip id=CMU_") for line in info) == 4
    openloop = _run("stage=openloop", "episodes=3", "clip=left_turn", cwd=tmp_path).stdout
    assert "openloop clip=CMU_016_41" in openloop and "completion=" in openloop
    _run("stage=rollout", "task=tracking", "clip=right_turn", "total_steps=60", cwd=tmp_path)
    playback = _run("stage=playback", "clip=CMU_016_24", cwd=tmp_path).stdout
    assert "playback clip=CMU_016_24 steps=83" in playback  # a clip outside the set: all of it
    videos = list((tmp_path / "outputs").rglob("playback_CMU_016_24.mp4"))
    assert videos and videos[0].stat().st_size > 1000


def _tiny_library(path):
    """A two-expert library with random weights: enough to drive the fragments controller."""
    import numpy as np
    import torch

    from hvc.agents.mlp import GaussianPolicy, NumpyPolicy
    from hvc.lowlevel.library import Expert, ExpertLibrary
    from hvc.mocap.reference import Reference

    experts = []
    for i, n in enumerate((9, 6)):
        torch.manual_seed(i)
        rng = np.random.default_rng(i)
        ref = Reference(f"CMU_00{i}_01", 0.03, False, rng.normal(size=(n, 56)), rng.normal(size=(n, 56)),
                        rng.normal(size=(n, 3)), np.tile([1.0, 0, 0, 0], (n, 1)), rng.normal(size=(n, 3)),
                        rng.normal(size=(n, 3)), rng.normal(size=(n, 4, 3)), np.linspace(0, 1, n))
        experts.append(Expert({"id": ref.clip_id, "behaviour": f"b{i}", "start": 0, "end": n},
                              NumpyPolicy.from_torch(GaussianPolicy(137, 56, [16], 0.1)), ref))
    return ExpertLibrary(experts, {}).save(path)


def test_main_job_drives_fragments_of_a_library(tmp_path):
    import json

    path = _tiny_library(tmp_path / "lib.npz")
    _run("stage=rollout", "total_steps=60", f"library={path}", "fragment_len=3", "task.init_from_clips=false",
         cwd=tmp_path)
    [run_dir] = list((tmp_path / "outputs" / "runs").glob("*/*"))
    summary = json.loads((run_dir / "summary.json").read_text())
    assert summary["hl_actions"] >= 60 // 3  # a new fragment at least every 3 steps


@pytest.mark.parametrize("task,extra", [("go_to_target", []), ("gaps", []), ("go_to_target", ["controller=query"]),
                                        ("gaps", ["render.width=48", "render.height=40"]),
                                        ("go_to_target", ["body=rolling_ball", "controller=end_to_end",
                                                          "task.time_limit=1.0"])])
def test_high_level_training_runs_logs_and_resumes(tmp_path, task, extra):
    import torch

    path = _tiny_library(tmp_path / "lib.npz")
    common = [f"task={task}", "stage=train", f"library={path}", "task.init_from_clips=false", "num_envs=2",
              "log_every=20", "hl.random_episodes=2", "hl.min_replay_unrolls=2", "algorithm.batch_size=4",
              "task.layout_pool=1", *extra]
    _run("total_steps=80", *common, cwd=tmp_path)
    [run_dir] = list((tmp_path / "outputs" / "runs").glob("*/*"))
    metrics = pd.read_csv(run_dir / "metrics.csv")
    continuous = any(e.startswith("controller=") for e in extra)  # query, end_to_end
    losses = {"critic_loss", "policy_loss"} if continuous else {"value_loss", "pg_loss"}
    assert {"random_return", "episode_return"} | losses <= set(metrics.key)
    assert not {"new_action", "hl_action", "episode_length"} & set(metrics.key)  # no env step info in the rows
    assert metrics.learner_steps.max() > 0
    first = torch.load(run_dir / "checkpoint.pt", weights_only=True)
    if "render.height=40" in extra:  # the encoder was built for the camera's 40x48 frames (3 pools: 5x6)
        assert first["agent"]["image.out.weight"].shape[1] == 32 * 5 * 6
    resolved = yaml.safe_load((run_dir / "config_resolved.yaml").read_text())
    pace = resolved["algorithm"]["updates_per_unroll"]
    rounds = -(-80 // (2 * resolved["task"]["agent"]["unroll"]))  # 2 envs, one unroll each per round
    assert first["counters"]["updates"] == int(rounds * 2 * pace)  # the learner's pace per unroll added
    _run("total_steps=160", f"resume={run_dir}", cwd=tmp_path)  # the run's own options come back by themselves
    assert list((tmp_path / "outputs" / "runs").glob("*/*")) == [run_dir]  # and no new dir was made for it
    assert yaml.safe_load((run_dir / "config_resolved.yaml").read_text()) == {**resolved, "total_steps": 160,
                                                                              "resume": str(run_dir)}
    second = torch.load(run_dir / "checkpoint.pt", weights_only=True)
    assert second["counters"]["env_steps"] >= 160 > first["counters"]["env_steps"]
    assert second["counters"]["updates"] > first["counters"]["updates"]
    learned = [k for k, v in first["agent"].items() if not k.startswith("normalizer.")
               and not torch.equal(v, second["agent"][k])]
    assert any(k.startswith("policy_out.") for k in learned) and any(k.startswith("value.") for k in learned)
    commands = (run_dir / "commands.log").read_text().splitlines()  # both invocations, in order
    assert len(commands) == 2 and "total_steps=80" in commands[0] and f"resume={run_dir}" in commands[1]


def test_a_run_resumed_from_its_first_checkpoint_logs_its_random_return_once(tmp_path):
    """The first checkpoint is taken at env step 0, after the random episodes: a run killed
    (SIGKILL: no checkpoint of its own) before its next one goes on from it, and does not play
    (and log) the random episodes again."""
    import time

    import torch

    common = ["body=rolling_ball", "controller=end_to_end", "num_envs=1", "hl.random_episodes=1",
              "hl.min_replay_unrolls=2", "algorithm.batch_size=4", "log_every=10", "hydra.run.dir=run"]
    proc = subprocess.Popen([sys.executable, "-m", "hvc.cli", "total_steps=10000000", *common], cwd=tmp_path,
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    checkpoint, deadline = tmp_path / "run" / "checkpoint.pt", time.monotonic() + 300
    while time.monotonic() < deadline and not checkpoint.exists():
        time.sleep(0.2)
    proc.kill()
    proc.wait(timeout=60)
    assert torch.load(checkpoint, weights_only=True)["counters"]["env_steps"] == 0
    _run("total_steps=40", "resume=run", *common[:-1], cwd=tmp_path)
    metrics = pd.read_csv(tmp_path / "run" / "metrics.csv")
    assert (metrics.key == "random_return").sum() == 1 and metrics.env_steps.max() >= 40


def test_metrics_logger_writes_csv_rows_and_tensorboard_events(tmp_path):
    from hvc.io.metrics import MetricsLogger

    with MetricsLogger(tmp_path / "metrics.csv", tensorboard=True) as metrics:
        metrics.log(10, {"a": 1.5, "b": 2}, learner_steps=320)
    with MetricsLogger(tmp_path / "metrics.csv") as metrics:  # a resumed run appends
        metrics.log(20, {"a": 2.5})
    frame = pd.read_csv(tmp_path / "metrics.csv")
    assert frame.to_dict("list") == {"env_steps": [10, 10, 20], "learner_steps": [320, 320, 0],
                                     "wall_time": frame.wall_time.tolist(), "key": ["a", "b", "a"],
                                     "value": [1.5, 2.0, 2.5]}
    assert list((tmp_path / "tb").glob("events.out.tfevents.*"))


def test_recorded_episodes_feed_the_transition_analysis(tmp_path):
    import numpy as np

    path = _tiny_library(tmp_path / "lib.npz")
    _run("stage=rollout", "total_steps=120", f"library={path}", "record_episodes=2", "task.init_from_clips=false",
         cwd=tmp_path)
    [run_dir] = list((tmp_path / "outputs" / "runs").glob("*/*"))
    episodes = sorted((run_dir / "episodes").glob("episode_*.npz"))
    assert len(episodes) == 2
    with np.load(episodes[0]) as ep:
        chosen = ep["hl_action"][ep["new_action"]]
        assert len(ep["reward"]) == len(ep["hl_action"]) and len(chosen) >= 1
        assert np.all((chosen >= 0) & (chosen < 5))  # 5 fragments in the tiny library at length 3
    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "analysis"))
    from fragment_transitions import plot, transition_counts

    counts, table = transition_counts(run_dir)
    assert counts.shape == (5, 5) and counts.sum() > 0 and len(table) == 5
    assert plot(run_dir, tmp_path / "t.png").stat().st_size > 1000


def test_saliency_of_a_trained_agent_on_episodes_recorded_after_training(tmp_path):
    """stage=record plays a training run's checkpoint; its dir feeds the saliency analysis."""
    import json

    import numpy as np

    path = _tiny_library(tmp_path / "lib.npz")
    _run("task=gaps", "stage=train", f"library={path}", "task.init_from_clips=false", "num_envs=1",
         "total_steps=60", "hl.random_episodes=0", "hl.min_replay_unrolls=2",
         "algorithm.batch_size=2", "task.layout_pool=1", "hydra.run.dir=train", cwd=tmp_path)
    _run("stage=record", "from_run=train", "record_episodes=1", "hydra.run.dir=rec", cwd=tmp_path)
    run_dir = tmp_path / "rec"
    summary = json.loads((run_dir / "summary.json").read_text())
    assert summary["episodes"] == 1 and summary["trained_env_steps"] == 60
    assert len(list((run_dir / "episodes").glob("episode_*.npz"))) == 1
    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "analysis"))
    from saliency import load_agent, plot, saliency_maps

    with np.load(run_dir / "episodes" / "episode_0000.npz") as data:
        episode = {k: data[k] for k in data.files}
    assert episode["reward"].sum() == pytest.approx(summary["mean_return"], abs=1e-4)
    steps, maps = saliency_maps(load_agent(run_dir), episode)
    assert len(steps) == int(episode["new_action"].sum()) and maps.shape[1:] == (64, 64)
    assert np.all((maps >= 0) & (maps <= 1)) and maps.max() == 1.0
    assert plot(run_dir, 0, tmp_path / "s.png").stat().st_size > 1000
    # a dir that is not a training run is named in one line
    bad = subprocess.run([sys.executable, "-m", "hvc.cli", "stage=record", "from_run=rec", "record_episodes=1"],
                         capture_output=True, text=True, cwd=tmp_path)
    assert bad.returncode == 2 and "stage=record plays stage=train runs" in bad.stderr


@pytest.mark.skipif(not __import__("hvc.mocap.source", fromlist=["x"]).SHARED_CLIPS.is_dir(),
                    reason="offline CMU clips not found")
@pytest.mark.parametrize("clips, line", [("steerable", "steer clip=CMU_009_06 commanded_rate=+1.50"),
                                         ("switching", "switch clip=switching transitions_completed=")])
def test_structured_policy_trains_ships_and_evaluates(tmp_path, clips, line):
    import re

    tiny = ["lowlevel.bc_steps=10", "lowlevel.bc_rollouts=1", "lowlevel.min_replay_unrolls=2",
            "lowlevel.batch_size=2", "lowlevel.eval_episodes=1", "lowlevel.hidden=[16]", "lowlevel.critic_hidden=[16]"]
    _run("stage=lowlevel", f"clips={clips}", "total_steps=60", *tiny, "hydra.run.dir=ll", cwd=tmp_path)
    library = tmp_path / "ll" / f"experts_{clips}.npz"
    out = _run("stage=evaluate", f"clips={clips}", f"library={library}", "episodes=7", "hydra.run.dir=ev",
               cwd=tmp_path).stdout
    assert line in out
    report = (tmp_path / "ev" / "evaluation.txt").read_text()  # the same lines, kept in the run dir
    assert report.splitlines() == [row for row in out.splitlines() if not row.startswith("[")]  # not the log's
    # the run dir itself evaluates the same way (its checkpoints, as a run in progress would)
    assert line in _run("stage=evaluate", f"clips={clips}", "library=ll", "episodes=7", cwd=tmp_path).stdout
    if clips == "steerable":  # every commanded rate of the range, each with an achieved rate
        rates = re.findall(r"commanded_rate=([-+.\d]+) achieved_rate=([-+.\dna]+)", out)
        assert [float(c) for c, _ in rates] == [-1.5, -1.0, -0.5, 0.0, 0.5, 1.0, 1.5]
    else:
        attempted = int(re.search(r"of (\d+)", out).group(1))
        assert attempted > 0  # the walks switch behaviours within the episodes
        kinds = re.findall(r"switch from=(\w+) to=(\w+) completed=[.\d]+ of (\d+)", out)
        assert sum(int(n) for *_, n in kinds) == attempted  # every switch in one kind, named by its behaviours
        graph = {("stand", "run"), ("run", "stand"), ("run", "left_turn"), ("left_turn", "run"),
                 ("run", "right_turn"), ("right_turn", "run")}
        assert {(a, b) for a, b, _ in kinds} <= graph
        from hvc.lowlevel.library import ExpertLibrary

        behaviours = ExpertLibrary.load(library).behaviours  # carried along: no mocap file needed to use it
        assert [b.clip_id for b in behaviours] == ["CMU_131_09", "CMU_009_06", "CMU_016_41", "CMU_016_43"]


def test_resuming_a_checkpoint_of_an_older_format_fails_in_one_line(tmp_path):
    import torch

    common = ["body=rolling_ball", "controller=end_to_end", "task.time_limit=1.0", "num_envs=1",
              "hl.random_episodes=0", "hl.min_replay_unrolls=2", "algorithm.batch_size=4"]
    _run("total_steps=40", *common, cwd=tmp_path)
    [run_dir] = list((tmp_path / "outputs" / "runs").glob("*/*"))
    state = torch.load(run_dir / "checkpoint.pt", weights_only=True)
    state["agent"] = {k: v for k, v in state["agent"].items() if not k.startswith("normalizer.")}
    torch.save(state, run_dir / "checkpoint.pt")  # as written before input normalisation
    result = subprocess.run([sys.executable, "-m", "hvc.cli", "total_steps=80", *common, f"resume={run_dir}"],
                            capture_output=True, text=True, cwd=tmp_path, timeout=600)
    lines = [line for line in result.stderr.splitlines() if line.strip() and "absl" not in line]
    assert result.returncode == 2 and len(lines) == 1 and "older hvc" in lines[0], result.stderr[-2000:]


def test_a_killed_training_run_saves_its_checkpoint_and_says_how_to_resume(tmp_path):
    import signal
    import time

    import torch

    proc = subprocess.Popen([sys.executable, "-m", "hvc.cli", "body=rolling_ball", "controller=end_to_end",
                             "num_envs=1", "total_steps=10000000", "hl.random_episodes=0", "hl.min_replay_unrolls=2",
                             "algorithm.batch_size=4", "log_every=10", "hydra.run.dir=run"],
                            cwd=tmp_path, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    deadline = time.monotonic() + 300
    metrics = tmp_path / "run" / "metrics.csv"
    while time.monotonic() < deadline and not (metrics.exists() and "critic_loss" in metrics.read_text()):
        time.sleep(1)
    proc.send_signal(signal.SIGTERM)
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == 130 and "resume=" in err, err[-2000:]
    state = torch.load(tmp_path / "run" / "checkpoint.pt", weights_only=True)
    assert state["counters"]["env_steps"] > 0 and state["counters"]["updates"] > 0


@pytest.mark.skipif(not __import__("hvc.mocap.source", fromlist=["x"]).SHARED_CLIPS.is_dir(),
                    reason="offline CMU clips not found")
def test_a_killed_lowlevel_run_saves_every_clip_it_was_training(tmp_path):
    """No periodic checkpoint is due, so only the stop itself can have written one."""
    import json
    import signal
    import time

    import torch

    tiny = ["lowlevel.bc_steps=10", "lowlevel.bc_rollouts=1", "lowlevel.min_replay_unrolls=2", "lowlevel.batch_size=2",
            "lowlevel.eval_episodes=1", "lowlevel.hidden=[16]", "lowlevel.critic_hidden=[16]", "lowlevel.log_every=50",
            "lowlevel.checkpoint_seconds=100000", "lowlevel.workers=2", "clips=go_to_target"]
    proc = subprocess.Popen([sys.executable, "-m", "hvc.cli", "stage=lowlevel", "total_steps=10000000", *tiny,
                             "hydra.run.dir=ll"], cwd=tmp_path, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    experts = tmp_path / "ll" / "experts"
    deadline = time.monotonic() + 300
    while time.monotonic() < deadline and len(list(experts.glob("*/progress.json"))) < 2:
        time.sleep(1)
    progress = {p.parent.name: json.loads(p.read_text())["env_steps"] for p in experts.glob("*/progress.json")}
    proc.send_signal(signal.SIGTERM)
    _, err = proc.communicate(timeout=300)
    assert proc.returncode == 130 and "resume=" in err, err[-2000:]
    assert len(progress) == 2  # two clips were training (workers=2)
    for name, steps in progress.items():
        state = torch.load(experts / name / "checkpoint.pt", weights_only=True)
        assert state["counters"]["env_steps"] >= steps > 0


@pytest.mark.skipif(not __import__("hvc.mocap.source", fromlist=["x"]).SHARED_CLIPS.is_dir(),
                    reason="offline CMU clips not found")
def test_a_finished_lowlevel_run_goes_on_in_place_or_in_a_branch(tmp_path):
    """resume= with a larger total_steps continues a finished expert from its checkpoint (its
    critic and replay), keeps the evaluation it ended with, and the run is finished again only
    when it finishes; with the same total_steps nothing trains. branch_from= does the same in a
    new dir with the source's options and one changed, leaving the source as it was."""
    import json

    import pandas as pd
    import torch

    from hvc.lowlevel.library import ExpertLibrary, shipped_library

    three = ExpertLibrary.load(shipped_library()).subset(range(3)).save(tmp_path / "three.npz")
    tiny = ["lowlevel.bc_steps=10", "lowlevel.bc_rollouts=1", "lowlevel.min_replay_unrolls=2",
            "lowlevel.batch_size=2", "lowlevel.eval_episodes=1", "lowlevel.critic_hidden=[16]"]
    _run("stage=lowlevel", "clips=go_to_target", "total_steps=40", f"lowlevel.reuse={three}", *tiny,
         "hydra.run.dir=ll", cwd=tmp_path)
    expert = tmp_path / "ll" / "experts" / "3_right_turn_CMU_016_43"

    def counters():
        return torch.load(expert / "checkpoint.pt", weights_only=True)["counters"]

    first = counters()
    again = _run("stage=lowlevel", "resume=ll", "total_steps=40", cwd=tmp_path)
    assert counters() == first and "is complete" in again.stdout + again.stderr
    bad = subprocess.run([sys.executable, "-m", "hvc.cli", "stage=lowlevel", "resume=ll", "total_steps=80",
                          "lowlevel.critic_hidden=[8]"], cwd=tmp_path, capture_output=True, text=True)
    assert bad.returncode != 0 and not (tmp_path / "ll" / "summary.json").exists()  # not finished at 80
    _run("stage=lowlevel", "resume=ll", "total_steps=80", "lowlevel.critic_hidden=[16]", cwd=tmp_path)
    assert counters()["env_steps"] >= 80 > first["env_steps"] >= 40
    metrics = pd.read_csv(expert / "metrics.csv")
    evaluated = metrics[metrics.key == "eval_reward"].env_steps.tolist()
    assert evaluated == [0, first["env_steps"], counters()["env_steps"]]
    library = ExpertLibrary.load(tmp_path / "ll" / "experts_go_to_target.npz")
    assert library.meta["provenance"]["env_steps"][3] == counters()["env_steps"]
    assert json.loads((tmp_path / "ll" / "summary.json").read_text())["experts"]

    source = counters()
    _run("branch_from=ll", "total_steps=120", "lowlevel.kl_cost=0.1", "hydra.run.dir=br", cwd=tmp_path)
    branched = torch.load(tmp_path / "br" / expert.relative_to(tmp_path / "ll") / "checkpoint.pt",
                          weights_only=True)["counters"]
    assert counters() == source and branched["env_steps"] >= 120  # the source untouched, the branch went on
    rows = pd.read_csv(tmp_path / "br" / expert.relative_to(tmp_path / "ll") / "metrics.csv")
    assert rows[rows.key == "eval_reward"].env_steps.tolist() == [*evaluated, branched["env_steps"]]
    options = yaml.safe_load((tmp_path / "br" / "overrides.yaml").read_text())
    assert {"stage=lowlevel", f"lowlevel.reuse={three}", "lowlevel.kl_cost=0.1", "total_steps=120"} <= set(options)
    def kl_cost(run):
        return yaml.safe_load((tmp_path / run / "config_resolved.yaml").read_text())["lowlevel"]["kl_cost"]

    assert (kl_cost("ll"), kl_cost("br")) == (0.3, 0.1)
    assert len((tmp_path / "br" / "commands.log").read_text().splitlines()) == 5  # the source's 4, then the branch
    assert (tmp_path / "br" / "summary.json").is_file()
    again = subprocess.run([sys.executable, "-m", "hvc.cli", "branch_from=ll", "total_steps=160", "hydra.run.dir=br"],
                           cwd=tmp_path, capture_output=True, text=True)
    assert again.returncode == 2 and "already holds a run" in again.stderr and again.stderr.rstrip().endswith("/br")
    resumed = _run("resume=br", "branch_from=ll", "total_steps=120", cwd=tmp_path)  # as queue.sh resumes a branch
    assert "is complete" in resumed.stdout + resumed.stderr
    for args, says in ((["resume=ll", "branch_from=br"], "starts a new run"),
                       (["branch_from=br/experts", "hydra.run.dir=b2"], "not a run dir")):
        bad = subprocess.run([sys.executable, "-m", "hvc.cli", *args], cwd=tmp_path, capture_output=True, text=True)
        assert bad.returncode == 2 and says in bad.stderr, (args, bad.stderr[-500:])
    from hvc.runtime.lock import locked

    with locked(tmp_path / "ll"):
        busy = subprocess.run([sys.executable, "-m", "hvc.cli", "branch_from=ll", "hydra.run.dir=b4"], cwd=tmp_path,
                              capture_output=True, text=True)
    assert busy.returncode == 2 and "in use by another hvc-run" in busy.stderr and not (tmp_path / "b4").exists()


@pytest.mark.skipif(not __import__("hvc.mocap.source", fromlist=["x"]).SHARED_CLIPS.is_dir(),
                    reason="offline CMU clips not found")
def test_reuse_shipped_keeps_every_shipped_expert_of_the_same_skill_under_the_sets_names():
    """clips=go_to_target_extraneous reusing the go_to_target and gaps libraries: the 4 base
    behaviours and the two jumps the gaps library has (same clip and range, named jump_tuck_a /
    jump_in_place there) are kept; the two clips neither has are left to train."""
    import numpy as np

    from hvc.lowlevel.library import SHIPPED_DIR, ExpertLibrary
    from hvc.mocap.clip_sets import entries_of, resolve
    from hvc.mocap.source import find_mocap_file
    from hvc.config import compose
    from hvc.runtime.lowlevel_stage import reusable_experts

    cfg = compose(["clips=go_to_target_extraneous", "lowlevel.reuse=shipped"])
    entries = resolve(entries_of(cfg.clips), str(find_mocap_file(None, "2019")))
    assert len(reusable_experts(cfg, entries)) == 8  # its own library ships too (since 2026-12-04)
    cfg = compose(["clips=go_to_target_extraneous",
                   f"lowlevel.reuse=[{SHIPPED_DIR / 'experts_go_to_target.npz'},{SHIPPED_DIR / 'experts_gaps.npz'}]"])
    reused = reusable_experts(cfg, entries)
    assert sorted(reused) == [0, 1, 2, 3, 4, 6]
    assert [reused[i][0].entry["behaviour"] for i in (4, 6)] == ["tuck_jump", "jump_in_place"]
    gaps = ExpertLibrary.load(SHIPPED_DIR / "experts_gaps.npz")
    tuck = next(i for i, e in enumerate(gaps.experts) if e.entry["behaviour"] == "jump_tuck_a")
    x = np.random.default_rng(0).normal(size=137).astype(np.float32)
    np.testing.assert_array_equal(reused[4][0].act(x), gaps.experts[tuck].act(x))
    assert reused[4][1] == gaps.meta["provenance"]["env_steps"][tuck]  # its training steps go with it
    assert reused[4][0].entry == entries[4].as_dict()


@pytest.mark.skipif(not __import__("hvc.mocap.source", fromlist=["x"]).SHARED_CLIPS.is_dir(),
                    reason="offline CMU clips not found")
def test_reuse_of_a_switching_library_gives_every_behaviour_its_expert():
    """lowlevel.reuse=<the switching library>: go_to_target's four clips are its four behaviours,
    each played by the switching policy with that behaviour's code; its env steps go with each."""
    import numpy as np

    from hvc.config import compose
    from hvc.lowlevel.library import ExpertLibrary, shipped_library
    from hvc.mocap.clip_sets import entries_of, resolve
    from hvc.mocap.source import find_mocap_file
    from hvc.runtime.lowlevel_stage import reusable_experts

    switching = ExpertLibrary.load(shipped_library("switching"))
    cfg = compose(["clips=go_to_target", f"lowlevel.reuse={shipped_library('switching')}"])
    entries = resolve(entries_of(cfg.clips), str(find_mocap_file(None, "2019")))
    reused = reusable_experts(cfg, entries)
    assert sorted(reused) == [0, 1, 2, 3]
    assert [reused[i][0].entry for i in range(4)] == [e.as_dict() for e in entries]
    assert {n for _, n in reused.values()} == set(switching.meta["provenance"]["env_steps"])
    x = np.random.default_rng(0).normal(size=137).astype(np.float32)
    np.testing.assert_allclose(reused[2][0].act(x), switching.experts[0].act(np.concatenate([x, np.eye(4)[2]])),
                               atol=1e-5)


@pytest.mark.skipif(not __import__("hvc.mocap.source", fromlist=["x"]).SHARED_CLIPS.is_dir(),
                    reason="offline CMU clips not found")
def test_reuse_takes_a_list_of_libraries(tmp_path):
    """lowlevel.reuse=[<a library>, <the shipped go_to_target and forage libraries>]: heterogeneous
    forage keeps that library's expert of its turn_left (the first source holding a skill wins), the
    base behaviours and forage's other walk-and-turn, and trains the rest (the about-faces; named
    libraries, not `shipped`, which holds the about-faces too now)."""
    from hvc.config import compose
    from hvc.lowlevel.library import SHIPPED_DIR, Expert, ExpertLibrary, shipped_library
    from hvc.mocap.clip_sets import entries_of, resolve
    from hvc.mocap.source import find_mocap_file
    from hvc.runtime.lowlevel_stage import reusable_experts

    cfg = compose(["clips=heterogeneous_forage"])
    entries = resolve(entries_of(cfg.clips), str(find_mocap_file(None, "2019")))
    stand = ExpertLibrary.load(shipped_library()).experts[0]
    turn = Expert({**entries[4].as_dict(), "behaviour": "walk_turn_left"}, stand.policy, stand.reference)
    forage = ExpertLibrary([turn], {"provenance": {"env_steps": [123]}}).save(tmp_path / "experts_forage.npz")
    cfg = compose(["clips=heterogeneous_forage", f"lowlevel.reuse=[{forage},{SHIPPED_DIR / 'experts_go_to_target.npz'},"
                                                 f"{SHIPPED_DIR / 'experts_forage.npz'}]"])
    reused = reusable_experts(cfg, entries)
    assert sorted(reused) == [0, 1, 2, 3, 4, 5]
    assert reused[4][0].entry["behaviour"] == "turn_left" and reused[4][1] == 123
    assert reused[5][0].entry["behaviour"] == "turn_right" and reused[5][1] != 123
    from hvc.errors import HvcUserError
    from hvc.runtime.inputs import check_inputs

    check_inputs(cfg)  # each library of the list checked before any work, "shipped" skipped
    with pytest.raises(HvcUserError, match=f"lowlevel.reuse={tmp_path / 'none.npz'} does not exist"):
        check_inputs(compose(["clips=heterogeneous_forage", f"lowlevel.reuse=[shipped,{forage},{tmp_path / 'none.npz'}]"]))


@pytest.mark.skipif(not __import__("hvc.mocap.source", fromlist=["x"]).SHARED_CLIPS.is_dir(),
                    reason="offline CMU clips not found")
def test_a_library_made_from_a_switching_library_carries_its_experts_scores(tmp_path):
    """stage=lowlevel with every expert reused: the switching policy's behaviours come without scores
    and are scored as training scores its experts; experts that bring their own keep them."""
    from hvc.lowlevel.library import ExpertLibrary, shipped_library

    _run("stage=lowlevel", "clips=go_to_target", f"lowlevel.reuse={shipped_library('switching')}",
         "lowlevel.eval_episodes=2", f"hydra.run.dir={tmp_path / 'played'}", cwd=tmp_path)
    played = ExpertLibrary.load(tmp_path / "played" / "experts_go_to_target.npz")
    for expert in played.experts:
        assert 0 < expert.scores["eval_reward"] < 1 and expert.scores["eval_completion"] > 0
        assert {"eval_fall_rate", "eval_steps", "eval_energy_qvel"} <= set(expert.scores)
    _run("stage=lowlevel", "clips=go_to_target", "lowlevel.reuse=shipped", "lowlevel.eval_episodes=2",
         f"hydra.run.dir={tmp_path / 'kept'}", cwd=tmp_path)
    kept = ExpertLibrary.load(tmp_path / "kept" / "experts_go_to_target.npz")
    assert [e.scores for e in kept.experts] == [e.scores for e in ExpertLibrary.load(shipped_library()).experts]


@pytest.mark.skipif(not __import__("hvc.mocap.source", fromlist=["x"]).SHARED_CLIPS.is_dir(),
                    reason="offline CMU clips not found")
def test_lowlevel_reuses_experts_of_another_library(tmp_path):
    """Only the clips the reused library lacks are trained; the others are kept as they are."""
    import numpy as np

    from hvc.lowlevel.library import ExpertLibrary, shipped_library

    shipped = ExpertLibrary.load(shipped_library())
    partial = shipped.subset(range(3)).save(tmp_path / "three.npz")
    tiny = ["lowlevel.bc_steps=10", "lowlevel.bc_rollouts=1", "lowlevel.min_replay_unrolls=2",
            "lowlevel.batch_size=2", "lowlevel.eval_episodes=1", "lowlevel.hidden=[256,256]",
            "lowlevel.critic_hidden=[16]"]
    _run("stage=lowlevel", "clips=go_to_target", "total_steps=40", f"lowlevel.reuse={partial}", *tiny,
         "hydra.run.dir=ll", cwd=tmp_path)
    trained = sorted(p.name for p in (tmp_path / "ll" / "experts").iterdir())
    assert trained == ["3_right_turn_CMU_016_43"]
    library = ExpertLibrary.load(tmp_path / "ll" / "experts_go_to_target.npz")
    assert library.clip_ids == shipped.clip_ids
    x = np.random.default_rng(0).normal(size=137).astype(np.float32)
    for kept, original in zip(library.experts[:3], shipped.experts[:3]):
        np.testing.assert_array_equal(kept.act(x), original.act(x))
    assert not np.allclose(library.experts[3].act(x), shipped.experts[3].act(x))  # newly trained
    assert library.meta["provenance"]["env_steps"][:3] == shipped.meta["provenance"]["env_steps"][:3]
    [command] = library.meta["provenance"]["run_commands"]  # every invocation on the run dir, with its version
    assert command.endswith("hydra.run.dir=ll") and "lowlevel.reuse=" in command and "[hvc " in command
    # read from the run dir's checkpoints (as `stage=evaluate library=<run dir>` does): the same experts
    from hvc.errors import HvcUserError
    from hvc.runtime.lowlevel_stage import library_from_run

    from_run = library_from_run(tmp_path / "ll")
    assert from_run.clip_ids == library.clip_ids
    for a, b in zip(from_run.experts, library.experts):
        np.testing.assert_array_equal(a.act(x), b.act(x))
    (tmp_path / "ll" / "experts" / "3_right_turn_CMU_016_43" / "checkpoint.pt").unlink()
    with pytest.raises(HvcUserError, match="no checkpoint yet in .*3_right_turn_CMU_016_43"):
        library_from_run(tmp_path / "ll")


@pytest.mark.skipif(not __import__("hvc.mocap.source", fromlist=["x"]).SHARED_CLIPS.is_dir(),
                    reason="offline CMU clips not found")
def test_steerable_policy_warm_starts_from_the_run_expert(tmp_path):
    """With its critic still warming up the new policy is the shipped run expert, and the
    rate input has no effect yet; no behaviour cloning ran."""
    import numpy as np

    from hvc.lowlevel.library import ExpertLibrary, shipped_library

    tiny = ["lowlevel.min_replay_unrolls=2", "lowlevel.batch_size=2", "lowlevel.eval_episodes=1",
            "lowlevel.critic_hidden=[16]", "lowlevel.warm_start_critic_steps=1000", "lowlevel.log_every=20"]
    _run("stage=lowlevel", "clips=steerable", "lowlevel.warm_start=shipped", "total_steps=60", *tiny,
         "hydra.run.dir=ll", cwd=tmp_path)
    [run] = [e for e in ExpertLibrary.load(shipped_library()).experts if e.entry["behaviour"] == "run"]
    [steerable] = ExpertLibrary.load(tmp_path / "ll" / "experts_steerable.npz").experts
    x = np.random.default_rng(0).normal(size=(5, run.policy.weights[0].shape[0] + 1)).astype(np.float32)
    np.testing.assert_allclose(steerable.act(x), run.act(x[:, :-1]), atol=1e-5)
    metrics = pd.read_csv(next((tmp_path / "ll" / "experts").glob("*/metrics.csv")))
    assert "bc_mse_after" not in set(metrics.key) and "critic_loss" in set(metrics.key)
    # the sensitivity analysis varies the rate input: still ignored, so no action changes with it
    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "analysis"))
    from steering_sensitivity import sensitivity

    result = sensitivity(tmp_path / "ll", states=50)
    assert result["rate"] == 1.5 and result["action_change"].shape == (56,)
    assert result["mean_abs_action_change"] < 1e-6 and result["mean_abs_grad"] > 0
    # a packed run has no replay to draw states from: one line saying how to get it back
    from hvc.io.pack import pack_run

    pack_run(tmp_path / "ll", tmp_path / "ll.tar.gz")
    shutil.rmtree(tmp_path / "ll")
    with tarfile.open(tmp_path / "ll.tar.gz") as tar:
        tar.extractall(tmp_path / "moved", filter="data")
    with pytest.raises(SystemExit, match="holds no replay.*resume the run"):
        sensitivity(tmp_path / "moved" / "ll", states=50)


@pytest.mark.skipif(not __import__("hvc.mocap.source", fromlist=["x"]).SHARED_CLIPS.is_dir(),
                    reason="offline CMU clips not found")
def test_switching_policy_distils_the_experts_of_its_behaviours(tmp_path):
    import numpy as np

    from hvc.lowlevel.library import ExpertLibrary, shipped_library

    tiny = ["lowlevel.bc_rollouts=2", "lowlevel.distill_steps=300", "lowlevel.min_replay_unrolls=2",
            "lowlevel.batch_size=2", "lowlevel.eval_episodes=1", "lowlevel.critic_hidden=[16]", "lowlevel.log_every=20"]
    _run("stage=lowlevel", "clips=switching", "lowlevel.warm_start=shipped", "lowlevel.kickstart_cost=0.3",
         "lowlevel.warm_start_critic_steps=0", "total_steps=40", *tiny, "hydra.run.dir=ll", cwd=tmp_path)
    metrics = pd.read_csv(next((tmp_path / "ll" / "experts").glob("*/metrics.csv"))).set_index("key").value
    assert metrics["distill_mse_after"] < 0.5 * metrics["distill_mse_before"]  # it regressed onto the experts
    assert "bc_mse_after" not in metrics.index
    teacher_kl = metrics.loc[["teacher_kl"]]  # RL kept the experts in its policy loss
    assert len(teacher_kl) >= 1 and ((teacher_kl > 0) & (teacher_kl < 1e3)).all()
    # the policy loss is SVG(0)'s -Q + eta KL(pi || pi_target), small here, plus 0.3 x that KL
    loss = metrics.loc[["policy_loss"]].to_numpy() + metrics.loc[["q"]].to_numpy()
    np.testing.assert_allclose(loss, 0.3 * teacher_kl.to_numpy(), rtol=0.1)
    untaught = subprocess.run([sys.executable, "-m", "hvc.cli", "stage=lowlevel", "clips=switching",
                               "lowlevel.kickstart_cost=0.3", "total_steps=10"], capture_output=True, text=True,
                              cwd=tmp_path, timeout=600)
    lines = [line for line in untaught.stderr.splitlines() if line.strip() and "][" not in line]
    assert untaught.returncode == 2 and len(lines) == 1 and "kickstart_cost=0.3 needs teachers" in lines[0]
    shipped = ExpertLibrary.load(shipped_library())
    three = shipped.subset(range(3)).save(tmp_path / "three.npz")
    bad = subprocess.run([sys.executable, "-m", "hvc.cli", "stage=lowlevel", "clips=switching",
                          f"lowlevel.warm_start={three}", "total_steps=10"], capture_output=True, text=True,
                         cwd=tmp_path, timeout=600)
    lines = [line for line in bad.stderr.splitlines() if line.strip() and "][" not in line]  # not the log lines
    assert bad.returncode == 2 and len(lines) == 1 and "lacks experts for behaviours ['CMU_016_43']" in lines[0]


@pytest.mark.skipif(not __import__("hvc.mocap.source", fromlist=["x"]).SHARED_CLIPS.is_dir(),
                    reason="offline CMU clips not found")
def test_switching_policy_goes_on_from_a_switching_library_of_the_same_behaviours(tmp_path):
    """lowlevel.warm_start=<a switching library>: the new policy starts as that policy (no
    distillation), its critic warming up; a library over other behaviours fails in one line."""
    import numpy as np

    from hvc.lowlevel.library import SHIPPED_DIR, ExpertLibrary

    shipped = SHIPPED_DIR / "experts_switching.npz"
    tiny = ["lowlevel.min_replay_unrolls=2", "lowlevel.batch_size=2", "lowlevel.eval_episodes=1",
            "lowlevel.critic_hidden=[16]", "lowlevel.warm_start_critic_steps=1000", "lowlevel.log_every=30"]
    result = _run("stage=lowlevel", "clips=switching", f"lowlevel.warm_start={shipped}", "total_steps=40", *tiny,
                  "hydra.run.dir=ll", cwd=tmp_path)
    # the closing line counts the worker's last steps, not its last periodic report's
    import torch

    [checkpoint] = (tmp_path / "ll" / "experts").glob("*/checkpoint.pt")
    final = torch.load(checkpoint, weights_only=True)["counters"]["env_steps"]
    rows = pd.read_csv(checkpoint.parent / "metrics.csv")
    assert rows.query("key == 'step_reward'").env_steps.max() < final  # reported before its last steps
    assert f"switching switching finished: env_steps={final}/40 " in result.stdout + result.stderr
    [before] = ExpertLibrary.load(shipped).experts
    [after] = ExpertLibrary.load(tmp_path / "ll" / "experts_switching.npz").experts
    x = np.random.default_rng(0).normal(size=(5, before.policy.weights[0].shape[0])).astype(np.float32)
    np.testing.assert_allclose(after.act(x), before.act(x), atol=1e-5)
    metrics = pd.read_csv(next((tmp_path / "ll" / "experts").glob("*/metrics.csv")))
    assert not {"distill_mse_after", "bc_mse_after"} & set(metrics.key) and "critic_loss" in set(metrics.key)
    other = ExpertLibrary.load(shipped)
    other.meta["switching_entries"] = other.meta["switching_entries"][::-1]
    other_path = other.save(tmp_path / "reversed.npz")
    bad = subprocess.run([sys.executable, "-m", "hvc.cli", "stage=lowlevel", "clips=switching",
                          f"lowlevel.warm_start={other_path}", "total_steps=10"], capture_output=True, text=True,
                         cwd=tmp_path, timeout=600)
    lines = [line for line in bad.stderr.splitlines() if line.strip() and "][" not in line]
    assert bad.returncode == 2 and len(lines) == 1 and "is a switching policy over" in lines[0], bad.stderr[-2000:]


def test_resume_true_continues_the_newest_run_of_the_same_job(tmp_path):
    import torch

    common = ["body=rolling_ball", "controller=end_to_end", "task.time_limit=1.0", "num_envs=1",
              "hl.random_episodes=0", "hl.min_replay_unrolls=2", "algorithm.batch_size=4"]
    bad = subprocess.run([sys.executable, "-m", "hvc.cli", "total_steps=40", *common, "resume=true"],
                         capture_output=True, text=True, cwd=tmp_path, timeout=600)
    assert bad.returncode == 2 and "resume=true found no earlier run" in bad.stderr
    _run("total_steps=40", *common, cwd=tmp_path)
    _run("total_steps=40", *common, "seed=3", cwd=tmp_path)  # newer, but another job
    run_dir, other = sorted(p for p in (tmp_path / "outputs" / "runs").glob("*/*_go_to_target_end_to_end")
                            if (p / "checkpoint.pt").exists())  # seed 0's, then seed 3's
    _run("total_steps=80", *common, "resume=true", cwd=tmp_path)
    assert torch.load(run_dir / "checkpoint.pt", weights_only=True)["counters"]["env_steps"] == 80
    commands = (run_dir / "commands.log").read_text().splitlines()
    assert len(commands) == 2 and f"resume={run_dir.relative_to(tmp_path)}" in commands[1]  # the run it found
    assert len((other / "commands.log").read_text().splitlines()) == 1
    sweep = subprocess.run([sys.executable, "-m", "hvc.cli", "-m", "total_steps=40", *common, "seed=0,1",
                            "resume=true"], capture_output=True, text=True, cwd=tmp_path, timeout=600)
    assert sweep.returncode == 2 and "resume=true picks one run" in sweep.stderr


def test_a_resume_keeps_the_runs_options_and_the_new_command_wins(tmp_path):
    from hvc.runtime.run_dirs import merge_overrides, save_overrides, saved_overrides

    (tmp_path / ".hydra").mkdir()
    (tmp_path / ".hydra" / "overrides.yaml").write_text(yaml.safe_dump(["task=tracking", "+x=1", "total_steps=10"]))
    assert saved_overrides(tmp_path) == ["task=tracking", "+x=1", "total_steps=10"]  # a run from before the record
    merged = merge_overrides(saved_overrides(tmp_path), ["total_steps=20", "x=2", f"resume={tmp_path}"])
    assert merged == ["task=tracking", "total_steps=20", "++x=2", f"resume={tmp_path}"]  # x is not in the schema
    save_overrides(tmp_path, merged)
    assert saved_overrides(tmp_path) == ["task=tracking", "total_steps=20", "++x=2"]  # ours first; no resume= in it
    assert merge_overrides(saved_overrides(tmp_path), ["resume=true"])[-1] == "resume=true"
    # another group drops the old group's options (task.turn_rate_repeat is not an option of every task)
    assert merge_overrides(["task=tracking", "task.turn_rate_repeat=0.5", "seed=1"], ["task=gaps"]) == ["seed=1",
                                                                                                    "task=gaps"]


def test_a_resume_may_change_an_option_of_the_runs_own_groups(tmp_path):
    from hvc.cli import _with_resumed_options
    from hvc.config import compose
    from hvc.runtime.run_dirs import save_overrides

    save_overrides(tmp_path, ["stage=lowlevel", "clips=steerable", "task=tracking", "total_steps=10"])
    argv = _with_resumed_options([f"resume={tmp_path}", "total_steps=20", "task.turn_rate_repeat=0.5"])
    assert argv[:3] == [f"resume={tmp_path}", "total_steps=20", "task.turn_rate_repeat=0.5"]
    assert sorted(argv[3:]) == ["clips=steerable", "hydra.output_subdir=null", f"hydra.run.dir={tmp_path}",
                                "stage=lowlevel", "task=tracking"]  # total_steps: the new one; no new dir
    cfg = compose([a for a in argv if not a.startswith("hydra.")])  # task.turn_rate_repeat exists only in task=tracking, restored before Hydra composes
    assert cfg.task.name == "tracking" and cfg.task.turn_rate_repeat == 0.5 and cfg.total_steps == 20
    assert _with_resumed_options(["resume=true", "x=1"]) == ["resume=true", "x=1"]  # found later, in _run
    from hvc.config import ConfigError

    with pytest.raises(ConfigError, match="continues one run"):  # every job of a sweep would write to it
        _with_resumed_options(["-m", f"resume={tmp_path}", "seed=0,1"])


def test_recorded_query_episodes_keep_the_query_in_force(tmp_path):
    """Fig. A.3 projects the trained query agent's queries beside the fragment keys: the
    record holds each step's query, changing only where a new fragment was chosen."""
    import numpy as np

    path = _tiny_library(tmp_path / "lib.npz")
    _run("stage=train", "controller=query", f"library={path}", "task.init_from_clips=false", "num_envs=1",
         "total_steps=40", "hl.random_episodes=0", "hl.min_replay_unrolls=2", "algorithm.batch_size=2",
         "hydra.run.dir=train", cwd=tmp_path)
    _run("stage=record", "from_run=train", "record_episodes=2", "hydra.run.dir=rec", cwd=tmp_path)
    for episode in sorted((tmp_path / "rec" / "episodes").glob("episode_*.npz")):
        with np.load(episode) as ep:
            query, new = ep["query"], ep["new_action"]
        assert query.shape == (len(new), 36) and np.isfinite(query).all()
        changed = np.flatnonzero(np.any(query[1:] != query[:-1], axis=1)) + 1
        assert set(changed) <= set(np.flatnonzero(new)) and len(changed) > 0
