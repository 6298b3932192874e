"""The PCE world models: dynamics of an imagined env built on :mod:`unipolicy_rl.polynomial_chaos`.

:class:`PCEDynamics` (``world_model=pce``) expands one control step; :class:`ThesisPCEDynamics`
(``world_model=pce_thesis``) steps the thesis' multi-element PCE; :class:`SparsePCEDynamics`
(``world_model=pce_sparse``) expands one control step with the terms each output's
leave-one-out error chooses. The mathematics they share (bases, least squares, sparse
selection, moments) lives in the library, which knows nothing of world models.
All own their closed-form fit (``fit``); :class:`~unipolicy_rl.world_models.ClosedFormTrainer`
splits the data and calls it.
"""

from unipolicy_rl.world_models.pce.dynamics import PCEDynamics
from unipolicy_rl.world_models.pce.sparse_dynamics import SparsePCEDynamics
from unipolicy_rl.world_models.pce.thesis_dynamics import ThesisPCEDynamics

__all__ = [
    "PCEDynamics",
    "SparsePCEDynamics",
    "ThesisPCEDynamics",
]
