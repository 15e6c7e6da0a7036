"""`stage=evaluate` runs side by side: one row per evaluated library (or policy), its
tracking score per clip and its random-switch survival, so libraries trained with different
options compare in one table (issue 23's goals are per clip and per library)."""
from __future__ import annotations

from typing import Sequence

import pandas as pd

# The survival columns, in the order a reader compares them: random switches, then played on.
SURVIVAL = ("compose_mean_steps", "compose_median_steps", "compose_held_mean_steps", "compose_held_median_steps")


def evaluation_table(frame: pd.DataFrame, by: Sequence[str] = ("library",), score: str = "reward") -> pd.DataFrame:
    """From `load_runs` of evaluate runs: per run (sorted), the `by` options (none: the run
    dir), `score` (reward, completion, fall_rate, ...) of each clip it evaluated (a column per
    clip id, in first-seen order) and the survival columns it logged. A run lacking one
    (another clip set, no composability) has NaN there."""
    by = list(by) or ["run"]
    missing = [k for k in by if k not in frame.columns]
    if missing:
        raise ValueError(f"no option {', '.join(missing)} in these runs; "
                         f"they have: {', '.join(frame.attrs.get('factors', [])) or 'none that differ'}")
    logged = frame.dropna(subset=["key"])
    clips = [k for k in dict.fromkeys(logged.key) if k.startswith(f"{score}/")]
    if not clips:
        raise ValueError(f"no {score}/<clip> rows: are these stage=evaluate runs? (score={score!r})")
    columns = clips + [k for k in SURVIVAL if k in set(logged.key)]
    values = logged[logged.key.isin(columns)].pivot_table(index="run", columns="key", values="value", aggfunc="last")
    labels = frame.groupby("run", sort=True)[[k for k in by if k != "run"]].first()
    table = labels.join(values.reindex(columns=columns)).reset_index()
    table = table[[*by, *columns]] if "run" in by else table[[*by, *columns]]
    return table.rename(columns={c: c.removeprefix(f"{score}/") for c in clips})


def markdown(table: pd.DataFrame, digits: int = 2) -> str:
    """`table` as a markdown table: scores to `digits` decimals, steps to one (whole ones
    without), NaN blank."""
    def cell(column: str, value) -> str:
        if not isinstance(value, float):
            return str(value)
        if pd.isna(value):
            return ""
        return f"{value:.1f}".removesuffix(".0") if column in SURVIVAL else f"{value:.{digits}f}"
    lines = ["| " + " | ".join(map(str, table.columns)) + " |", "|" + " --- |" * len(table.columns)]
    lines += ["| " + " | ".join(cell(c, v) for c, v in zip(table.columns, row)) + " |"
              for row in table.itertuples(index=False)]
    return "\n".join(lines)
