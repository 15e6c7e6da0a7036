"""The sweep files run as written (budget=smoke, fewer seeds) and a sweep dir becomes a figure:
the paper's figures are one command away."""
import json
import re
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "analysis"))


def _sweep(name: str, *args: str, cwd: Path) -> list[Path]:
    """The job dirs of `hvc-run --config-dir sweeps --config-name <name> -m budget=smoke ...`."""
    sweep_dir = cwd / "sweep"
    result = subprocess.run([sys.executable, "-m", "hvc.cli", "--config-dir", str(REPO / "sweeps"),
                             "--config-name", name, "-m", "budget=smoke", "num_envs=1",
                             f"hydra.sweep.dir={sweep_dir}", *args],
                            capture_output=True, text=True, cwd=cwd, timeout=900)
    assert result.returncode == 0, result.stderr[-3000:]
    return sorted(p for p in sweep_dir.iterdir() if p.is_dir())


def test_fragment_count_arms_run_their_own_skills(tmp_path):
    """Fig. A.4B: x1 / x2 / x4 are 105 / 210 / 420 fragments, not one library thrice."""
    jobs = _sweep("fragment_count", "seed=0", cwd=tmp_path)
    fragments = {}
    for job in jobs:
        clips = yaml.safe_load((job / "config_resolved.yaml").read_text())["clips"]["name"]
        [count] = set(re.findall(r"skills: .* fragments=(\d+)", "".join(p.read_text() for p in job.glob("*.log"))))
        fragments[clips] = int(count)
        assert json.loads((job / "skills.json").read_text())["fragments"] == int(count)  # the job's own record
    assert fragments == {"go_to_target": 105, "go_to_target_x2": 210, "go_to_target_x4": 420}


@pytest.mark.slow  # six training jobs: minutes; the plotting path is covered on hand-made runs in test_aggregate
def test_fragment_len_sweep_to_a_figure_of_means_over_seeds(tmp_path):
    """Fig. A.4A at smoke scale: three lengths x two seeds, one command to the figure."""
    import matplotlib.pyplot as plt
    import plot_sweep

    jobs = _sweep("fragment_len", "seed=0,1", "total_steps=600", cwd=tmp_path)
    assert len(jobs) == 6 and all((j / "summary.json").is_file() for j in jobs)
    out = plot_sweep.main([str(tmp_path / "sweep"), "--by", "fragment_len", "--partial", "-o", str(tmp_path / "a4a.png")])
    assert out.stat().st_size > 5000
    legend = [t.get_text() for t in plt.gcf().legends[0].get_texts()]
    assert [t for t in legend if "seeds" in t] == [f"fragment_len={n} (2 seeds)" for n in (1, 3, 10)]


def test_the_behaviours_sweep_trains_every_arm_from_the_shipped_libraries(tmp_path):
    """Fig. A.4C at smoke scale: go_to_target, locomotion_8 and go_to_target_extraneous each train
    from their shipped library (a set without one fails in one line: tests/test_skills.py)."""
    sweep_dir = tmp_path / "sweep"
    result = subprocess.run([sys.executable, "-m", "hvc.cli", "--config-dir", str(REPO / "sweeps"),
                             "--config-name", "behaviours", "-m", "budget=smoke", "num_envs=1", "seed=0",
                             f"hydra.sweep.dir={sweep_dir}"], capture_output=True, text=True, cwd=tmp_path, timeout=900)
    assert result.returncode == 0, result.stderr[-3000:]
    jobs = sorted(p for p in sweep_dir.iterdir() if p.is_dir())
    assert [(j / "summary.json").exists() for j in jobs] == [True, True, True]
    described = [json.loads((j / "skills.json").read_text()) for j in jobs]
    assert [(d["clip_set"], d["experts"], d["source"]) for d in described] == [
        ("go_to_target", 4, "shipped experts_go_to_target.npz"),
        ("locomotion_8", 8, "shipped experts_locomotion_8.npz"),
        ("go_to_target_extraneous", 8, "shipped experts_go_to_target_extraneous.npz")]
