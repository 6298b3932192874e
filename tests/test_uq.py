"""A policy's episode over the uncertain design as a PCE in (l, rho): the fit, its moments, the CLI."""

from __future__ import annotations

import math
import sys
import types

import pytest
import torch
from test_evaluation import ENV_KWARGS, EPISODE_LENGTH, constant_policy
from test_pce import imported_by

from unipolicy_rl.polynomial_chaos import DesignResponse, gauss_legendre_designs, uniform_designs

LENGTHS, DENSITIES = (0.15, 0.20), (0.4, 0.6)


def polynomial_episodes(designs: torch.Tensor, steps: int = 7) -> torch.Tensor:
    """``[n, steps, 2]``: coordinates of degree <= 3 in (l, rho) that change with the step."""
    length, density = designs[:, :1], designs[:, 1:]
    t = torch.arange(1, steps + 1, dtype=torch.float64)
    x = t * (20 * length - 2 * density) + (t / steps) * (40 * length) ** 3
    v = torch.sin(t) * density**2 + 10 * length * density
    return torch.stack([x, v], -1)


def test_the_design_response_recovers_a_polynomial_episode_and_its_moments():
    nodes = gauss_legendre_designs(5, LENGTHS, DENSITIES)
    assert nodes.shape == (25, 2)
    assert ((nodes[:, 0] > 0.15) & (nodes[:, 0] < 0.20) & (nodes[:, 1] > 0.4) & (nodes[:, 1] < 0.6)).all()
    response = DesignResponse.fit(nodes, polynomial_episodes(nodes), LENGTHS, DENSITIES, order=4)
    held_out = uniform_designs(200, LENGTHS, DENSITIES, torch.Generator().manual_seed(1))
    torch.testing.assert_close(response(held_out), polynomial_episodes(held_out), atol=1e-9, rtol=1e-9)
    # Moments from the coefficients against Monte Carlo of the true function.
    monte_carlo = polynomial_episodes(uniform_designs(400_000, LENGTHS, DENSITIES, torch.Generator().manual_seed(2)))
    torch.testing.assert_close(response.mean(), monte_carlo.mean(0), atol=5e-3, rtol=2e-3)
    torch.testing.assert_close(response.variance(), monte_carlo.var(0), atol=5e-4, rtol=1e-2)
    # Its distribution costs no physics: samples of the expansion have the same moments.
    sampled = response.sample(200_000, torch.Generator().manual_seed(3))
    torch.testing.assert_close(sampled.mean(0), response.mean(), atol=5e-3, rtol=2e-3)


def test_bad_design_response_input_is_named():
    nodes = gauss_legendre_designs(3, LENGTHS, DENSITIES)
    episodes = polynomial_episodes(nodes)
    with pytest.raises(ValueError, match=r"trajectories must be shaped \[9, steps, features\]"):
        DesignResponse.fit(nodes, episodes[:5], LENGTHS, DENSITIES)
    with pytest.raises(ValueError, match=r"underdetermined fit: 15 terms but only 9 samples"):
        DesignResponse.fit(nodes, episodes, LENGTHS, DENSITIES, order=4)
    outside = nodes.clone()
    outside[0, 0] = 0.3
    with pytest.raises(ValueError, match="0.3"):
        DesignResponse.fit(outside, episodes, LENGTHS, DENSITIES, order=2)
    with pytest.raises(ValueError, match="points must be a positive integer"):
        gauss_legendre_designs(0, LENGTHS, DENSITIES)


def test_uq_builds_on_the_library_and_evaluation_not_on_world_models():
    assert imported_by("unipolicy_rl.uq", ("unipolicy_rl.world_models", "unipolicy_rl.collectors",
                                           "unipolicy_rl.objectives")) == []


@pytest.fixture
def fake_checkpoint(tmp_path, monkeypatch):
    """A checkpoint file plus a stand-in ``unipolicy_rl.checkpoint`` that loads a constant policy."""
    path = tmp_path / "run" / "checkpoint.pt"
    path.parent.mkdir()
    path.write_bytes(b"not read by the stand-in loader")
    loaded = types.SimpleNamespace(policy=constant_policy(), env_kwargs=dict(ENV_KWARGS), config={}, epoch=0)
    module = types.ModuleType("unipolicy_rl.checkpoint")
    module.load_policy = lambda checkpoint, device="cpu": loaded
    monkeypatch.setitem(sys.modules, "unipolicy_rl.checkpoint", module)
    return path


def test_the_uq_cli_fits_real_episodes_and_checks_them_against_monte_carlo(fake_checkpoint, capsys):
    from unipolicy_rl.uq import main

    # The base's height: under a constant action it settles with the legs' length, smoothly.
    result = main([str(fake_checkpoint), "--order", "2", "--nodes", "3", "--check", "8", "--coordinates", "2", "0"])
    out_dir = fake_checkpoint.parent / "uq"
    assert result["plot"] == out_dir / "uq_bands.png" and result["plot"].stat().st_size > 0
    moments = torch.load(out_dir / "design_response.pt")
    assert moments["mean"].shape == moments["variance"].shape and moments["mean"].shape[0] == EPISODE_LENGTH
    figures = result["figures"][10]["base z (m)"]
    assert figures["mc_std"] > 1e-3  # the design matters ...
    assert figures["relative_error"] < 0.01  # ... and the expansion follows it
    assert math.isclose(figures["pce_mean"], figures["mc_mean"], abs_tol=4 * figures["mc_mean_se"])
    assert "| 10 | base z (m) |" in capsys.readouterr().out


def test_the_uq_cli_names_bad_arguments(tmp_path, fake_checkpoint):
    from unipolicy_rl.uq import main

    with pytest.raises(FileNotFoundError, match="nowhere"):
        main([str(tmp_path / "nowhere" / "checkpoint.pt")])
    with pytest.raises(ValueError, match="--nodes 2 gives 4 episodes, fewer than the 10 terms of order 3"):
        main([str(fake_checkpoint), "--order", "3", "--nodes", "2"])
    with pytest.raises(ValueError, match="--check must be >= 2"):
        main([str(fake_checkpoint), "--check", "1"])
    with pytest.raises(ValueError, match="the policy's observation has 18 columns"):
        main([str(fake_checkpoint), "--coordinates", "18"])
