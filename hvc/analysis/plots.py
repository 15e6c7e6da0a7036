"""The figures' plots: curves with standard-error bands per arm, one panel per facet, and
final IQM with its confidence interval per arm; legends outside the axes, so that no
curve hides under one."""
from __future__ import annotations

from pathlib import Path
from typing import Sequence

import matplotlib.pyplot as plt
import numpy as np
import pandas as pd

LEGEND_INCHES = 2.2              # room the figure keeps right of its panels for the legend
LEGEND_INCHES_PER_CHAR = 0.065  # legend text at fontsize 8
X_LABELS = {"learner_steps": "transitions processed by the learner", "env_steps": "env steps"}


def _key(group) -> tuple:
    """A groupby key as a tuple, whether pandas gave a scalar or a 1-tuple."""
    return group if isinstance(group, tuple) else (group,)


def _label(keys: Sequence[str], values, depth: int = 2) -> str:
    """`controller=fragments` reads as "fragments"; numbers, "default" and files keep their key,
    files shortened to their last `depth` path parts (a library's folder names its training)."""
    parts = []
    for k, v in zip(keys, _key(values)):
        if isinstance(v, str) and "/" in v:
            parts.append(f"{k}=" + "/".join(part for part in Path(v).parts[-depth:] if part != "/"))
        elif isinstance(v, str) and v != "default" and k not in ("fragment_len", "seed"):
            parts.append(v)
        else:
            parts.append(f"{k}={v}")
    return ", ".join(parts) or "all runs"


def _labels(keys: Sequence[str], arms: Sequence) -> list[str]:
    """A label per arm (in order; an arm may repeat), file paths given as many trailing parts as
    it takes to tell the arms apart (two libraries both named experts_go_to_target.npz in
    folders of the same name), or as given when no number of parts does."""
    unique = {}
    for arm in arms:  # keyed by text, since a NaN value never equals itself
        unique.setdefault(tuple(map(str, _key(arm))), _key(arm))
    depth = 2
    while True:
        labels = {k: _label(keys, arm, depth) for k, arm in unique.items()}
        if len(set(labels.values())) == len(labels):
            break
        if labels == {k: _label(keys, arm, depth + 1) for k, arm in unique.items()}:  # no deeper part tells
            labels = {k: ", ".join(f"{key}={v}" for key, v in zip(keys, arm)) for k, arm in unique.items()}
            break
        depth += 1
    return [labels[tuple(map(str, _key(arm)))] for arm in arms]


def _panels(facet: str | None, frame: pd.DataFrame, width: float = 4.2, height: float = 3.4):
    names = list(pd.unique(frame[facet])) if facet else [None]
    cols = min(len(names), 3)
    rows = int(np.ceil(len(names) / cols))
    fig, axes = plt.subplots(rows, cols, figsize=(width * cols + LEGEND_INCHES, height * rows), squeeze=False,
                             layout="constrained")
    for ax in axes.flat[len(names):]:
        ax.set_visible(False)
    return fig, names, list(axes.flat)


def plot_curves(curves: pd.DataFrame, by: Sequence[str] = (), facet: str | None = None,
                x: str = "learner_steps", scores: pd.DataFrame | None = None, title: str | None = None):
    """One line per arm of `by` (mean over seeds; band: +- one standard error) in one panel
    per value of `facet`; the legend says how many seeds each arm has. A dashed line in the
    arm's colour marks its random policy's return where `scores` (final_scores) gives it."""
    by = [b for b in by if b != facet]
    fig, names, axes = _panels(facet, curves)
    arms = [_key(a) for a in curves.groupby(by, sort=True).groups] if by else [()]
    colours = {arm: f"C{i % 10}" for i, arm in enumerate(arms)}
    labels = dict(zip(arms, _labels(by, arms)))
    for name, ax in zip(names, axes):
        panel = curves[curves[facet] == name] if facet else curves
        for arm, c in (panel.groupby(by, sort=True) if by else [((), panel)]):
            arm = _key(arm) if by else ()
            colour = colours[arm]
            label = f"{labels[arm]} ({c.n_runs.iloc[0]} seeds)"
            ax.plot(c[x], c["mean"], color=colour, label=label)
            ax.fill_between(c[x], c["mean"] - c.se.fillna(0), c["mean"] + c.se.fillna(0), color=colour, alpha=0.25)
            if scores is not None:  # each arm's own random policy: bodies and tasks differ in scale
                mine = scores[facet] == name if facet else pd.Series(True, index=scores.index)
                for key, value in zip(by, arm):
                    mine &= scores[key] == value
                random = scores[mine].random
                if random.notna().any():
                    ax.axhline(random.mean(), color=colour, ls="--", lw=1, label="random policy (dashed)")
        if facet:
            ax.set_title(f"{facet}={name}")
        ax.set_xlabel(X_LABELS[x])
        ax.set_ylabel("return per episode")
        ax.grid(alpha=0.3)
    handles = {}
    for ax in axes:
        for handle, label in zip(*ax.get_legend_handles_labels()):
            handles.setdefault(label, handle)
    if "random policy (dashed)" in handles:
        handles["random policy (dashed)"] = plt.Line2D([], [], color="grey", ls="--", lw=1)
    fig.legend(list(handles.values()), list(handles), loc="outside right upper", fontsize=8)
    # the legend's room comes on top of the panels', so long arm labels do not squeeze the axes
    fig.set_figwidth(fig.get_figwidth() + max(0.0, LEGEND_INCHES_PER_CHAR * max(map(len, handles), default=0) - LEGEND_INCHES))
    if title:
        fig.suptitle(title, x=0.02, ha="left", fontsize=10)
    return fig


def plot_final(table: pd.DataFrame, by: Sequence[str], facet: str | None = None, title: str | None = None):
    """Per arm: the IQM of final returns with its 95% bootstrap CI, one panel per facet."""
    by = [b for b in by if b != facet]
    fig, names, axes = _panels(facet, table, width=max(3.0, 0.7 * len(table) + 1.5), height=3.2)
    names_of = pd.Series(_labels(by, [tuple(r[b] for b in by) for _, r in table.iterrows()]), index=table.index)
    for name, ax in zip(names, axes):
        panel = table[table[facet] == name] if facet else table
        labels = list(names_of[panel.index])
        pos = np.arange(len(panel))
        ax.errorbar(pos, panel.iqm, yerr=[panel.iqm - panel.ci_low, panel.ci_high - panel.iqm],
                    fmt="o", capsize=4)
        for p, (_, r) in zip(pos, panel.iterrows()):
            ax.annotate(f"n={r.n_runs}", (p, r.iqm), textcoords="offset points", xytext=(6, 0), fontsize=7)
        ax.set_xticks(pos, labels, rotation=30, ha="right")
        ax.set_ylabel("final return (IQM, 95% CI)")
        ax.set_title(f"{facet}={name}" if facet else (title or ""))
        ax.grid(alpha=0.3, axis="y")
    return fig
