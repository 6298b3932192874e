"""Polynomial chaos: the Legendre basis, batched least squares, moments and the reduction step."""

import ast
import math
import subprocess
import sys

import numpy as np
import pytest
import torch
from numpy.polynomial import legendre as npleg
from tensordict import TensorDict

from unipolicy_rl.polynomial_chaos import (
    Basis,
    PolynomialChaos,
    UniformInputs,
    least_squares,
    legendre,
    multi_indices,
    reduce,
    solve_normal_equations,
    squared_norms,
    variance,
)
from unipolicy_rl.world_models import StateLayout


def imported_by(module: str, prefixes: tuple[str, ...]) -> list[str]:
    """The modules under ``prefixes`` that importing ``module`` loads, in a fresh interpreter
    (the test process has imported everything already)."""
    script = (f"import sys, {module}; "
              f"print(sorted(m for m in sys.modules if m.startswith({prefixes!r})))")
    result = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, result.stderr
    return ast.literal_eval(result.stdout.strip().splitlines()[-1])


def test_the_polynomial_chaos_library_imports_no_world_model_and_no_evaluation():
    assert imported_by("unipolicy_rl.polynomial_chaos", ("unipolicy_rl.world_models", "unipolicy_rl.collectors",
                                                         "unipolicy_rl.objectives", "unipolicy_rl.evaluation")) == []


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
        (lambda: least_squares(torch.ones(4, 1), torch.ones(4, 1), dropped=torch.tensor([True])),
         "dropped holds every term of a problem at zero"),
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


def one_input_held(problems: int, n: int, seed: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Samples ``[problems, n, 2]`` whose input 1 sits at 0.3 throughout, and noisy targets in input 0."""
    g = torch.Generator().manual_seed(seed)
    x = torch.rand(problems, n, 2, generator=g, dtype=torch.float64) * 2 - 1
    x[..., 1] = 0.3
    y = torch.sin(3 * x[..., :1]) + 0.1 * torch.randn(problems, n, 1, generator=g, dtype=torch.float64)
    return x, y


def test_a_singular_fit_falls_back_to_a_solve_that_reaches_the_least_squares_optimum():
    # An input that never varies repeats the constant term in its terms' columns: the Gram matrix is singular.
    # torch's default CPU driver (gelsy) misjudges this matrix's rank and leaves a residual far above the optimum,
    # silently: the fallback must use a driver that finds the rank.
    x, y = one_input_held(4, 60, seed=0)
    design = Basis.create(2, 3)(x)
    coefficients, diagnostics = least_squares(design, y)
    assert diagnostics.fallbacks == 4 and bool(diagnostics.failed.all())  # Cholesky could factor none of them
    assert bool((diagnostics.condition > 1e12).all())  # and the condition says why
    for p in range(4):
        optimum = np.linalg.lstsq(design[p].numpy(), y[p].numpy(), rcond=None)[0]  # SVD-based
        ours = design[p].numpy() @ coefficients[p].numpy()
        np.testing.assert_allclose(np.linalg.norm(ours - y[p].numpy()),
                                   np.linalg.norm(design[p].numpy() @ optimum - y[p].numpy()), rtol=1e-12)
        np.testing.assert_allclose(ours, design[p].numpy() @ optimum, atol=1e-10)  # the optimum's fitted values


def test_an_input_that_never_varies_has_its_terms_dropped_and_is_reported():
    x, y = one_input_held(3, 60, seed=1)
    # A sample of weight 0 is no part of the fit: where input 1 differs there, it still never varies.
    x, y = torch.cat([x, torch.full((3, 1, 2), 0.9, dtype=torch.float64)], 1), torch.cat([y, y[:, :1]], 1)
    weights = torch.ones(3, 61, dtype=torch.float64)
    weights[:, -1] = 0
    pce = PolynomialChaos.fit(x, y, [-1, -1], [1, 1], order=3, weights=weights)
    diagnostics = pce.diagnostics
    assert diagnostics.constant_inputs == (1,) and diagnostics.fallbacks == 0
    involves = pce.basis.indices[:, 1] > 0
    assert torch.equal(diagnostics.dropped, involves.expand(3, -1))
    assert diagnostics.summary()["dropped_terms"] == 3 * int(involves.sum())
    assert bool((pce.coefficients[:, involves] == 0).all())  # nothing attributed to the input that never moved
    # The rest is the expansion in input 0 alone: the same least-squares optimum, the same moments.
    alone = PolynomialChaos.fit(x[..., :1], y, [-1], [1], order=3, weights=weights)
    torch.testing.assert_close(pce.coefficients[:, ~involves], alone.coefficients, atol=1e-12, rtol=0)
    torch.testing.assert_close(pce.variance(), alone.variance(), atol=1e-12, rtol=0)
    assert diagnostics.condition.max() < 10  # the condition of the kept terms, as if the others were absent
    torch.testing.assert_close(diagnostics.condition, alone.diagnostics.condition)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_a_singular_cuda_fit_is_solved_on_the_cpu_and_handed_back_on_the_gpu():
    # CUDA's only lstsq driver assumes full rank: the fallback solves there on the CPU.
    x, y = one_input_held(2, 60, seed=2)
    design = Basis.create(2, 3)(x)
    on_gpu, diagnostics = least_squares(design.cuda(), y.cuda())
    on_cpu, _ = least_squares(design, y)
    assert on_gpu.device.type == "cuda" and diagnostics.fallbacks == 2
    torch.testing.assert_close(on_gpu.cpu(), on_cpu)


def test_a_float32_factor_falls_back_to_float64_where_it_cannot_factor():
    # [[1, 1], [1, 1 + 1e-9]] is positive definite, but singular once rounded to float32.
    gram = torch.tensor([[[1.0, 1.0], [1.0, 1.0 + 1e-9]], [[2.0, 0.0], [0.0, 3.0]]], dtype=torch.float64)
    moment = torch.tensor([[[2.0], [2.0 + 1e-9]], [[2.0], [3.0]]], dtype=torch.float64)
    samples = torch.tensor([10, 10])
    exact, _ = solve_normal_equations(gram, moment, torch.ones(2, 1, dtype=torch.float64), samples)
    assert torch.linalg.cholesky_ex(gram[0].float()).info != 0  # the premise: float32 cannot factor it
    mixed, diagnostics = solve_normal_equations(gram, moment, torch.ones(2, 1, dtype=torch.float64), samples,
                                                factor_dtype=torch.float32)
    assert diagnostics.fallbacks == 0
    torch.testing.assert_close(mixed, exact, rtol=1e-5, atol=1e-5)
    torch.testing.assert_close(mixed[1], torch.ones(2, 1, dtype=torch.float64))


def test_the_transposed_design_matrix_is_the_design_matrix():
    basis = Basis.create(4, 3, "hyperbolic", q=0.75)
    z = torch.rand(2, 7, 4, dtype=torch.float64) * 2 - 1
    direct = torch.stack([torch.stack([legendre(z[..., j], 3)[..., a] for j, a in enumerate(row)]).prod(0)
                          for row in basis.indices.tolist()], -1)
    torch.testing.assert_close(basis.transposed(z), direct.transpose(-1, -2))
    torch.testing.assert_close(basis(z), direct)


# ---- the one-step PCE world model (world_model=pce) -------------------------------------------

def test_the_one_step_pce_fits_a_toy_dynamics_to_a_stated_held_out_error():
    from test_world_models import TOY, one_step_r2, toy_transitions

    from unipolicy_rl.world_models import ClosedFormTrainer, PCEDynamics

    model = PCEDynamics(TOY, action_dim=2, order=3, truncation="total_degree", max_interaction=None,
                        interactions="all", members=3)
    report = ClosedFormTrainer().fit(model, toy_transitions(4000, 0), torch.Generator().manual_seed(0))
    held_out = toy_transitions(1000, 1)
    # Stated accuracy: the held-out one-step prediction explains >= 95% of the state change's variance.
    assert one_step_r2(model, held_out) >= 0.95, report
    assert int(model.fitted_terms) == model.terms == 165 and report.validation_error.shape == (3,)
    assert (report.validation_error < 0.05).all()
    member = torch.zeros(1000, dtype=torch.long)
    args = (held_out["state"], held_out["action"], held_out["design"], member)
    assert torch.equal(model.predict(*args, deterministic=True), model.predict(*args, deterministic=True))
    assert not torch.equal(model.predict(*args), model.predict(*args))  # residual noise
    # Bootstrap members differ, a little.
    other = model.predict(*args[:3], torch.ones(1000, dtype=torch.long), deterministic=True)
    assert 0 < (other - model.predict(*args, deterministic=True)).abs().mean() < 0.01
    # Few data: only the leading (low-degree) terms are fitted, never an underdetermined system.
    small = PCEDynamics(TOY, action_dim=2, order=3, truncation="total_degree", max_interaction=None,
                        interactions="all", members=1)
    ClosedFormTrainer(oversampling=2.0).fit(small, toy_transitions(100, 2), torch.Generator().manual_seed(0))
    assert int(small.fitted_terms) == 40 and (small.coefficients[:, 40:] == 0).all()


def test_the_members_normal_equations_are_the_weighted_sums_over_whole_episode_groups():
    from test_world_models import TOY, toy_transitions

    from unipolicy_rl.world_models import PCEDynamics
    from unipolicy_rl.world_models.pce import dynamics
    from unipolicy_rl.world_models.trainer import EPISODE_START

    model = PCEDynamics(TOY, action_dim=2, order=3, truncation="total_degree", max_interaction=None,
                        interactions="all", members=3, chunk_size=700)
    data = toy_transitions(3000, 0)
    data.set(EPISODE_START, torch.arange(3000) % 10 == 0)  # 300 episodes of 10 steps
    train = torch.randperm(3000, generator=torch.Generator().manual_seed(1))[:2400]
    bootstrap = model.episode_bootstrap(data, train, torch.Generator().manual_seed(0))
    # Whole episodes: every training row of an episode shares its group (and so its draws).
    episode = train // 10
    assert bootstrap.groups == dynamics.BOOTSTRAP_GROUPS
    for e in episode.unique()[:50]:
        assert bootstrap.group[episode == e].unique().numel() == 1
    weights = bootstrap.weights()
    assert (weights[0] == 1).all() and not (weights[1:] == 1).all()
    assert torch.equal(bootstrap.samples(), (weights > 0).sum(1))
    # The grouped, chunked sums equal the brute-force X^T W X, X^T W Y, sum w y^2 (float64).
    inputs, targets, _ = model.regression_data(data)
    model.set_data_ranges(inputs[train], targets[train], targets[train])
    active = torch.arange(model.terms)
    gram, moment, square = model.normal_equations(inputs[train], targets[train], bootstrap, active)
    x, y, w = model.design_matrix(inputs[train]).double(), targets[train].double(), weights.double()
    torch.testing.assert_close(gram, torch.einsum("mr,ri,rj->mij", w, x, x), rtol=1e-5, atol=1e-3)
    torch.testing.assert_close(moment, torch.einsum("mr,ri,ro->mio", w, x, y), rtol=1e-5, atol=1e-3)
    torch.testing.assert_close(square, w @ y.pow(2), rtol=1e-9, atol=0)


def test_a_singular_gram_matrix_is_fitted_with_a_larger_ridge_and_the_ridge_used_is_reported():
    """Two inputs that are one (as the velocities of rigidly joined links nearly are): without a
    ridge their normal equations are singular; the fit raises the ridge until every member factors."""
    from test_world_models import TOY, one_step_r2, toy_transitions

    from unipolicy_rl.world_models import ClosedFormTrainer, PCEDynamics

    def duplicated(n: int, seed: int):
        data = toy_transitions(n, seed)
        for key in ("state", "next_state"):
            data[key][:, 5] = data[key][:, 4]
        return data

    def fitted(ridge: float):
        model = PCEDynamics(TOY, action_dim=2, order=3, truncation="total_degree", max_interaction=None,
                            interactions="all", members=3, ridge=ridge)
        return model, ClosedFormTrainer().fit(model, duplicated(4000, 0), torch.Generator().manual_seed(0))

    model, report = fitted(0.0)
    assert 0 < report.extras["ridge"] <= 1e-2
    reference, _ = fitted(1e-3)  # a ridge that factors at once: the retried fit is as good
    held_out = duplicated(1000, 1)
    assert one_step_r2(model, held_out) >= one_step_r2(reference, held_out) - 0.01 >= 0.8
    plain = ClosedFormTrainer().fit(PCEDynamics(TOY, action_dim=2, members=3), toy_transitions(4000, 0),
                                    torch.Generator().manual_seed(0))
    assert plain.extras["ridge"] == 1e-6  # factorable at the configured ridge: unchanged


def test_a_long_pce_rollout_keeps_velocities_within_the_datas_range_but_lets_positions_move_on():
    from test_world_models import TOY, toy_transitions

    from unipolicy_rl.world_models import ClosedFormTrainer, PCEDynamics

    model = PCEDynamics(TOY, action_dim=2, order=3, members=1, margin=0.1)
    data = toy_transitions(2000, 0)
    ClosedFormTrainer().fit(model, data, torch.Generator().manual_seed(0))
    velocities = torch.tensor(TOY.velocity_columns)
    seen = data["next_state"][:, velocities]
    low, high = seen.amin(0), seen.amax(0)
    state = data["state"][:200].clone()
    member = torch.zeros(200, dtype=torch.long)
    start = state.clone()
    for _ in range(200):  # the same extreme action every step: drives the toy's rates one way
        state = model.predict(state, torch.ones(200, 2), data["design"][:200], member)
    margin = 0.1 * (high - low)
    assert (state[:, velocities] >= low - margin - 1e-5).all() and (state[:, velocities] <= high + margin + 1e-5).all()
    assert ((state - start)[:, :2].abs() > high.abs().max()).any()  # positions are free to leave it


def test_the_one_step_pce_fits_real_robot_data_at_two_samples_per_term():
    """The first fits of PCE-TRPO: 20 real episodes, 1,600 training transitions, and bootstrap
    members that draw whole episodes, the one that sees the fewest rows setting the basis (two
    rows per term). The robot's features are strongly correlated, and in float32 the Gram matrix
    lost its positive definiteness here (the run stopped)."""
    from torchrl.envs.utils import RandomPolicy

    from unipolicy_rl.collectors import transitions
    from unipolicy_rl.envs import BatchedWalkerEnv, RobotSettings
    from unipolicy_rl.world_models import PCEDynamics, StateLayout

    env = BatchedWalkerEnv(20, full_state=True, episode_length=None)
    env.set_seed(0)
    torch.manual_seed(0)
    rollout = env.rollout(100, RandomPolicy(env.action_spec), break_when_any_done=False)
    env.close()
    layout = StateLayout.for_env(RobotSettings(), "thesis", False, "full")
    model = PCEDynamics(layout, 4)
    data = transitions(rollout, layout.from_full)
    order = torch.randperm(2000, generator=torch.Generator().manual_seed(1))
    train, validation = order[:1600], order[1600:]
    fewest = int(model.episode_bootstrap(data, train, torch.Generator().manual_seed(0)).samples().min())
    report = model.fit(data, train, validation, 2.0, torch.Generator().manual_seed(0))
    assert int(model.fitted_terms) == fewest // 2 and fewest < 1600
    assert torch.isfinite(report.validation_error).all() and (report.validation_error < 1.5).all()


def test_the_one_step_pce_sparse_basis_keeps_only_control_interactions():
    from test_world_models import TOY

    from unipolicy_rl.world_models import PCEDynamics

    model = PCEDynamics(TOY, action_dim=2)  # 4 features, 2 actions, 2 design values
    active = model.basis.indices > 0
    multi = active.sum(1) > 1
    assert (active[multi][:, 4:].any(1)).all() and multi.any()
    with pytest.raises(ValueError, match="interactions must be one of"):
        PCEDynamics(TOY, action_dim=2, interactions="some")
    with pytest.raises(ValueError, match="truncation must be one of"):
        PCEDynamics(TOY, action_dim=2, truncation="box")


# A two-epoch source=pce run, small imagined batches and checks (tests here and in test_pce_narx.py).
PCE_TINY = ["source=pce", "workers=1", "epochs=2", "evaluation.every_steps=1", "imagination.steps_per_batch=60",
            "imagination.horizon.start=3", "imagination.horizon.end=3", "imagination.stopping.max_updates=2",
            "imagination.stopping.check_every=2", "imagination.stopping.check_starts=4",
            "imagination.stopping.check_horizon=3"]


@pytest.mark.slow
def test_train_with_the_pce_source_runs_end_to_end(tmp_path):
    from test_train import TINY, run_train

    result = run_train(*TINY, *PCE_TINY, f"hydra.run.dir={tmp_path}")
    assert result.returncode == 0, result.stderr
    text = (tmp_path / "metrics.csv").read_text()
    assert "model/validation_mse" in text and "imagined/reward_per_step" in text
    assert "model/kept_updates" in text  # source=pce keeps imagined updates by the real rule (short_branch)


# ---- the thesis' ME-PCE (standalone) ----------------------------------------------------------

def toy_episodes(n: int, seed: int, horizon: int = 6, held_at_bound: int | None = None):
    """A state that depends smoothly on the design and the last two actions only (action
    ``held_at_bound`` always 1, as a policy pushing a joint to its limit)."""
    g = torch.Generator().manual_seed(seed)
    design = torch.stack([0.15 + 0.05 * torch.rand(n, generator=g), 0.4 + 0.2 * torch.rand(n, generator=g)], -1)
    actions = torch.rand(n, horizon, 2, generator=g) * 2 - 1
    if held_at_bound is not None:
        actions[..., held_at_bound] = 1.0
    states = torch.zeros(n, horizon, 2)
    for t in range(1, horizon + 1):
        last = actions[:, t - 1]
        before = actions[:, t - 2] if t >= 2 else torch.zeros_like(last)
        states[:, t - 1, 0] = 10 * design[:, 0] * last[:, 0] + before[:, 1] ** 2 + 0.1 * t
        states[:, t - 1, 1] = design[:, 1] * last[:, 1] * before[:, 0]
    return design, actions, states


def test_the_thesis_me_pce_recovers_a_windowed_state_and_its_moments():
    from unipolicy_rl.polynomial_chaos import ThesisMEPCE

    design, actions, states = toy_episodes(3000, 0)
    pce = ThesisMEPCE((0.15, 0.2), (0.4, 0.6), action_dim=2, order=3, divisions=2, window=2)
    assert pce.terms == math.comb(6 + 3, 3)
    report = pce.fit(design, actions, states)
    assert report["max_condition"] < 100
    d2, a2, s2 = toy_episodes(500, 1)
    torch.testing.assert_close(pce.predict(d2, a2), s2, atol=1e-4, rtol=0)  # exact: the state is in the basis
    mean, var = pce.moments()
    d3, a3, _ = toy_episodes(60_000, 2)
    sampled = pce.predict(d3, a3)
    torch.testing.assert_close(mean, sampled.mean(0), atol=0.01, rtol=0.01)
    torch.testing.assert_close(var, sampled.var(0), atol=0.01, rtol=0.02)
    # Fitting one more action and reducing it away keeps the mean; the variance mode keeps the variance too.
    for mode in ("projection", "variance"):
        reduced = ThesisMEPCE((0.15, 0.2), (0.4, 0.6), action_dim=2, order=3, divisions=2, window=2, reduction=mode)
        reduced.fit(design, actions, states)
        reduced_mean, reduced_var = reduced.moments()
        torch.testing.assert_close(reduced_mean, mean, atol=1e-3, rtol=0)
        torch.testing.assert_close(reduced_var, var, atol=1e-3, rtol=1e-3)
    with pytest.raises(ValueError, match="underdetermined fit: 84 terms per element"):
        pce.fit(design[:200], actions[:200], states[:200])
    with pytest.raises(ValueError, match="divisions must be an integer >= 1, got 0"):
        ThesisMEPCE((0.15, 0.2), (0.4, 0.6), divisions=0)
    with pytest.raises(ValueError, match=r"design \[0.3"):
        pce.predict(torch.tensor([[0.3, 0.5]]), a2[:1])


# ---- the thesis' ME-PCE as a world model (world_model=pce_thesis) -------------------------------

TOY_STATE = StateLayout(num_bodies=0, num_joint_values=2, state_columns=(0, 1), observation_columns=(0, 1))


def toy_batch(n: int, seed: int, horizon: int = 6, held_at_bound: int | None = None) -> TensorDict:
    """:func:`toy_episodes` as a real batch ``[robots, steps]``: every row one episode from a reset (state 0)."""
    design, actions, states = toy_episodes(n, seed, horizon, held_at_bound)
    before = torch.cat([torch.zeros(n, 1, 2), states[:, :-1]], 1)
    return TensorDict({"state": before, "action": actions, "design": design.unsqueeze(1).expand(n, horizon, 2),
                       "next": {"state": states, "physics_fault": torch.zeros(n, horizon, 1, dtype=torch.bool)}},
                      [n, horizon])


def imagine(model, batch: TensorDict) -> torch.Tensor:
    """The model stepped from each episode's start with the episode's actions: ``[n, horizon, outputs]``."""
    state = torch.cat([batch["state"][:, 0], model.memory_of(batch)[0][:, 0]], -1)
    out = []
    for s in range(batch.shape[1]):
        state = model.predict(state, batch["action"][:, s], batch["design"][:, s], None)
        out.append(state[:, :model.layout.robot_size])
    return torch.stack(out, 1)


def test_the_thesis_world_model_steps_its_memory_and_reproduces_held_out_episodes():
    from unipolicy_rl.collectors import transitions
    from unipolicy_rl.world_models import ClosedFormTrainer, ThesisPCEDynamics

    model = ThesisPCEDynamics(TOY_STATE, action_dim=2, length_range=(0.15, 0.2), density_range=(0.4, 0.6),
                              horizon=6, order=3, divisions=2, window=2)
    assert model.layout.size == 2 + 1 + 2  # the state, the step, the one past action of a window of 2
    data = transitions(toy_batch(3000, 0), TOY_STATE.from_full, model.memory_of)
    report = ClosedFormTrainer().fit(model, data, torch.Generator().manual_seed(0))
    assert model.fitted_terms == model.terms and report.members_without_data == 0
    assert float(report.validation_error[0]) < 1e-6  # the toy state lies in the basis
    held_out = toy_batch(200, 1)
    # Stepped through its own memory, the model follows whole held-out episodes open loop.
    torch.testing.assert_close(imagine(model, held_out), held_out["next", "state"], atol=1e-3, rtol=0)


def test_the_thesis_world_model_fits_what_few_episodes_determine():
    from unipolicy_rl.collectors import transitions
    from unipolicy_rl.world_models import ClosedFormTrainer, ThesisPCEDynamics

    def fitted(episodes: int, divisions: int):
        model = ThesisPCEDynamics(TOY_STATE, action_dim=2, length_range=(0.15, 0.2), density_range=(0.4, 0.6),
                                  horizon=6, order=3, divisions=divisions, window=2)
        data = transitions(toy_batch(episodes, 0), TOY_STATE.from_full, model.memory_of)
        return model, ClosedFormTrainer().fit(model, data, torch.Generator().manual_seed(0))

    # 300 episodes over 4 elements (60 per element and step, 84 terms): the leading terms, never an
    # underdetermined solve; they hold most of the toy state.
    model, report = fitted(300, 2)
    assert 1 <= model.fitted_terms < model.terms
    assert float(report.validation_error[0]) < 0.05
    # 10 episodes over 16 elements: unvisited elements are reported and predict their step's mean.
    model, report = fitted(10, 4)
    assert report.members_without_data > 0
    assert torch.isfinite(imagine(model, toy_batch(50, 1))).all()


def test_the_thesis_world_model_solves_an_element_whose_actions_sit_at_their_bound():
    from unipolicy_rl.collectors import transitions
    from unipolicy_rl.world_models import ClosedFormTrainer, ThesisPCEDynamics

    def saturated(n: int, seed: int) -> TensorDict:
        return toy_batch(n, seed, held_at_bound=1)  # the held action's terms repeat the constant

    model = ThesisPCEDynamics(TOY_STATE, action_dim=2, length_range=(0.15, 0.2), density_range=(0.4, 0.6),
                              horizon=6, order=3, divisions=1, window=2, ridge=0.0)
    data = transitions(saturated(600, 0), TOY_STATE.from_full, model.memory_of)
    report = ClosedFormTrainer().fit(model, data, torch.Generator().manual_seed(0))
    assert report.extras["solve_fallbacks"] == 0  # the held action's terms are left out, the rest is well posed
    held_out = saturated(100, 1)
    torch.testing.assert_close(imagine(model, held_out), held_out["next", "state"], atol=1e-3, rtol=0)


def test_a_singular_element_is_solved_by_rank_revealing_least_squares_and_counted():
    from unipolicy_rl.polynomial_chaos import ThesisMEPCE

    pce = ThesisMEPCE((0.15, 0.2), (0.4, 0.6), action_dim=1, order=2, divisions=1, window=1)
    g = torch.Generator().manual_seed(0)
    xt = pce.fit_basis.transposed(torch.rand(1, 50, 3, generator=g, dtype=torch.float64) * 2 - 1)
    xt[:, 2] = xt[:, 1]  # two terms equal on every sample: the normal equations are singular
    y = (xt[:, 0] + 2 * xt[:, 1] - xt[:, 3]).unsqueeze(-1)
    weight, counts = torch.ones(1, 50, dtype=torch.float64), torch.tensor([50])
    c, diagnostics = pce.solve_step(xt, y, weight, counts, t=1, fallback=True)
    assert diagnostics.fallbacks == 1
    torch.testing.assert_close((xt.mT @ c), y, atol=1e-4, rtol=0)  # a solution that fits
    torch.testing.assert_close(c[0, 1], c[0, 2])  # the minimum-norm one splits the repeated term evenly


@pytest.mark.slow
def test_train_with_the_thesis_pce_world_model_runs_end_to_end(tmp_path):
    from test_train import TINY, run_train

    result = run_train(*TINY, "source=pce", "world_model=pce_thesis", "workers=1", "epochs=2",
                       "evaluation.every_steps=1", "world_model.model.divisions=2", "world_model.model.order=2",
                       "imagination.steps_per_batch=60", "imagination.stopping.max_updates=2",
                       f"hydra.run.dir={tmp_path}")
    assert result.returncode == 0, result.stderr
    text = (tmp_path / "metrics.csv").read_text()
    assert "model/validation_mse" in text and "imagined/reward_per_step" in text


def test_the_basis_fitted_is_set_by_the_member_that_sees_the_fewest_rows():
    """A Poisson draw of whole episodes can leave a member a small share of a buffer of few
    episodes (a first epoch): the basis then shrinks to what that member can fit, never an
    underdetermined member."""
    from test_world_models import TOY, toy_transitions

    from unipolicy_rl.world_models import PCEDynamics
    from unipolicy_rl.world_models.trainer import EPISODE_START

    model = PCEDynamics(TOY, action_dim=2, order=3, truncation="total_degree", max_interaction=None,
                        interactions="all", members=3)
    data = toy_transitions(530, 0)
    data.set(EPISODE_START, torch.arange(530) % 100 == 0)  # 6 episodes, 5 of them in training
    train, validation = torch.arange(430), torch.arange(430, 530)
    assert len(train) / 2.0 > model.terms  # the plain sample alone would fit every term
    fewest = []
    for seed in range(10):
        generator = torch.Generator().manual_seed(seed)
        samples = model.episode_bootstrap(data, train, torch.Generator().manual_seed(seed)).samples()
        model.fit(data, train, validation, 2.0, generator)
        assert int(model.fitted_terms) == min(model.terms, int(samples.min()) // 2)
        assert torch.isfinite(model.coefficients).all() and (model.coefficients[:, int(model.fitted_terms):] == 0).all()
        fewest.append(int(samples.min()))
    assert min(fewest) < model.terms  # some draw left a member fewer rows than the whole basis has terms


def test_imagined_branches_draw_only_the_members_within_the_elite_tolerance_of_the_best():
    """A bootstrap member fitted on a few episodes can be far worse than the plain fit on held-out
    rows; with ``elite_tolerance`` the members whose validation error is more than that multiple
    of the best are left out of the draw, and without it every member is drawn."""
    from test_world_models import TOY, toy_transitions

    from unipolicy_rl.world_models import PCEDynamics
    from unipolicy_rl.world_models.trainer import EPISODE_START

    data = toy_transitions(530, 0)
    data.set(EPISODE_START, torch.arange(530) % 100 == 0)  # 6 episodes, 5 of them in training
    train, validation = torch.arange(430), torch.arange(430, 530)
    design = torch.zeros(4000, 2)
    left_out = 0
    for seed in range(10):
        model = PCEDynamics(TOY, action_dim=2, order=3, truncation="total_degree", max_interaction=None,
                            interactions="all", members=3, elite_tolerance=1.2)
        report = model.fit(data, train, validation, 2.0, torch.Generator().manual_seed(seed))
        error = report.validation_error
        expected = (error <= 1.2 * error.min()).nonzero().squeeze(1)
        assert torch.equal(model.elites, expected) and report.elites == expected.tolist()
        assert report.extras["elites"] == len(expected)
        drawn = model.draw_members(design, torch.Generator().manual_seed(seed)).unique()
        assert torch.equal(drawn, expected)
        left_out += 3 - len(expected)
    assert left_out > 0  # some draw of a few episodes made a member worse than 1.2x the best
    every = PCEDynamics(TOY, action_dim=2, order=3, truncation="total_degree", max_interaction=None,
                        interactions="all", members=3, elite_tolerance=None)
    every.fit(data, train, validation, 2.0, torch.Generator().manual_seed(0))
    assert every.draw_members(design, torch.Generator().manual_seed(0)).unique().tolist() == [0, 1, 2]


def test_a_bad_elite_tolerance_is_refused_and_an_old_checkpoint_loads_every_member_as_elite():
    from test_world_models import TOY

    from unipolicy_rl.world_models import PCEDynamics

    for bad in (0.5, -1.0, True, "1.5"):
        with pytest.raises(ValueError, match=f"elite_tolerance must be a number >= 1 .*got {bad!r}"):
            PCEDynamics(TOY, action_dim=2, elite_tolerance=bad)
    model = PCEDynamics(TOY, action_dim=2, members=3, elite_tolerance=1.5)
    state = model.state_dict()
    del state["elite_mask"]
    state["elites"] = torch.arange(3)  # as checkpoints before the elite mask kept them
    model.elite_mask.fill_(False)
    model.load_state_dict(state)
    assert model.elites.tolist() == [0, 1, 2]
