import itertools
import subprocess
import sys

import pytest

from hvc.config import CHEAP_BODY_ENVS, ConfigError, compose, group_options, resolve_parallelism

TASKS = group_options("task")
CONTROLLERS = group_options("controller")
BODIES = group_options("body")


def test_groups_have_the_options_the_paper_needs():
    assert set(TASKS) >= {"go_to_target", "walls", "gaps", "forage", "heterogeneous_forage", "tracking"}
    assert set(CONTROLLERS) == {"steerable", "switching", "fragments", "query", "end_to_end"}
    assert set(BODIES) >= {"cmu_humanoid", "cmu_humanoid_2020", "rolling_ball"}


@pytest.mark.parametrize("task,controller,body", list(itertools.product(TASKS, CONTROLLERS, BODIES)))
def test_every_combination_composes_or_fails_in_one_line(task, controller, body):
    overrides = [f"task={task}", f"controller={controller}", f"body={body}",
                 *(["stage=rollout"] if task == "tracking" else [])]  # stage=train takes high-level tasks
    humanoid_needed = controller != "end_to_end" or task == "tracking"
    should_fail = humanoid_needed and body == "rolling_ball"
    if should_fail:
        with pytest.raises(ConfigError) as error:
            compose(overrides)
        message = str(error.value)
        assert "\n" not in message and "allowed" in message
        assert (body in message) or (task in message)
    else:
        cfg = compose(overrides)
        assert cfg.task.name == task and cfg.controller.name == controller and cfg.body.name == body
        assert cfg.algorithm.name in cfg.controller.algorithms  # each controller brings its learner


def test_table_a1_lives_with_each_task():
    expected = {"go_to_target": (10, 128, [128, 1], 0.99, 10**6), "walls": (20, 128, [128, 1], 0.99, 10**4),
                "gaps": (20, 128, [128, 1], 0.99, 10**4), "forage": (50, 256, [200, 200, 1], 0.995, 10**4),
                "heterogeneous_forage": (200, 256, [200, 200, 1], 0.99, 10**5)}
    for task, (unroll, lstm, mlp, gamma, replay) in expected.items():
        agent = compose([f"task={task}"]).task.agent
        assert (agent.unroll, agent.lstm_size, list(agent.value_mlp), agent.gamma, agent.replay_size) == \
               (unroll, lstm, mlp, gamma, replay)


def test_tasks_bring_their_clip_sets_and_timesteps():
    assert compose(["task=gaps"]).clips.name == "gaps"
    assert compose(["task=walls"]).clips.name == "go_to_target"
    assert compose(["task=gaps", "clips=forage"]).clips.name == "forage"  # command line wins
    for task in ("go_to_target", "walls", "gaps", "forage"):
        cfg = compose([f"task={task}"])
        assert (cfg.task.control_timestep, cfg.task.physics_timestep) == (0.03, 0.005)
    assert compose(["task=heterogeneous_forage"]).task.physics_timestep == 0.001


@pytest.mark.parametrize("value", [1, 3, 10, 57])
def test_fragment_len_accepts_any_positive_integer(value):
    cfg = compose([f"fragment_len={value}"])
    assert cfg.fragment_len == value


@pytest.mark.parametrize("value", ["0", "-3", "2.5", "abc"])
def test_fragment_len_rejects_non_positive_or_non_integer(value):
    with pytest.raises(ConfigError, match="fragment_len"):
        compose([f"fragment_len={value}"])


def test_unknown_group_option_names_the_allowed_ones():
    with pytest.raises(ConfigError) as error:
        compose(["task=moon_landing"])
    assert "moon_landing" in str(error.value) and "go_to_target" in str(error.value)


@pytest.mark.parametrize("overrides, expected", [
    (["body=rolling_ball", "controller=end_to_end", "num_envs=3"], 3),  # a cheap body: every env in process
    (["num_envs=3"], 1),                                                # the humanoid: one, the rest in workers
    (["num_envs=3", "in_process_envs=0"], 0),                          # an explicit number is kept
    (["body=rolling_ball", "controller=end_to_end", "task=walls", "num_envs=3"], 1),  # the camera: workers
])
def test_in_process_envs_auto_depends_on_the_body(overrides, expected):
    cfg = compose(overrides)
    resolve_parallelism(cfg)
    assert cfg.num_envs == 3 and cfg.in_process_envs == expected


def test_num_envs_auto_is_one_per_core_for_the_humanoid_and_more_for_the_rolling_ball():
    import os

    humanoid, ball = compose([]), compose(["body=rolling_ball", "controller=end_to_end"])
    for cfg in (humanoid, ball):
        resolve_parallelism(cfg)
    assert humanoid.num_envs == len(os.sched_getaffinity(0)) and humanoid.in_process_envs == 1
    assert ball.num_envs == CHEAP_BODY_ENVS == ball.in_process_envs


def test_torch_threads_auto_takes_every_core_only_for_vision():
    import os

    plain, vision, pinned = compose([]), compose(["task=gaps"]), compose(["task=gaps", "torch_threads=1"])
    for cfg in (plain, vision, pinned):
        resolve_parallelism(cfg)
    assert plain.torch_threads == 1 and pinned.torch_threads == 1
    assert vision.torch_threads == len(os.sched_getaffinity(0))


def test_wrong_algorithm_for_controller_fails():
    with pytest.raises(ConfigError, match="allowed: vtrace"):
        compose(["controller=fragments", "algorithm=svg0_retrace"])


def _hvc_run(*args, cwd):
    return subprocess.run([sys.executable, "-m", "hvc.cli", *args], capture_output=True, text=True, cwd=cwd,
                          timeout=300)


@pytest.mark.parametrize("args,needle", [
    (["stage=info", "mocap_file=/nonexistent/clips.h5"], "does not exist"),
    (["stage=evaluate", "library=/nonexistent/lib.npz"], "does not exist"),
    (["body=rolling_ball", "controller=fragments"], "rolling_ball"),
    (["fragment_len=0"], "fragment_len"),
    (["task=nowhere"], "nowhere"),
    (["stage=dance"], "dance"),
    (["task=tracking"], "stage=lowlevel"),
    (["algorithm.updates_per_unroll=0"], "algorithm.updates_per_unroll=0"),
    (["num_envs=0"], "num_envs=0 must be a positive integer or auto"),
    (["in_process_envs=-1"], "in_process_envs=-1 must be an integer from 0 to num_envs, or auto"),
    (["torch_threads=0"], "torch_threads=0 must be a positive integer or auto"),
    (["num_envs=2", "in_process_envs=3"], "in_process_envs=3 exceeds num_envs=2"),
    (["stage=lowlevel", "task=tracking", "task.termination_error=-0.1"], "task.termination_error=-0.1 must be"),
    (["stage=lowlevel", "task=tracking", "task.heading_termination=0"], "task.heading_termination=0 must be"),
    (["stage=lowlevel", "lowlevel.cut_ins=1.5"], "lowlevel.cut_ins=1.5 must be a probability from 0 to 1"),
    (["stage=lowlevel", "lowlevel.switch_starts=true"], "lowlevel.switch_starts=True must be a probability"),
    (["stage=lowlevel", "lowlevel.pushes=2"], "lowlevel.pushes=2 must be a probability from 0 to 1"),
    (["stage=lowlevel", "lowlevel.kickstart_cost=-0.1"], "lowlevel.kickstart_cost=-0.1 must be a weight of 0"),
    (["stage=lowlevel", "lowlevel.kickstart_cost=0.1", "lowlevel.bc_rollouts=0"], "gives kickstarting no teacher walks"),
    (["stage=lowlevel", "lowlevel.push_force=-5"], "lowlevel.push_force=-5 must be a positive force in newtons"),
    (["stage=lowlevel", "lowlevel.push_steps=1.5"], "lowlevel.push_steps=1.5 must be a whole number of control steps"),
    (["controller=fragments", "clips=go_to_target_x2", "clips.entries=[{id:CMU_131_14,behaviour:stand_c,start:42,end:84}]",
      "library=null", "num_envs=1"], "stage=lowlevel clips=go_to_target_x2"),
    # typed keys (hvc/schema.py): Hydra's own message, the key and the type it wants
    (["algorithm.learning_rate=fast"], "algorithm.learning_rate=fast: Value 'fast' of type 'str' could not be "
                                       "converted to Float"),
    (["controller=query", "controller.k_nearest=2.5"], "converted to Integer"),
    (["controller=query", "algorithm.retrace_lambda=0.5"], "algorithm.retrace_lambda=0.5: no key algorithm.retrace_lambda in the config"),
    (["controller=steerable", "controller.sigma_clip=wide"], "controller.sigma_clip=wide"),
])
def test_cli_rejects_bad_values_with_one_line_before_work(tmp_path, args, needle):
    result = _hvc_run(*args, cwd=tmp_path)
    assert result.returncode == 2
    lines = [line for line in result.stderr.splitlines() if line.strip()]
    assert len(lines) == 1, result.stderr
    assert needle in lines[0] and lines[0].startswith("hvc-run: error:")
    assert not (tmp_path / "outputs").exists() or not list((tmp_path / "outputs").rglob("metrics.csv"))


def test_cli_help_lists_groups_and_cfg_prints_composed_config(tmp_path):
    help_text = _hvc_run("--help", cwd=tmp_path).stdout
    for group in ("body", "task", "controller", "algorithm", "clips", "reward"):
        assert f"{group}:" in help_text
    assert "heterogeneous_forage" in help_text and "end_to_end" in help_text
    shown = _hvc_run("--cfg", "job", "controller=fragments", "task=gaps", cwd=tmp_path)
    assert shown.returncode == 0
    assert "name: gaps" in shown.stdout and "name: fragments" in shown.stdout


@pytest.mark.parametrize("sweep,expected", [("fragment_len", {"fragment_len": "1,3,10", "seed": "0,1,2"}),
                                            ("fragment_count", None), ("behaviours", None), ("core_tasks", None),
                                            ("rolling_ball", None)])
def test_sweep_files_compose_with_their_grids(tmp_path, sweep, expected):
    from pathlib import Path

    sweeps = Path(__file__).resolve().parents[1] / "sweeps"
    shown = subprocess.run([sys.executable, "-m", "hvc.cli", "--config-dir", str(sweeps), "--config-name", sweep,
                            "--cfg", "hydra"], capture_output=True, text=True, cwd=tmp_path, timeout=120)
    assert shown.returncode == 0, shown.stderr
    import yaml

    params = yaml.safe_load(shown.stdout)["hydra"]["sweeper"]["params"]
    assert params and all("," in str(v) for v in params.values())
    if expected:
        assert {k: str(v) for k, v in params.items()} == expected
    job = subprocess.run([sys.executable, "-m", "hvc.cli", "--config-dir", str(sweeps), "--config-name", sweep,
                          "--cfg", "job"], capture_output=True, text=True, cwd=tmp_path, timeout=120)
    assert job.returncode == 0 and "stage: train" in job.stdout


def test_every_stage_validate_admits_has_a_runner():
    from hydra.utils import get_method

    from hvc.cli import STAGE_RUNNERS
    from hvc.config import STAGES

    assert set(STAGE_RUNNERS) == set(STAGES)
    assert all(callable(get_method(path)) for path in STAGE_RUNNERS.values())


def test_every_task_kind_validate_admits_has_a_composer_builder():
    from hvc.config import RUNNABLE_TASK_KINDS
    from hvc.envs.builders import TASK_BUILDERS

    assert set(RUNNABLE_TASK_KINDS) == set(TASK_BUILDERS)


def test_openmp_threads_sleep_when_idle_unless_the_user_says_otherwise():
    """Spinning OpenMP threads slowed a 2-thread learner beside another run several-fold."""
    import os
    import subprocess
    import sys

    code = "import hvc, os; print(os.environ['OMP_WAIT_POLICY'])"
    env = {k: v for k, v in os.environ.items() if k != "OMP_WAIT_POLICY"}
    assert subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True).stdout.strip() == "PASSIVE"
    env["OMP_WAIT_POLICY"] = "ACTIVE"
    assert subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True).stdout.strip() == "ACTIVE"
