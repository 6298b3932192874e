"""Surrogate world models: what the robot's next state will be, learned from real transitions.

A :class:`Dynamics` predicts (neural ensembles and closed-form polynomial-chaos models alike;
:class:`TokenEnsemble` for robots of any grammar morphology, on a :class:`TokenLayout`);
:class:`ModelTrainer` or :class:`ClosedFormTrainer` fits it (:class:`PendingFit`: on a second
thread while the policy trains); :func:`make_world_model`
composes it into TorchRL's ``WorldModel``; :class:`ImaginedWalkerEnv` rolls policies through it.
:mod:`~unipolicy_rl.evaluation.accuracy` measures its trajectories against real ones.
"""

from unipolicy_rl.world_models.disagreement import DisagreementCut, MemberDisagreement
from unipolicy_rl.world_models.dynamics import Dynamics, NeuralDynamics
from unipolicy_rl.world_models.ensemble import CellEnsemble, GaussianEnsemble
from unipolicy_rl.world_models.imagined import ImaginedWalkerEnv, make_world_model, member_returns
from unipolicy_rl.world_models.layout import StateLayout
from unipolicy_rl.world_models.pce import PCEDynamics, SparsePCEDynamics, ThesisPCEDynamics
from unipolicy_rl.world_models.pending_fit import PendingFit, check_background_fit
from unipolicy_rl.world_models.token_ensemble import TokenEnsemble
from unipolicy_rl.world_models.token_layout import TokenLayout
from unipolicy_rl.world_models.trainer import ClosedFormTrainer, FitReport, ModelTrainer, split_transitions

__all__ = [
    "CellEnsemble",
    "ClosedFormTrainer",
    "DisagreementCut",
    "Dynamics",
    "FitReport",
    "GaussianEnsemble",
    "ImaginedWalkerEnv",
    "MemberDisagreement",
    "ModelTrainer",
    "NeuralDynamics",
    "PCEDynamics",
    "PendingFit",
    "SparsePCEDynamics",
    "StateLayout",
    "ThesisPCEDynamics",
    "TokenEnsemble",
    "TokenLayout",
    "check_background_fit",
    "make_world_model",
    "member_returns",
    "split_transitions",
]
