"""A sixth controller enters through one new file and one config file (issue 20), and
`hvc-run` trains it like the five: written into a copy of the package, nothing else edited."""
import os
import shutil
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parent.parent

CONTROLLER = '''
"""Clip starts: the high level picks a clip and its expert runs from the clip's first frame
for `hold_steps` control steps (fragments of one per clip, all at the start)."""
from hvc.controllers.fragments import FragmentsController
from hvc.envs.spaces import ActionSpace
from hvc.mocap.clip_sets import Fragment


class ClipStartsController(FragmentsController):
    def __init__(self, skills, hold_steps: int):
        super().__init__(skills)
        self.fragments = [Fragment(i, 0, hold_steps) for i in range(len(skills.library.experts))]
        self.action_space = ActionSpace(discrete=True, n=len(self.fragments))

    @classmethod
    def from_config(cls, config, env, skills):
        return cls(skills, int(config["hold_steps"]))
'''

CONFIG = '''
defaults:
  - override /algorithm@_global_.algorithm: vtrace
name: clip_starts
_target_: hvc.controllers.clip_starts.ClipStartsController
skills: clip_set
needs_humanoid: true
algorithms: [vtrace]
hold_steps: 7
'''


def test_a_sixth_controller_is_one_file_and_one_config(tmp_path):
    ignore = shutil.ignore_patterns("__pycache__")
    shutil.copytree(REPO / "hvc", tmp_path / "hvc", ignore=ignore)
    shutil.copytree(REPO / "conf", tmp_path / "conf", ignore=ignore)
    (tmp_path / "hvc" / "controllers" / "clip_starts.py").write_text(textwrap.dedent(CONTROLLER))
    (tmp_path / "conf" / "controller" / "clip_starts.yaml").write_text(textwrap.dedent(CONFIG))
    run_dir = tmp_path / "run"
    env = {**os.environ, "PYTHONPATH": str(tmp_path), "MUJOCO_GL": os.environ.get("MUJOCO_GL", "egl")}
    result = subprocess.run(
        [sys.executable, "-m", "hvc.cli", "controller=clip_starts", "task=go_to_target", "num_envs=1",
         "total_steps=60", "hl.random_episodes=0", "hl.min_replay_unrolls=2", "algorithm.batch_size=2",
         "log_every=10", "record_episodes=1", "task.time_limit=1.0", f"hydra.run.dir={run_dir}"],
        cwd=tmp_path, env=env, capture_output=True, text=True, timeout=600)
    assert result.returncode == 0, result.stderr[-3000:]
    assert "hvc.controllers.clip_starts" in (run_dir / "config_resolved.yaml").read_text()
    episode = np.load(next((run_dir / "episodes").glob("episode_*.npz")))
    chosen = episode["hl_action"][episode["new_action"]]
    assert set(chosen.astype(int)) <= {0, 1, 2, 3}  # one choice per go_to_target clip, not 105 fragments
    held = np.diff(np.flatnonzero(episode["new_action"]))
    assert np.all(held[:-1] == 7) if len(held) > 1 else len(episode["new_action"]) <= 8  # hold_steps
    import pandas as pd

    metrics = pd.read_csv(run_dir / "metrics.csv")
    assert metrics["env_steps"].max() == 60 and "pg_loss" in set(metrics["key"])  # V-trace trained it
