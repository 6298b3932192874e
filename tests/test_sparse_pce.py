"""Adaptive sparse polynomial chaos: terms chosen per output by corrected leave-one-out error."""

import pytest
import torch
from tensordict import TensorDict
from test_world_models import THESIS_FROM_FULL, TOY, one_step_r2, real_transitions, toy_transitions
from torchrl.envs.utils import check_env_specs

from unipolicy_rl.envs import BatchedWalkerEnv, RewardWeights
from unipolicy_rl.networks import make_actor
from unipolicy_rl.polynomial_chaos import Basis, PolynomialChaos, UniformInputs, sparse_least_squares
from unipolicy_rl.world_models import ClosedFormTrainer, ImaginedEnv, SparsePCEDynamics, make_world_model
from unipolicy_rl.world_models.trainer import EPISODE_START

LOW = torch.tensor([0.15, 0.4, -1.0, -2.0], dtype=torch.float64)
HIGH = torch.tensor([0.2, 0.6, 1.0, 2.0], dtype=torch.float64)
# Two outputs, each a handful of terms of the order-4 hyperbolic (q = 0.75) basis in 4 inputs (35 terms).
SPARSE_TRUTH = [
    {(0, 0, 0, 0): 1.0, (1, 0, 0, 0): 0.5, (0, 2, 0, 0): -0.8, (1, 0, 1, 0): 0.4},
    {(0, 0, 0, 1): 2.0, (0, 0, 3, 0): 0.3, (2, 1, 0, 0): 0.6},
]
NOISE = 0.02


def sparse_problem(n: int, seed: int) -> tuple[Basis, torch.Tensor, torch.Tensor, torch.Tensor]:
    """(basis, true coefficients ``[35, 2]``, samples ``x [n, 4]`` in their ranges, noisy ``y [n, 2]``)."""
    basis = Basis.create(4, 4, "hyperbolic", q=0.75)
    rows = basis.indices.tolist()
    truth = torch.zeros(basis.terms, 2, dtype=torch.float64)
    for output, terms in enumerate(SPARSE_TRUTH):
        for index, value in terms.items():
            truth[rows.index(list(index)), output] = value
    g = torch.Generator().manual_seed(seed)
    x = LOW + (HIGH - LOW) * torch.rand(n, 4, generator=g, dtype=torch.float64)
    y = basis(UniformInputs(LOW, HIGH).to_unit(x)) @ truth + NOISE * torch.randn(n, 2, generator=g,
                                                                                   dtype=torch.float64)
    return basis, truth, x, y


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_the_sparse_fit_recovers_a_known_sparse_polynomial_from_noisy_samples(seed):
    basis, truth, x, y = sparse_problem(150, seed)  # 150 samples, 35 candidates, 3-4 true terms per output
    pce, fit = PolynomialChaos.fit_sparse(x, y, LOW, HIGH, order=4, q=0.75, tolerance=0.1)
    assert torch.equal(fit.selected, truth != 0)  # exactly the true terms, per output
    assert torch.equal(pce.basis.indices, basis.indices)
    # The coefficient's standard error is NOISE / sqrt(150) = 0.0016: within 0.01 is about 6 of them.
    torch.testing.assert_close(pce.coefficients, truth, atol=0.01, rtol=0)
    assert (fit.loo_error < 10 * NOISE**2 / y.var(0)).all()
    # Blatman and Sudret's rule (the lowest error) keeps every true term; what noise adds is noise-sized.
    _, lowest = PolynomialChaos.fit_sparse(x, y, LOW, HIGH, order=4, q=0.75)
    assert (lowest.selected >= (truth != 0)).all() and (lowest.terms >= fit.terms).all()
    extra = lowest.selected & (truth == 0)
    assert (lowest.coefficients[extra].abs() < 0.01).all()


def brute_force_loo(design: torch.Tensor, y: torch.Tensor, weights: torch.Tensor) -> float:
    """Mean over every row of ``(y_i - x_i c_(-i))^2``, ``c_(-i)`` the weighted least squares without row i."""
    errors = []
    for i in range(len(y)):
        keep = torch.ones(len(y), dtype=torch.bool)
        keep[i] = False
        root = weights[keep].sqrt().unsqueeze(-1)
        solution = torch.linalg.lstsq(design[keep] * root, y[keep].unsqueeze(-1) * root, driver="gelsd").solution
        errors.append(float((design[i] @ solution.squeeze(-1) - y[i]) ** 2))
    return sum(errors) / len(errors)


@pytest.mark.parametrize("weighted", [False, True])
def test_the_leave_one_out_error_along_the_path_matches_brute_force(weighted):
    g = torch.Generator().manual_seed(4)
    basis = Basis.create(2, 3)  # 10 terms
    z = torch.rand(40, 2, generator=g, dtype=torch.float64) * 2 - 1
    design = basis(z)
    y = torch.sin(2 * z[:, :1]) + z[:, 1:] ** 2 + 0.05 * torch.randn(40, 1, generator=g, dtype=torch.float64)
    # A bootstrap draw: rows drawn twice (left out with both copies) and rows not drawn (out of bag).
    weights = torch.poisson(torch.ones(40), generator=g).double() if weighted else torch.ones(40, dtype=torch.float64)
    fit = sparse_least_squares(design, y, weights, patience=10)  # no early end: the whole path
    path = fit.path[0]
    assert sorted(path.tolist()) == list(range(10))
    total = float(weights.sum())
    for k in range(1, 11):
        columns = design[:, path[:k]]
        gram = columns.T @ (columns * weights.unsqueeze(-1))
        chapelle = total / (total - k) * (1 + float(torch.linalg.inv(gram).trace()))
        expected = brute_force_loo(columns, y[:, 0], weights) * chapelle / float(y.var(correction=0))
        assert float(fit.loo_path[0, k - 1]) == pytest.approx(expected, rel=1e-8), k
    # The chosen fit is the weighted least squares on its terms.
    chosen = fit.selected[:, 0]
    root = weights.sqrt().unsqueeze(-1)
    reference = torch.linalg.lstsq(design[:, chosen] * root, y * root, driver="gelsd").solution
    torch.testing.assert_close(fit.coefficients[chosen], reference, atol=1e-10, rtol=0)
    assert (fit.coefficients[~chosen] == 0).all()
    assert float(fit.loo_error[0]) == float(fit.loo_path[0].min())


def test_problems_in_a_batch_are_fitted_as_if_alone():
    _, _, x, y = sparse_problem(120, 5)
    design = Basis.create(4, 4, "hyperbolic", q=0.75)(UniformInputs(LOW, HIGH).to_unit(x))
    weights = torch.poisson(torch.ones(3, 120), generator=torch.Generator().manual_seed(0)).double()
    together = sparse_least_squares(design.expand(3, -1, -1), y.expand(3, -1, -1), weights)
    for member in range(3):
        alone = sparse_least_squares(design, y, weights[member])
        assert torch.equal(together.selected[member], alone.selected)
        torch.testing.assert_close(together.coefficients[member], alone.coefficients, atol=1e-12, rtol=0)
    assert not torch.equal(together.selected[0], together.selected[1])  # different draws, different terms


def test_an_input_that_never_varies_is_no_candidate_and_the_fit_is_that_of_the_others():
    g = torch.Generator().manual_seed(6)
    x = torch.rand(80, 2, generator=g, dtype=torch.float64) * 2 - 1
    x[:, 1] = 0.3
    y = 1.0 + x[:, :1] - 0.5 * x[:, :1] ** 3 + 0.01 * torch.randn(80, 1, generator=g, dtype=torch.float64)
    pce, fit = PolynomialChaos.fit_sparse(x, y, [-1, -1], [1, 1], order=4, q=1.0, max_interaction=None,
                                          tolerance=0.1)
    involves = pce.basis.indices[:, 1] > 0
    assert not fit.selected[involves].any() and (pce.coefficients[involves] == 0).all()
    alone, _ = PolynomialChaos.fit_sparse(x[:, :1], y, [-1], [1], order=4, q=1.0, max_interaction=None,
                                          tolerance=0.1)
    torch.testing.assert_close(pce.coefficients[~involves], alone.coefficients, atol=1e-12, rtol=0)
    # x - x^3 / 2 in orthonormal Legendre terms: the constant, P1 and P3 only.
    assert pce.basis.indices[fit.selected[:, 0]].tolist() == [[0, 0], [1, 0], [3, 0]]


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_fewer_samples_than_candidate_terms_give_a_sparse_fit_of_the_truth(seed):
    """40 samples, 56 candidates: least squares on the whole basis is underdetermined, the sparse
    fit is not. Every true term is found; with this few samples greedy selection also fits some
    noise (the left-out rows cannot see that a term was chosen for them), so the claim is the
    fit's accuracy, not its exact terms."""
    g = torch.Generator().manual_seed(seed)
    basis = Basis.create(3, 5)  # 56 candidate terms
    z = torch.rand(40, 3, generator=g, dtype=torch.float64) * 2 - 1
    truth = torch.zeros(basis.terms, 1, dtype=torch.float64)
    truth[[0, 2, 9], 0] = torch.tensor([1.0, -2.0, 0.7], dtype=torch.float64)
    noise = 0.01
    y = basis(z) @ truth + noise * torch.randn(40, 1, generator=g, dtype=torch.float64)
    pce, fit = PolynomialChaos.fit_sparse(z, y, [-1] * 3, [1] * 3, order=5, q=1.0, max_interaction=None,
                                          tolerance=0.1)
    assert (fit.selected >= (truth != 0)).all() and int(fit.terms) <= 13
    fresh = torch.rand(2000, 3, generator=g, dtype=torch.float64) * 2 - 1
    assert float((pce(fresh) - basis(fresh) @ truth).square().mean().sqrt()) < 2 * noise
    with pytest.raises(ValueError, match="at least 2 samples of weight > 0 .*got 1"):
        PolynomialChaos.fit_sparse(z[:1], y[:1], [-1] * 3, [1] * 3, order=5)


@pytest.mark.parametrize(
    ("settings", "match"),
    [
        ({"order": -1}, "order must be an integer >= 0, got -1"),
        ({"order": 2.5}, "order must be an integer >= 0, got 2.5"),
        ({"q": 0.0}, "q must lie in .* got 0.0"),
        ({"q": 1.5}, "q must lie in .* got 1.5"),
        ({"max_terms": 0}, "max_terms must be a positive integer or None, got 0"),
        ({"patience": 0}, "patience must be a positive integer, got 0"),
        ({"tolerance": -0.1}, "tolerance must be a finite number >= 0, got -0.1"),
        ({"max_interaction": 0}, "max_interaction must be an integer >= 1 or None, got 0"),
    ],
)
def test_bad_sparse_settings_are_refused_by_name(settings, match):
    _, _, x, y = sparse_problem(40, 0)
    with pytest.raises(ValueError, match=match):
        PolynomialChaos.fit_sparse(x, y, LOW, HIGH, **{"order": 3, **settings})


# ---- the sparse one-step PCE world model (world_model=pce_sparse) ------------------------------

def episodes(transitions: TensorDict, length: int) -> TensorDict:
    """``transitions`` cut into episodes of ``length`` rows, marked as the replay buffer marks them."""
    start = torch.arange(transitions.batch_size[0]) % length == 0
    return transitions.set(EPISODE_START, start)


def test_the_sparse_pce_fits_a_toy_dynamics_with_few_terms_per_output():
    # The candidates of the fixed-basis toy test in tests/test_pce.py (165 terms), 3,000 transitions.
    model = SparsePCEDynamics(TOY, action_dim=2, order=3, truncation="total_degree", max_interaction=None,
                              interactions="all", members=2)
    report = ClosedFormTrainer().fit(model, episodes(toy_transitions(3000, 0), 50), torch.Generator().manual_seed(0))
    # Stated accuracy: the held-out one-step prediction explains >= 95% of the state change's variance.
    assert one_step_r2(model, toy_transitions(1000, 1)) >= 0.95, report
    assert (report.validation_error < 0.03).all()
    # Each output keeps a handful of the candidates; what it does not keep is exactly zero.
    kept = (model.coefficients != 0).sum(1)  # [members, outputs]
    assert (kept >= 1).all() and kept.float().mean() < model.terms / 4
    assert report.extras["mean_terms"] == pytest.approx(float(kept.float().mean()))
    assert 0 < report.extras["loo_error"] < 0.05


def test_bootstrap_members_resample_whole_episodes_and_choose_their_own_terms_on_thin_data():
    model = SparsePCEDynamics(TOY, action_dim=2, order=4, q=0.75, members=4)
    data = episodes(toy_transitions(240, 2), 20)  # 12 episodes of 20 steps
    train = torch.arange(240)
    weights = model.episode_bootstrap(data, train, torch.Generator().manual_seed(0)).weights()
    assert (weights[0] == 1).all()
    per_episode = weights.reshape(4, 12, 20)
    assert (per_episode == per_episode[..., :1]).all()  # one draw per episode, shared by its steps
    assert not (weights[1:] == 1).all()
    ClosedFormTrainer().fit(model, data, torch.Generator().manual_seed(0))
    selected = model.coefficients != 0  # [members, terms, outputs]
    differ = [not torch.equal(selected[a], selected[b]) for a in range(4) for b in range(a + 1, 4)]
    assert all(differ)  # every pair of members keeps different terms
    # ... and predicts differently, where the data do not pin the dynamics down.
    probe = toy_transitions(500, 3)
    args = (probe["state"], probe["action"], probe["design"])
    first, second = (model.predict(*args, torch.full((500,), m), deterministic=True) for m in (0, 1))
    assert (first - second).abs().mean() > 1e-4


def test_the_sparse_pces_imagined_env_passes_torchrls_checks():
    data = real_transitions()
    model = SparsePCEDynamics(THESIS_FROM_FULL, 4, order=3, members=2, max_terms=20)
    ClosedFormTrainer().fit(model, data, torch.Generator().manual_seed(0))
    assert int(model.fitted_terms) >= 1
    reference = BatchedWalkerEnv(1, full_state=True)
    imagined = ImaginedEnv(make_world_model(model, RewardWeights()), reference,
                                 lambda n: data[torch.randint(data.batch_size[0], (n,))].select("state", "design"),
                                 batch_size=6)
    check_env_specs(imagined)
    assert imagined.rollout(5, make_actor(18, 4), break_when_any_done=False).shape == (6, 5)
    reference.close()


@pytest.mark.parametrize(
    ("settings", "match"),
    [
        ({"order": -1}, "order must be an integer >= 1 .*, got -1"),
        ({"q": 2.0}, "q must lie in .* got 2.0"),
        ({"max_terms": 0}, "max_terms must be a positive integer or None, got 0"),
        ({"patience": -3}, "patience must be a positive integer, got -3"),
        ({"tolerance": -1.0}, "tolerance must be a finite number >= 0, got -1.0"),
        ({"loo_samples": 1}, "loo_samples must be an integer >= 2, got 1"),
        ({"members": 0}, "members must be a positive integer, got 0"),
        ({"interactions": "some"}, "interactions must be one of .*'some'"),
    ],
)
def test_bad_sparse_pce_settings_are_refused_by_name(settings, match):
    with pytest.raises(ValueError, match=match):
        SparsePCEDynamics(TOY, action_dim=2, **settings)
