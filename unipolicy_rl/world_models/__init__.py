"""Surrogate world models: what an env's next state will be, learned from real transitions.

A :class:`Dynamics` predicts (neural ensembles and closed-form polynomial-chaos models alike;
:class:`TokenEnsemble` for robots of any grammar morphology, on a :class:`TokenLayout`) on a
:class:`Layout` of the env's state: :class:`FlatLayout` for any TorchRL env with a flat
observation and a bounded action (``FlatLayout.from_env(env)``), :class:`StateLayout` for the
walker; :class:`ModelTrainer` or :class:`ClosedFormTrainer` fits it (:class:`PendingFit`: on a
second thread while the policy trains); :func:`make_world_model` composes it, with a known or
learned reward and termination, into TorchRL's ``WorldModel``; :class:`ImaginedEnv` rolls
policies through it. :mod:`~unipolicy_rl.evaluation.accuracy` measures its trajectories against
real ones.

Importing this package needs no physics engine: the grammar robots' token models load on first
use (PEP 562), and nothing here imports PyBullet.
"""

import importlib

from unipolicy_rl.world_models.disagreement import DisagreementCut, DisagreementPenalty, MemberDisagreement
from unipolicy_rl.world_models.dynamics import LEARNABLE, REWARD, TERMINATED, Dynamics, NeuralDynamics
from unipolicy_rl.world_models.ensemble import CellEnsemble, GaussianEnsemble
from unipolicy_rl.world_models.episodes import episode_starts
from unipolicy_rl.world_models.imagined import LEARNED, ImaginedEnv, make_world_model, member_returns
from unipolicy_rl.world_models.layout import FlatLayout, Layout, StateLayout
from unipolicy_rl.world_models.pce import PCEDynamics, SparsePCEDynamics, ThesisPCEDynamics
from unipolicy_rl.world_models.pending_fit import PendingFit, check_background_fit
from unipolicy_rl.world_models.trainer import ClosedFormTrainer, FitReport, ModelTrainer, split_transitions

# The grammar robots' token models (their layout reads the grammar's parts) -> their module.
_TOKEN_MODELS = {"TokenEnsemble": "token_ensemble", "TokenLayout": "token_layout"}


def __getattr__(name: str):
    if name not in _TOKEN_MODELS:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    value = getattr(importlib.import_module(f"{__name__}.{_TOKEN_MODELS[name]}"), name)
    globals()[name] = value
    return value


__all__ = [
    "LEARNABLE",
    "LEARNED",
    "REWARD",
    "TERMINATED",
    "CellEnsemble",
    "ClosedFormTrainer",
    "DisagreementCut",
    "DisagreementPenalty",
    "Dynamics",
    "FitReport",
    "FlatLayout",
    "GaussianEnsemble",
    "ImaginedEnv",
    "Layout",
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
    "episode_starts",
    "make_world_model",
    "member_returns",
    "split_transitions",
]
