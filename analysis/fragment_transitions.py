"""Fragment transition density (the paper's Sec. 3.2 / Appendix C analysis).

    python analysis/fragment_transitions.py outputs/<run dir> [out.png]

Reads the run's recorded episodes (record_episodes=N) and fragments.csv, counts how often
fragment i is followed by fragment j when the high level chooses, and draws the density
with the clips' boundaries, plus how often each clip's fragments were chosen.
`behaviour_shares` sets each behaviour's share of the choices beside its share of the
library's fragments (Fig. A.4C: are extraneous behaviours ignored?).
"""
from __future__ import annotations

import argparse
from pathlib import Path

import matplotlib.pyplot as plt
import numpy as np
import pandas as pd


def chosen_fragments(run_dir: Path, skip_rewarded_at_start: bool = False) -> list[np.ndarray]:
    """The fragments the high level chose, one array per recorded episode. `skip_rewarded_at_start`
    leaves out the episodes rewarded from their first step (on go_to_target: spawned at the target,
    where the agent only stands), so what is left describes the walks to the target."""
    episodes = []
    for path in sorted((run_dir / "episodes").glob("episode_*.npz")):
        with np.load(path) as ep:
            if skip_rewarded_at_start and len(ep["reward"]) and ep["reward"][0] > 0:
                continue
            picks = ep["hl_action"][ep["new_action"]].astype(int)
        episodes.append(picks[picks >= 0])
    return episodes


def transition_counts(run_dir: Path) -> tuple[np.ndarray, pd.DataFrame]:
    table = pd.read_csv(run_dir / "fragments.csv")
    n = len(table)
    counts = np.zeros((n, n))
    for chosen in chosen_fragments(run_dir):
        np.add.at(counts, (chosen[:-1], chosen[1:]), 1)
    return counts, table


def behaviour_shares(run_dir: Path, skip_rewarded_at_start: bool = False) -> pd.DataFrame:
    """Per behaviour: `chosen`, its share of the high level's choices, and `fragments`, its share
    of the library (what uniform choices would give); `skip_rewarded_at_start` as in `chosen_fragments`."""
    table = pd.read_csv(run_dir / "fragments.csv")
    chosen = chosen_fragments(run_dir, skip_rewarded_at_start)
    picks = np.concatenate(chosen) if chosen else np.zeros(0, int)
    behaviours = list(dict.fromkeys(table.behaviour))
    counts = pd.Series(table.behaviour.to_numpy()[picks]).value_counts().reindex(behaviours, fill_value=0)
    return pd.DataFrame({"chosen": counts / max(len(picks), 1),
                         "fragments": table.behaviour.value_counts(normalize=True).reindex(behaviours)},
                        index=pd.Index(behaviours, name="behaviour"))


def draw(counts: np.ndarray, table: pd.DataFrame, title: str = "fragment transitions (log density)"):
    """Fig. A.5: the transition density with the clips' blocks, beside the share of choices per behaviour."""
    density = counts / max(counts.sum(), 1)
    fig, (ax, bx) = plt.subplots(1, 2, figsize=(12, 5), gridspec_kw={"width_ratios": [3, 2]}, layout="constrained")
    ax.imshow(np.log1p(density * 1e4), cmap="magma", origin="lower")
    for b in np.flatnonzero(np.diff(table["clip"].values)) + 0.5:
        ax.axhline(b, color="w", lw=0.5)
        ax.axvline(b, color="w", lw=0.5)
    ax.set(xlabel="next fragment", ylabel="fragment", title=title)
    usage = table.assign(chosen=counts.sum(0) + counts.sum(1)).groupby("behaviour", sort=False).chosen.sum()
    bx.bar(usage.index, usage.values / max(usage.values.sum(), 1))
    bx.set_title("share of choices per behaviour")
    bx.tick_params(axis="x", rotation=45)
    return fig


def plot(run_dir: Path, out: Path) -> Path:
    fig = draw(*transition_counts(run_dir))
    fig.savefig(out, dpi=110)
    return out


def main(argv: list[str] | None = None) -> Path:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("run_dir", type=Path, help="a run dir with episodes/ and fragments.csv (record_episodes=N)")
    parser.add_argument("out", type=Path, nargs="?", help="the figure (default: <run dir>/fragment_transitions.png)")
    args = parser.parse_args(argv)
    return plot(args.run_dir, args.out or args.run_dir / "fragment_transitions.png")


if __name__ == "__main__":
    print(main())
