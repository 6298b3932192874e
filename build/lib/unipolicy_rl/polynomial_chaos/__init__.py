"""Polynomial chaos (PCE) in torch, a library of its own: Legendre bases on uniform inputs,
batched least squares, adaptive sparse least squares (terms chosen per output by corrected
leave-one-out error), moments and Sobol' indices from coefficients, the thesis' reduction step and its
multi-element PCE (:class:`ThesisMEPCE`), and a policy's episode over the uncertain design as a
PCE (:class:`DesignResponse`).

It imports no other part of unipolicy_rl, so the PCE world models
(:mod:`unipolicy_rl.world_models.pce`) and the uncertainty quantification of a policy
(:mod:`unipolicy_rl.uq`) both build on it without pulling in each other.
"""

from unipolicy_rl.polynomial_chaos.basis import (
    TRUNCATIONS,
    Basis,
    UniformInputs,
    legendre,
    multi_indices,
    squared_norms,
    total_degree_terms,
)
from unipolicy_rl.polynomial_chaos.design_response import DesignResponse, gauss_legendre_designs, uniform_designs
from unipolicy_rl.polynomial_chaos.expansion import REDUCTIONS, PolynomialChaos, mean, reduce, variance
from unipolicy_rl.polynomial_chaos.regression import FitDiagnostics, least_squares, solve_normal_equations
from unipolicy_rl.polynomial_chaos.sensitivity import SobolIndices, sobol_indices
from unipolicy_rl.polynomial_chaos.sparse import SparseFit, select_terms, sparse_least_squares
from unipolicy_rl.polynomial_chaos.thesis import ThesisMEPCE

__all__ = [
    "REDUCTIONS",
    "TRUNCATIONS",
    "Basis",
    "DesignResponse",
    "FitDiagnostics",
    "PolynomialChaos",
    "SobolIndices",
    "SparseFit",
    "ThesisMEPCE",
    "UniformInputs",
    "gauss_legendre_designs",
    "least_squares",
    "legendre",
    "mean",
    "multi_indices",
    "reduce",
    "select_terms",
    "sobol_indices",
    "solve_normal_equations",
    "sparse_least_squares",
    "squared_norms",
    "total_degree_terms",
    "uniform_designs",
    "variance",
]
