"""Polynomial chaos: the Legendre basis, batched least squares, moments and the reduction step."""

import math

import numpy as np
import pytest
import torch
from numpy.polynomial import legendre as npleg

from unipolicy_rl.world_models.pce import (
    Basis,
    PolynomialChaos,
    UniformInputs,
    least_squares,
    legendre,
    multi_indices,
    reduce,
    squared_norms,
    variance,
)


def gauss_legendre_grid(dimension: int, points: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Tensor-product Gauss-Legendre nodes on [-1, 1]^d and weights of the uniform density (sum 1)."""
    nodes, weights = npleg.leggauss(points)
    grids = np.meshgrid(*([nodes] * dimension), indexing="ij")
    w = np.ones_like(grids[0])
    for wg in np.meshgrid(*([weights / 2] * dimension), indexing="ij"):
        w = w * wg
    return (torch.from_numpy(np.stack([g.ravel() for g in grids], -1)), torch.from_numpy(w.ravel()))


@pytest.mark.parametrize("orthonormal", [True, False])
def test_the_basis_is_orthogonal_under_the_uniform_measure_with_the_legendre_norms(orthonormal):
    basis = Basis.create(3, 4, orthonormal=orthonormal)
    z, w = gauss_legendre_grid(3, 6)  # exact for degree <= 11 per input, the products here reach 8
    psi = basis(z)
    gram = psi.T @ (psi * w.unsqueeze(-1))
    expected = torch.diag(squared_norms(basis.indices, orthonormal))
    torch.testing.assert_close(gram, expected, atol=1e-12, rtol=0)
    if not orthonormal:
        # E[P_n^2] = 1/(2n+1), not the Hermite n!: P_3 of one input has norm 1/7 (Hermite would say 6).
        term = basis.indices.tolist().index([3, 0, 0])
        assert math.isclose(float(gram[term, term]), 1 / 7)


def test_the_recurrence_matches_direct_evaluation():
    z = torch.linspace(-1, 1, 41, dtype=torch.float64)
    values = legendre(z, 5, orthonormal=False)
    for n in range(6):
        direct = npleg.legval(z.numpy(), [0] * n + [1])
        np.testing.assert_allclose(values[:, n].numpy(), direct, atol=1e-12)


def test_multi_index_sets_have_the_stated_sizes():
    assert multi_indices(14, 3).shape == (680, 14)  # C(17, 3), the thesis' basis
    assert multi_indices(2, 3).shape == (10, 2)
    total = multi_indices(5, 3)
    assert (total.sum(1) <= 3).all() and (total[0] == 0).all()
    hyperbolic = multi_indices(5, 3, "hyperbolic", q=0.5)
    assert ((hyperbolic > 0).sum(1) <= 1).all() and hyperbolic.shape[0] == 1 + 5 * 3  # no interactions survive
    assert multi_indices(5, 3, "hyperbolic", q=1.0).shape == total.shape
    limited = multi_indices(5, 3, max_interaction=2)
    assert ((limited > 0).sum(1) <= 2).all() and limited.shape[0] == total.shape[0] - math.comb(5, 3)


def test_the_fit_recovers_a_known_expansion():
    g = torch.Generator().manual_seed(0)
    basis = Basis.create(3, 3)
    truth = torch.randn(basis.terms, 2, generator=g, dtype=torch.float64)
    low, high = torch.tensor([0.15, 0.4, -1.0]), torch.tensor([0.2, 0.6, 1.0])
    x = low + (high - low) * torch.rand(500, 3, generator=g, dtype=torch.float64)
    y = basis(UniformInputs(low, high).to_unit(x)) @ truth
    pce = PolynomialChaos.fit(x, y, low, high, order=3)
    torch.testing.assert_close(pce.coefficients, truth, atol=1e-9, rtol=0)
    assert pce.diagnostics.residual_rms.max() < 1e-9 and pce.diagnostics.condition.max() < 10


def test_the_batched_fit_matches_numpy_lstsq_on_a_directly_evaluated_design_matrix():
    rng = np.random.default_rng(1)
    indices = multi_indices(2, 3)
    problems, n = 4, 60
    x = rng.uniform(-1, 1, size=(problems, n, 2))
    y = np.sin(3 * x[..., :1]) * np.exp(x[..., 1:]) + 0.1 * rng.normal(size=(problems, n, 1))
    ours, _ = least_squares(Basis(indices, orthonormal=False)(torch.from_numpy(x)), torch.from_numpy(y))
    for p in range(problems):
        # Reference: each column built by numpy's own Legendre evaluation, solved by numpy.
        columns = [np.prod([npleg.legval(x[p, :, j], [0] * a + [1]) for j, a in enumerate(row)], axis=0)
                   for row in indices.tolist()]
        reference = np.linalg.lstsq(np.stack(columns, -1), y[p], rcond=None)[0]
        np.testing.assert_allclose(ours[p].numpy(), reference, atol=1e-10)


def test_moments_from_the_coefficients_match_monte_carlo_of_the_fitted_model():
    g = torch.Generator().manual_seed(2)
    low, high = [0.15, 0.4], [0.2, 0.6]
    x = torch.tensor(low) + torch.tensor([0.05, 0.2]) * torch.rand(400, 2, generator=g)
    y = torch.stack([torch.exp(5 * x[:, 0]) * x[:, 1], torch.cos(10 * x[:, 1]) + x[:, 0] ** 2], -1).double()
    for orthonormal in (True, False):
        pce = PolynomialChaos.fit(x.double(), y, low, high, order=4, orthonormal=orthonormal)
        samples = torch.tensor(low) + torch.tensor([0.05, 0.2]) * torch.rand(400_000, 2, generator=g)
        model = pce(samples.double())
        torch.testing.assert_close(pce.mean(), model.mean(0), rtol=2e-3, atol=1e-4)
        torch.testing.assert_close(pce.variance(), model.var(0), rtol=2e-2, atol=1e-6)


def test_the_reduction_keeps_the_mean_and_the_variance_it_should():
    g = torch.Generator().manual_seed(3)
    dimension, order = 4, 3
    for orthonormal in (True, False):
        indices = multi_indices(dimension, order)
        norms = squared_norms(indices, orthonormal)
        c = torch.randn(5, indices.shape[0], 2, generator=g, dtype=torch.float64)  # 5 expansions, 2 outputs
        full_variance = variance(c, norms)
        kept_indices, projected = reduce(c, indices, [0], "projection", norms)
        assert (kept_indices[:, 0] == 0).all() and kept_indices.shape[0] == math.comb(3 + 3, 3)
        torch.testing.assert_close(projected[..., 0, :], c[..., 0, :])  # the mean
        # The projection loses exactly the dropped input's share of the variance...
        involved = indices[:, 0] > 0
        share = (c[..., involved, :] ** 2 * norms[involved].unsqueeze(-1)).sum(-2)
        torch.testing.assert_close(variance(projected, norms[(indices[:, 0] == 0)]), full_variance - share)
        # ... which is E[y | kept inputs] (law of total variance): averaged over z_0 by quadrature.
        basis = Basis(indices, orthonormal)
        z = torch.rand(500, dimension, generator=g, dtype=torch.float64) * 2 - 1
        nodes, weights = (torch.from_numpy(a) for a in npleg.leggauss(order + 1))
        grid = z.unsqueeze(0).repeat(order + 1, 1, 1)
        grid[..., 0] = nodes.unsqueeze(-1)
        conditional = ((basis(grid) @ c[0]) * (weights / 2).reshape(-1, 1, 1)).sum(0)
        reduced = Basis(kept_indices, orthonormal)(z) @ projected[0]
        torch.testing.assert_close(reduced, conditional, atol=1e-10, rtol=0)
        # The thesis' mode keeps the full variance, with the Legendre norms.
        _, matched = reduce(c, indices, [0], "variance", norms)
        torch.testing.assert_close(matched[..., 0, :], c[..., 0, :])
        torch.testing.assert_close(variance(matched, norms[(indices[:, 0] == 0)]), full_variance)


@pytest.mark.parametrize(
    ("call", "match"),
    [
        (lambda: multi_indices(3, -1), "order must be an integer >= 0, got -1"),
        (lambda: multi_indices(3, 2, "simplex"), "truncation must be one of .*'simplex'"),
        (lambda: multi_indices(3, 2, "hyperbolic", q=1.5), "q must lie in"),
        (lambda: legendre(torch.zeros(3), -2), "order must be an integer >= 0, got -2"),
        (lambda: UniformInputs([0.2], [0.15]), r"low < high, got \[0.2, 0.15\]"),
        (lambda: UniformInputs([0.15, 0.4], [0.2, 0.6]).to_unit(torch.tensor([[0.17, 0.7]])),
         "input 1 = 0.7.* outside its uniform range"),
        (lambda: PolynomialChaos.fit(torch.rand(5, 3), torch.rand(5, 1), [0] * 3, [1] * 3, order=2),
         "underdetermined fit: 10 terms but only 5 samples"),
        (lambda: least_squares(torch.ones(4, 3), torch.full((4, 1), math.nan)), "targets has non-finite"),
        (lambda: reduce(torch.zeros(4, 1), multi_indices(3, 1), [5]), "cannot drop input 5"),
        (lambda: reduce(torch.zeros(4, 1), multi_indices(3, 1), [0], "hermite"), "reduction must be one of"),
    ],
)
def test_bad_input_is_refused_by_name(call, match):
    with pytest.raises(ValueError, match=match):
        call()


def test_an_ill_conditioned_fit_is_reported_not_silent():
    x = torch.linspace(-1, 1, 50, dtype=torch.float64).unsqueeze(-1)
    design = torch.cat([torch.ones_like(x), x, x], -1)  # two identical columns: singular
    coefficients, diagnostics = least_squares(design, 2 * x + 1)
    assert torch.isfinite(coefficients).all()
    assert diagnostics.fallbacks == 1 or diagnostics.condition.max() > 1e6
    torch.testing.assert_close(design @ coefficients, 2 * x + 1)
