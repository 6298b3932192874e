"""Evaluation: a policy on a grid of designs (CSV, summary), on every morphology of a set
(``robot=grammar``), its real episodes at any designs
(:func:`policy_trajectories`) and the pictures that go with them.

How close a surrogate's trajectories are to real ones is measured by
:mod:`unipolicy_rl.evaluation.accuracy`, imported from there.
"""

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
from unipolicy_rl.evaluation.morphologies import (
    MorphologyResult,
    evaluate_on_morphologies,
    format_morphology_summary,
    summarise_morphologies,
    write_morphology_csvs,
)
from unipolicy_rl.evaluation.plots import plot_heatmaps, plot_training_curve
from unipolicy_rl.evaluation.trajectories import policy_trajectories

__all__ = [
    "CSV_COLUMNS",
    "GRID_WALKING_MEAN",
    "WALKING_DISPLACEMENT",
    "DesignResult",
    "MorphologyResult",
    "design_rollouts",
    "episode_outcomes",
    "evaluate_on_designs",
    "evaluate_on_morphologies",
    "format_morphology_summary",
    "format_summary",
    "format_table",
    "grid_score",
    "plot_heatmaps",
    "plot_training_curve",
    "policy_trajectories",
    "read_csv",
    "rollout_designs",
    "summarise",
    "summarise_morphologies",
    "walks_the_grid",
    "write_csv",
    "write_morphology_csvs",
]
