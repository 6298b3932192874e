"""Evaluation: a policy on a grid of designs (CSV, summary) and the pictures that go with it."""

from unipolicy_rl.evaluation.grid import (
    CSV_COLUMNS,
    GRID_WALKING_MEAN,
    WALKING_DISPLACEMENT,
    DesignResult,
    design_rollouts,
    episode_outcomes,
    evaluate_on_designs,
    format_summary,
    format_table,
    grid_score,
    read_csv,
    rollout_designs,
    summarise,
    walks_the_grid,
    write_csv,
)
from unipolicy_rl.evaluation.plots import plot_heatmaps, plot_training_curve

__all__ = [
    "CSV_COLUMNS",
    "GRID_WALKING_MEAN",
    "WALKING_DISPLACEMENT",
    "DesignResult",
    "design_rollouts",
    "episode_outcomes",
    "evaluate_on_designs",
    "format_summary",
    "format_table",
    "grid_score",
    "plot_heatmaps",
    "plot_training_curve",
    "read_csv",
    "rollout_designs",
    "summarise",
    "walks_the_grid",
    "write_csv",
]
