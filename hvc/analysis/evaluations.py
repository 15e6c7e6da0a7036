"""`stage=evaluate` runs side by side: one row per evaluated library (or policy), its
tracking score per clip and its random-switch survival, so libraries trained with different
options compare in one table (issue 23's goals are per clip and per library)."""
from __future__ import annotations

import re
from typing import Sequence

import pandas as pd

# The survival columns, in the order a reader compares them: random switches, then played on.
SURVIVAL = ("compose_mean_steps", "compose_median_steps", "compose_held_mean_steps", "compose_held_median_steps")
# Each median's 95% bootstrap interval (logged since 2026-12-06): columns of the table, printed inside the median's cell.
INTERVALS = {median: (f"{median.removesuffix('_steps')}_ci95_low", f"{median.removesuffix('_steps')}_ci95_high")
             for median in SURVIVAL if median.endswith("_median_steps")}


def evaluation_table(frame: pd.DataFrame, by: Sequence[str] = ("library",), score: str = "reward") -> pd.DataFrame:
    """From `load_runs` of evaluate runs: per run (in the order of their dirs' names, numbers
    read as numbers, so a sweep's jobs keep theirs), the `by` options naming it, `score`
    (reward, completion, fall_rate, ...) of each clip it evaluated (a column per clip id, in
    first-seen order) and the survival columns it logged; NaN where a run lacks one (another
    clip set, no composability). The run dir is added where the `by` options name two runs
    alike, and each run's status where one has not finished."""
    by = list(by) or ["run"]
    missing = [k for k in by if k not in frame.columns]
    if missing:
        raise ValueError(f"no option {', '.join(missing)} in these runs; options that differ between them: "
                         f"{', '.join(frame.attrs.get('factors', [])) or 'none'}")
    logged = frame.dropna(subset=["key"])
    clips = [k for k in dict.fromkeys(logged.key) if k.startswith(f"{score}/")]
    if not clips:
        raise ValueError(f"no {score}/<clip> rows: are these stage=evaluate runs? (score={score!r})")
    survival = [c for k in SURVIVAL for c in (k, *INTERVALS.get(k, ())) if c in set(logged.key)]
    columns = clips + survival
    values = logged[logged.key.isin(columns)].pivot_table(index="run", columns="key", values="value", aggfunc="last")
    labels = [k for k in by if k != "run"]
    runs = frame.groupby("run")[["status", *labels]].first()
    runs = runs.loc[sorted(runs.index, key=_natural)]
    if "run" not in by and runs[labels].astype(str).duplicated(keep=False).any():
        by = ["run", *by]
    shown = by + (["status"] if (runs.status != "finished").any() else [])
    table = runs.join(values.reindex(columns=columns)).reset_index()[[*shown, *columns]]
    names = {c: c.removeprefix(f"{score}/") for c in clips}
    table = table.rename(columns=names)
    table.attrs["scores"] = list(names.values())  # which columns are clips (for markdown)
    return table


def markdown(table: pd.DataFrame, digits: int = 2) -> str:
    """`table` (an `evaluation_table`) as a markdown table: clip scores to `digits` decimals,
    survival steps to one (whole ones without), a median with its interval as `26 [24, 29]`,
    other columns as they are, NaN blank."""
    scores = set(table.attrs.get("scores", []))
    bounds = {c for pair in INTERVALS.values() for c in pair}
    shown = [c for c in table.columns if c not in bounds]

    def steps(value) -> str:
        return f"{value:.1f}".removesuffix(".0")

    def cell(column: str, row: dict) -> str:
        value = row[column]
        if isinstance(value, float) and pd.isna(value):
            return ""
        if column in SURVIVAL:
            low, high = (row.get(c, float("nan")) for c in INTERVALS.get(column, ("", "")))
            return steps(value) + ("" if pd.isna(low) or pd.isna(high) else f" [{steps(low)}, {steps(high)}]")
        return f"{value:.{digits}f}" if column in scores else str(value)
    lines = ["| " + " | ".join(map(str, shown)) + " |", "|" + " --- |" * len(shown)]
    lines += ["| " + " | ".join(cell(c, row) for c in shown) + " |" for row in table.to_dict("records")]
    return "\n".join(lines)


def _natural(text: str) -> list:
    return [int(part) if part.isdigit() else part for part in re.split(r"(\d+)", str(text))]
