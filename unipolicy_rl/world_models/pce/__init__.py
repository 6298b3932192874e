"""Polynomial chaos (PCE) in torch: Legendre bases on uniform inputs, batched least squares,
moments from coefficients, the thesis' reduction step; the PCE world models built on them; and a
policy's episode over the uncertain design as a PCE (:class:`DesignResponse`)."""

from unipolicy_rl.world_models.pce.basis import (
    TRUNCATIONS,
    Basis,
    UniformInputs,
    legendre,
    multi_indices,
    squared_norms,
    total_degree_terms,
)
from unipolicy_rl.world_models.pce.design_response import (
    DesignResponse,
    gauss_legendre_designs,
    policy_trajectories,
    uniform_designs,
)
from unipolicy_rl.world_models.pce.dynamics import PCEDynamics, PCETrainer
from unipolicy_rl.world_models.pce.expansion import REDUCTIONS, PolynomialChaos, mean, reduce, variance
from unipolicy_rl.world_models.pce.regression import FitDiagnostics, least_squares, solve_normal_equations
from unipolicy_rl.world_models.pce.thesis import ThesisMEPCE
from unipolicy_rl.world_models.pce.thesis_dynamics import ThesisPCEDynamics, ThesisPCETrainer

__all__ = [
    "REDUCTIONS",
    "TRUNCATIONS",
    "Basis",
    "DesignResponse",
    "FitDiagnostics",
    "PCEDynamics",
    "PCETrainer",
    "ThesisMEPCE",
    "ThesisPCEDynamics",
    "ThesisPCETrainer",
    "PolynomialChaos",
    "UniformInputs",
    "gauss_legendre_designs",
    "least_squares",
    "legendre",
    "mean",
    "multi_indices",
    "policy_trajectories",
    "reduce",
    "solve_normal_equations",
    "squared_norms",
    "total_degree_terms",
    "uniform_designs",
    "variance",
]
