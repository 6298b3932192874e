"""Surrogate world models: what the robot's next state will be, learned from real transitions.

A :class:`DynamicsModel` predicts; :class:`ModelTrainer` fits it; :func:`make_world_model`
composes it into TorchRL's ``WorldModel``; :class:`ImaginedWalkerEnv` rolls policies through it.
:mod:`~unipolicy_rl.world_models.accuracy` measures its trajectories against real ones.
"""

from unipolicy_rl.world_models.accuracy import (
    band,
    jensen_shannon,
    normalised_mean_difference,
    plot_bands,
    relative_error,
)
from unipolicy_rl.world_models.ensemble import CellEnsemble, DynamicsModel, GaussianEnsemble
from unipolicy_rl.world_models.imagined import ImaginedWalkerEnv, make_world_model, member_returns
from unipolicy_rl.world_models.layout import StateLayout
from unipolicy_rl.world_models.pce import PCEDynamics, PCETrainer, ThesisPCEDynamics, ThesisPCETrainer
from unipolicy_rl.world_models.trainer import FitReport, ModelTrainer

__all__ = [
    "CellEnsemble",
    "DynamicsModel",
    "FitReport",
    "GaussianEnsemble",
    "ImaginedWalkerEnv",
    "ModelTrainer",
    "PCEDynamics",
    "PCETrainer",
    "StateLayout",
    "ThesisPCEDynamics",
    "ThesisPCETrainer",
    "band",
    "jensen_shannon",
    "make_world_model",
    "member_returns",
    "normalised_mean_difference",
    "plot_bands",
    "relative_error",
]
