"""Polynomial chaos (PCE) in torch: Legendre bases on uniform inputs, batched least squares,
moments from coefficients, the thesis' reduction step; and the PCE world models built on them."""

from unipolicy_rl.world_models.pce.basis import (
    TRUNCATIONS,
    Basis,
    UniformInputs,
    legendre,
    multi_indices,
    squared_norms,
    total_degree_terms,
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
    "FitDiagnostics",
    "PCEDynamics",
    "PCETrainer",
    "ThesisMEPCE",
    "ThesisPCEDynamics",
    "ThesisPCETrainer",
    "PolynomialChaos",
    "UniformInputs",
    "least_squares",
    "legendre",
    "mean",
    "multi_indices",
    "reduce",
    "solve_normal_equations",
    "squared_norms",
    "total_degree_terms",
    "variance",
]
