"""`hvc-bench` runs end to end (numbers are not asserted: these machines are noisy)."""
import os
import re
import subprocess
import sys


def test_bench_prints_every_measurement_line():
    import importlib.util

    ray = importlib.util.find_spec("ray") is not None
    result = subprocess.run([sys.executable, "-m", "hvc.bench", "--tasks", "go_to_target", "--seconds", "0.2",
                             "--no-composer", "--no-render", "--train-steps", "600", *([] if ray else ["--no-ray"])],
                            capture_output=True, text=True, timeout=600)
    assert result.returncode == 0, result.stderr[-3000:]
    out = result.stdout
    assert re.search(r"bench task=go_to_target ceiling_sps=\d+ hvc_sps=\d+", out)
    for task in ("go_to_target", "gaps"):
        assert re.search(rf"bench hl task={task} controller=fragments actor_sps=\d+ learner_tps=\d+", out)
    if len(os.sched_getaffinity(0)) > 1:  # vision: the learner at torch_threads=auto too
        assert re.search(r"bench hl task=gaps .* learner_tps_\d+_threads=\d+", out)
    for match in re.finditer(r"bench image_precision task=gaps threads=(\d+) float32_tps=(\d+) "
                             r"bfloat16_tps=(\d+) ratio=([\d.]+)", out):
        assert abs(int(match[3]) / int(match[2]) - float(match[4])) < 0.02
    assert len(re.findall(r"bench image_precision task=gaps threads=", out)) == len({1, len(os.sched_getaffinity(0))})
    assert "image_precision task=go_to_target" not in out  # no camera there
    assert re.search(r"bench expert_inference hidden=256 us_per_step=[\d.]+ goal_us=30", out)
    for body in ("body=rolling_ball controller=end_to_end", "controller=fragments"):
        assert re.search(rf"bench vector_env {body} num_envs=2 ceiling_sps=\d+ in_process=0:sps=\d+,ratio=[\d.]+ "
                         rf"in_process=1:sps=\d+,ratio=[\d.]+ in_process=2:sps=\d+,ratio=[\d.]+ goal=0.85", out)
    match = re.search(r"bench train controller=fragments task=go_to_target train_sps=(\d+) actor_sps=(\d+) "
                      r"train_tps=(\d+) learner_tps=(\d+) sum=([\d.]+) goal=0.9", out)
    assert match
    train_sps, actor_sps, train_tps, learner_tps, total = map(float, match.groups())
    assert train_tps > 0 and 0 < train_sps  # the run learned and acted
    assert abs(train_sps / actor_sps + train_tps / learner_tps - total) < 0.02
    if ray:
        match = re.search(r"bench ray_actors controller=fragments num_envs=2 acting local_sps=(\d+) "
                          r"ray_actors_sps=(\d+) ratio=([\d.]+) goal=0.8", out)
        assert match
        local, remote, ratio = map(float, match.groups())
        assert local > 0 and remote > 0 and abs(remote / local - ratio) < 0.01


def test_bench_only_measures_the_lines_asked_for():
    result = subprocess.run([sys.executable, "-m", "hvc.bench", "--only", "expert", "--seconds", "0.2"],
                            capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stderr[-3000:]
    lines = [line for line in result.stdout.splitlines() if line.startswith("bench ")]
    assert len(lines) == 1 and lines[0].startswith("bench expert_inference")
