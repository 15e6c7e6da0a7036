"""Episode records for the analyses (fragment transitions, saliency): per step of env 0,
the high-level action in force (fragment index, turning rate or behaviour), whether it
was newly chosen, the reward, the proprioception and task input and, for vision tasks,
the frame the agent saw: enough to replay the agent's LSTM over the episode. The query
controller's episodes also keep the query in force (the paper's Fig. A.3 projects queries
and fragment keys together)."""
from __future__ import annotations

import csv
from pathlib import Path

import numpy as np


def write_fragment_table(path: Path, skills) -> None:
    """fragments.csv: index, clip, clip id, behaviour, start, length: what a fragment index means."""
    entries = [e.entry for e in skills.library.experts]
    with open(path, "w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(("index", "clip", "clip_id", "behaviour", "start", "length"))
        for i, frag in enumerate(skills.fragments):
            e = entries[frag.clip]
            writer.writerow((i, frag.clip, e["id"], e["behaviour"], frag.start, frag.length))


class EpisodeRecorder:
    def __init__(self, out_dir: Path, max_episodes: int):
        self.out_dir = Path(out_dir)
        self.max_episodes = int(max_episodes)
        self.saved = 0
        self._steps: dict[str, list] = {"hl_action": [], "new_action": [], "reward": [], "image": [],
                                        "proprio": [], "task": [], "query": []}

    @classmethod
    def for_run(cls, cfg, run_dir: Path, skills=None) -> "EpisodeRecorder":
        """`cfg.record_episodes` episodes under run_dir/episodes, with fragments.csv beside them
        when the actions are fragment indices (`skills`: the job's, hvc.skills)."""
        recorder = cls(run_dir / "episodes", int(cfg.record_episodes))
        if recorder.active and skills is not None and skills.fragments:
            write_fragment_table(run_dir / "fragments.csv", skills)
        return recorder

    @property
    def active(self) -> bool:
        return self.saved < self.max_episodes

    def add(self, obs_before: dict, reward: float, info: dict, done: bool, query: np.ndarray | None = None) -> None:
        """One step of env 0: the observation it acted on, then what the step returned, and
        for the query controller the query in force (in the controller's normalised key space)."""
        if not self.active:
            return
        self._steps["hl_action"].append(float(info.get("hl_action", np.nan)))
        self._steps["new_action"].append(bool(info.get("new_action", True)))
        self._steps["reward"].append(float(reward))
        self._steps["proprio"].append(np.asarray(obs_before["proprio"], np.float32))
        self._steps["task"].append(np.asarray(obs_before["task"], np.float32))
        if "image" in obs_before:
            self._steps["image"].append(np.asarray(obs_before["image"], np.uint8))
        if query is not None:
            self._steps["query"].append(np.asarray(query, np.float32))
        if done:
            self.out_dir.mkdir(parents=True, exist_ok=True)
            arrays = {k: np.asarray(v) for k, v in self._steps.items() if v}
            np.savez_compressed(self.out_dir / f"episode_{self.saved:04d}.npz", **arrays)
            self.saved += 1
            self._steps = {k: [] for k in self._steps}
