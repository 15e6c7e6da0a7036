"""Saliency maps of a trained high-level agent (the paper's Sec. 3.2 analysis).

    python analysis/saliency.py outputs/<train run dir> [episode index] [out.png]

For a recorded episode (record_episodes=N during stage=train) the agent's LSTM is replayed
over the steps; at each step where a new action was chosen,
    S = min(g, (1/3) sum_c |d log pi(a_t | h_t) / d I_xyc|) / Z
with g the 99th percentile of the raw map (a clip against a few extreme pixels) and Z the
normaliser to [0, 1]. The figure shows frames with their saliency overlaid.
"""
from __future__ import annotations

import argparse
from pathlib import Path

import matplotlib.pyplot as plt
import numpy as np
import torch

from hvc.agents.network import AgentSpec, HighLevelAgent


def load_agent(run_dir: Path) -> HighLevelAgent:
    state = torch.load(run_dir / "checkpoint.pt", weights_only=True, map_location="cpu")
    spec = AgentSpec(**{k: tuple(v) if isinstance(v, list) else v for k, v in state["spec"].items()})
    agent = HighLevelAgent(spec)
    agent.load_state_dict(state["agent"])
    return agent.eval()


def saliency_maps(agent: HighLevelAgent, episode: dict, percentile: float = 99.0) -> tuple[np.ndarray, np.ndarray]:
    """(steps where an action was chosen, maps [n, H, W] in [0, 1])."""
    if not agent.spec.discrete:
        raise ValueError("saliency of log pi(a|h) is implemented for discrete controllers")
    images = torch.from_numpy(episode["image"]).float().requires_grad_(True)
    actions = torch.from_numpy(episode["hl_action"].astype(np.int64)).clamp(min=0)
    prev_action = torch.cat([torch.zeros(1, dtype=torch.long), actions[:-1]])
    rewards = torch.from_numpy(episode["reward"].astype(np.float32))
    prev_reward = torch.cat([torch.zeros(1), rewards[:-1]])
    steps = np.flatnonzero(episode["new_action"])
    maps = []
    for t in steps:
        if images.grad is not None:
            images.grad = None
        logits, _, _ = agent(torch.from_numpy(episode["proprio"][:t + 1, None]),
                             torch.from_numpy(episode["task"][:t + 1, None]), prev_reward[:t + 1, None],
                             prev_action[:t + 1, None], agent.initial_state(1),
                             image=images[:t + 1, None])  # float pixels: gradients reach them
        log_pi = torch.log_softmax(logits[-1, 0], -1)[actions[t]]
        grad, = torch.autograd.grad(log_pi, images, retain_graph=False)
        raw = grad[t].abs().sum(-1).numpy() / 3.0
        g = np.percentile(raw, percentile)
        clipped = np.minimum(g, raw)
        maps.append(clipped / max(clipped.max(), 1e-12))
    return steps, np.asarray(maps)


def plot(run_dir: Path, episode_index: int, out: Path, columns: int = 6) -> Path:
    agent = load_agent(run_dir)
    with np.load(run_dir / "episodes" / f"episode_{episode_index:04d}.npz") as data:
        episode = {k: data[k] for k in data.files}
    steps, maps = saliency_maps(agent, episode)
    pick = np.linspace(0, len(steps) - 1, min(columns, len(steps))).astype(int)
    fig, axes = plt.subplots(1, len(pick), figsize=(2.2 * len(pick), 2.4), squeeze=False)
    for ax, k in zip(axes[0], pick):
        ax.imshow(episode["image"][steps[k]])
        ax.imshow(maps[k], cmap="inferno", alpha=0.6)
        ax.set_title(f"t={steps[k]}")
        ax.axis("off")
    fig.tight_layout()
    fig.savefig(out, dpi=110)
    return out


def main(argv: list[str] | None = None) -> Path:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("run_dir", type=Path, help="a train or record run dir with recorded episodes")
    parser.add_argument("index", type=int, nargs="?", default=0, help="the recorded episode (default 0)")
    parser.add_argument("out", type=Path, nargs="?", help="the figure (default: <run dir>/saliency_<index>.png)")
    args = parser.parse_args(argv)
    return plot(args.run_dir, args.index, args.out or args.run_dir / f"saliency_{args.index}.png")


if __name__ == "__main__":
    print(main())
