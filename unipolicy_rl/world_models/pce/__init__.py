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
from unipolicy_rl.world_models.pce.expansion import REDUCTIONS, PolynomialChaos, mean, reduce, variance
from unipolicy_rl.world_models.pce.regression import FitDiagnostics, least_squares

__all__ = [
    "REDUCTIONS",
    "TRUNCATIONS",
    "Basis",
    "FitDiagnostics",
    "PolynomialChaos",
    "UniformInputs",
    "least_squares",
    "legendre",
    "mean",
    "multi_indices",
    "reduce",
    "squared_norms",
    "total_degree_terms",
    "variance",
]
