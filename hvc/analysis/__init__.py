"""From run dirs to the paper's figures: load runs into one tidy frame (runs.py), per-episode
returns (returns.py), curves of the mean and its standard error over seeds (curves.py),
final performance as IQM with bootstrap confidence intervals (final.py), their plots
(plots.py), and evaluate runs side by side (evaluations.py). Scripts and notebooks in
analysis/ are thin layers over these."""
from hvc.analysis.curves import curves
from hvc.analysis.final import final_scores, iqm_table, window_scores
from hvc.analysis.returns import episode_returns, mean_episode_length, mean_return
from hvc.analysis.runs import find_runs, load_runs

__all__ = ["curves", "episode_returns", "final_scores", "find_runs", "iqm_table", "load_runs",
           "mean_episode_length", "mean_return", "window_scores"]
