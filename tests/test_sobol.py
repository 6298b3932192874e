"""Sobol' indices from a polynomial chaos expansion's coefficients, and those of the one-step PCE world models."""

import math

import pytest
import torch
from tensordict import TensorDict

from unipolicy_rl.polynomial_chaos import PolynomialChaos, legendre, multi_indices, sobol_indices, squared_norms
from unipolicy_rl.world_models import PCEDynamics, SparsePCEDynamics, StateLayout

# Ishigami (a = 7, b = 0.1) on U(-pi, pi)^3: closed-form variance shares (Sudret 2008, table 1).
A, B = 7.0, 0.1
V1 = 0.5 * (1 + B * math.pi**4 / 5) ** 2
V2 = A**2 / 8
V13 = B**2 * math.pi**8 * (1 / 18 - 1 / 50)
V = V1 + V2 + V13
ISHIGAMI_FIRST = torch.tensor([V1 / V, V2 / V, 0.0], dtype=torch.float64)
ISHIGAMI_TOTAL = torch.tensor([(V1 + V13) / V, V2 / V, V13 / V], dtype=torch.float64)


def ishigami(x: torch.Tensor) -> torch.Tensor:
    return torch.sin(x[..., 0]) + A * torch.sin(x[..., 1]) ** 2 + B * x[..., 2] ** 4 * torch.sin(x[..., 0])


def test_ishigami_indices_from_a_fitted_expansion_match_the_closed_form_to_0_01():
    g = torch.Generator().manual_seed(0)
    x = (torch.rand(4000, 3, generator=g, dtype=torch.float64) * 2 - 1) * math.pi
    pce = PolynomialChaos.fit(x, ishigami(x).unsqueeze(-1), [-math.pi] * 3, [math.pi] * 3, order=12)
    indices = pce.sobol_indices()
    assert indices.first.shape == (1, 3) and indices.total.shape == (1, 3)
    torch.testing.assert_close(indices.first[0], ISHIGAMI_FIRST, atol=0.01, rtol=0)
    torch.testing.assert_close(indices.total[0], ISHIGAMI_TOTAL, atol=0.01, rtol=0)
    torch.testing.assert_close(indices.variance[0], torch.tensor(V, dtype=torch.float64), atol=0, rtol=0.01)
    # The only interaction is x1 x3's.
    torch.testing.assert_close(indices.interaction[0], torch.tensor(V13 / V, dtype=torch.float64), atol=0.01, rtol=0)


def additive_plus_interaction(z: torch.Tensor, orthonormal: bool) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """``y = 3 psi_1(z1) + 2 psi_2(z2) + psi_1(z1) psi_1(z2)`` (z3 plays no part) in the orthonormal
    basis; its multi-indices and its coefficients in the basis asked for (plain Legendre
    polynomials are the orthonormal ones over ``sqrt(2n + 1)``), and its values at ``z``."""
    indices = multi_indices(3, 2)
    wanted = {(1, 0, 0): 3.0, (0, 2, 0): 2.0, (1, 1, 0): 1.0}
    coefficients = torch.zeros(indices.shape[0], 1, dtype=torch.float64)
    for term, row in enumerate(indices.tolist()):
        if tuple(row) in wanted:
            plain_to_orthonormal = math.prod(math.sqrt(2 * a + 1) for a in row)
            coefficients[term, 0] = wanted[tuple(row)] * (1.0 if orthonormal else plain_to_orthonormal)
    psi = legendre(z, 2, orthonormal=True)
    y = 3 * psi[:, 0, 1] + 2 * psi[:, 1, 2] + psi[:, 0, 1] * psi[:, 1, 1]
    return indices, coefficients, y


@pytest.mark.parametrize("orthonormal", [True, False])
def test_a_polynomial_with_closed_form_indices_gives_them_exactly_in_either_basis(orthonormal):
    indices, coefficients, _ = additive_plus_interaction(torch.zeros(1, 3), orthonormal)
    variance = 9.0 + 4.0 + 1.0
    result = sobol_indices(indices, coefficients, squared_norms(indices, orthonormal))
    expected_first = torch.tensor([[9.0, 4.0, 0.0]], dtype=torch.float64) / variance
    expected_total = torch.tensor([[10.0, 5.0, 0.0]], dtype=torch.float64) / variance
    torch.testing.assert_close(result.first, expected_first)
    torch.testing.assert_close(result.total, expected_total)
    torch.testing.assert_close(result.variance, torch.tensor([variance], dtype=torch.float64))
    if not orthonormal:  # leaving out the norms of a plain Legendre basis overweights every higher-degree term
        wrong = sobol_indices(indices, coefficients)
        assert not torch.allclose(wrong.first, expected_first, atol=0.05)


def test_a_noise_free_fit_of_that_polynomial_recovers_its_indices():
    g = torch.Generator().manual_seed(1)
    z = torch.rand(200, 3, generator=g, dtype=torch.float64) * 2 - 1
    _, _, y = additive_plus_interaction(z, True)
    for orthonormal in (True, False):
        pce = PolynomialChaos.fit(z, y.unsqueeze(-1), [-1] * 3, [1] * 3, order=3, orthonormal=orthonormal)
        indices = pce.sobol_indices()
        torch.testing.assert_close(indices.first[0], torch.tensor([9.0, 4.0, 0.0], dtype=torch.float64) / 14)
        torch.testing.assert_close(indices.total[0], torch.tensor([10.0, 5.0, 0.0], dtype=torch.float64) / 14)


def test_indices_lie_in_0_1_first_order_below_total_on_any_coefficients():
    indices = multi_indices(4, 3, "hyperbolic", 0.75, 2)
    coefficients = torch.randn(5, indices.shape[0], 3, generator=torch.Generator().manual_seed(2))
    coefficients[1, :, 2] = 0.0  # a constant output: nothing drives it
    result = sobol_indices(indices, coefficients)
    assert result.first.shape == result.total.shape == (5, 3, 4)
    assert (result.first >= 0).all() and (result.total <= 1 + 1e-12).all()
    assert (result.first <= result.total + 1e-12).all()
    assert (result.first.sum(-1) <= 1 + 1e-12).all()
    varying = result.variance > 0
    assert (result.total.sum(-1)[varying] >= 1 - 1e-12).all()
    assert not varying[1, 2] and (result.total[1, 2] == 0).all()


def test_mismatched_coefficients_or_bad_norms_are_refused_by_size():
    indices = multi_indices(2, 2)
    with pytest.raises(ValueError, match="coefficients have 5 terms, the multi-index set 6"):
        sobol_indices(indices, torch.zeros(5, 1))
    with pytest.raises(ValueError, match="norms must be 6 positive numbers"):
        sobol_indices(indices, torch.zeros(6, 1), torch.zeros(6))


# One body (position and velocity xyz), no joints: features z, vx, vy, vz, then 2 actions and (l, rho).
TOY = StateLayout(num_bodies=1, num_joint_values=0, state_columns=tuple(range(6)), observation_columns=tuple(range(6)))


def toy_transitions(n: int) -> TensorDict:
    """x moves by ``0.1 vx + 0.05 action0^2``, z by ``0.2 l vz`` (an interaction); nothing else moves."""
    g = torch.Generator().manual_seed(3)
    state = torch.rand(n, 6, generator=g) * 2 - 1
    action = torch.rand(n, 2, generator=g) * 2 - 1
    design = torch.stack([0.15 + 0.05 * torch.rand(n, generator=g), 0.4 + 0.2 * torch.rand(n, generator=g)], -1)
    change = torch.zeros(n, 6)
    change[:, 0] = 0.1 * state[:, 3] + 0.05 * action[:, 0] ** 2
    change[:, 2] = 0.2 * design[:, 0] * state[:, 5]
    return TensorDict({"state": state, "action": action, "design": design, "next_state": state + change}, [n])


@pytest.mark.parametrize("model_class", [PCEDynamics, SparsePCEDynamics])
def test_the_one_step_pce_world_models_name_the_inputs_that_drive_each_output(model_class):
    model = model_class(TOY, 2, order=2, truncation="total_degree", q=1.0, members=2)
    data = toy_transitions(2000)
    model.fit(data, torch.arange(1600), torch.arange(1600, 2000), oversampling=2.0,
              generator=torch.Generator().manual_seed(0))
    names = model.input_names()
    assert names == ["base.z", "base.vx", "base.vy", "base.vz", "action0", "action1", "l", "rho"]
    indices = model.sobol_indices(member=0)
    assert indices.first.shape == (6, len(names))
    x, z = TOY.state_names().index("base.x"), TOY.state_names().index("base.z")
    # x: vx (linear) and action0 (quadratic) only, no interaction between them.
    driving = indices.total[x] > 0.01
    assert driving.tolist() == [n in ("base.vx", "action0") for n in names]
    torch.testing.assert_close(indices.first[x].sum(), torch.tensor(1.0, dtype=torch.float64), atol=1e-3, rtol=0)
    # z: l and vz, through their product: vz alone carries most, and l's share is its interaction's.
    assert indices.total[z].argmax() == names.index("base.vz")
    assert indices.total[z, names.index("l")] > indices.first[z, names.index("l")] + 1e-3
    with pytest.raises(ValueError, match="member must be an integer in"):
        model.sobol_indices(member=2)
