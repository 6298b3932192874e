"""Accuracy measures of surrogate trajectories: JSD per step, relative error with floors, NMD, bands."""

import math
import warnings

import pytest
import torch

from unipolicy_rl.evaluation.accuracy import (
    NonFiniteSurrogateWarning,
    band,
    jensen_shannon,
    nonfinite_count,
    normalised_mean_difference,
    plot_bands,
    relative_error,
)


def normal(*shape: int, seed: int = 0) -> torch.Tensor:
    return torch.randn(*shape, generator=torch.Generator().manual_seed(seed), dtype=torch.float64)


# -- Jensen-Shannon divergence -----------------------------------------------------------------

def test_identical_samples_have_zero_divergence_also_when_each_episode_is_sampled_several_times():
    truth = normal(50, 8, 3)
    assert jensen_shannon(truth, truth).abs().max() < 1e-12
    repeated = truth.unsqueeze(1).expand(-1, 4, -1, -1)  # [episodes, samples, steps, features]
    assert jensen_shannon(truth, repeated).abs().max() < 1e-12


@pytest.mark.parametrize("samples", [1, 7])
def test_samples_that_do_not_overlap_are_one_bit_apart_even_with_a_narrow_gap(samples):
    truth = torch.rand(40, 5, 2, generator=torch.Generator().manual_seed(1), dtype=torch.float64)  # in [0, 1)
    surrogate = 1.001 + torch.rand(40, samples, 5, 2, generator=torch.Generator().manual_seed(2),
                                   dtype=torch.float64)
    torch.testing.assert_close(jensen_shannon(truth, surrogate), torch.ones(5, 2, dtype=torch.float64))
    # A surrogate far below gives the same bit: only the ordering matters, not the side or distance.
    torch.testing.assert_close(jensen_shannon(truth, -1e6 - surrogate), torch.ones(5, 2, dtype=torch.float64))


@pytest.mark.parametrize("bins", [10, 7])
def test_the_divergence_is_symmetric(bins):
    first, second = normal(60, 6, 2, seed=3), 0.7 * normal(60, 6, 2, seed=4) + 0.5
    torch.testing.assert_close(jensen_shannon(first, second, bins), jensen_shannon(second, first, bins),
                               rtol=0, atol=1e-12)


def test_half_overlapping_uniforms_are_half_a_bit_apart_in_bits_not_nats():
    # P = U(0, 2), Q = U(1, 3): JSD = 0.5 bit exactly (0.35 if it were nats). Binning can only
    # lose divergence and 20,000 samples leave a small plug-in bias: 0.05 covers both.
    g = torch.Generator().manual_seed(5)
    p = 2 * torch.rand(20000, 1, 1, generator=g, dtype=torch.float64)
    q = 1 + 2 * torch.rand(20000, 1, 1, generator=g, dtype=torch.float64)
    assert abs(float(jensen_shannon(p, q, bins=20)) - 0.5) < 0.05


def test_one_diverged_surrogate_sample_does_not_hide_the_rest():
    # Equal-width bins over the pooled range would put all of both samples into one bin next to
    # a value at 1e6 and read near 0 for any surrogate; bins of equal mass keep the comparison.
    truth = normal(200, 1, 1, seed=6)
    shifted = normal(200, 1, 1, seed=7) + 2.0  # N(2, 1) against N(0, 1): about 0.45 bit
    clean = float(jensen_shannon(truth, shifted))
    shifted[0] = 1e6
    assert clean > 0.3 and abs(float(jensen_shannon(truth, shifted)) - clean) < 0.03
    same = normal(200, 1, 1, seed=8)
    same[0] = 1e6
    assert float(jensen_shannon(truth, same)) < 0.1


# -- relative error and normalised mean difference ----------------------------------------------

def test_relative_error_matches_a_hand_computed_case_with_the_floor():
    truth = torch.tensor([[[0.005], [-2.0]], [[0.02], [1.0]]])  # [2 episodes, 2 steps, 1 feature]
    surrogate = torch.tensor([[[0.007], [-1.0]], [[0.01], [1.5]]])
    # Step 0: |0.005 - 0.007| / max(0.005, 0.01) = 0.2 (the floor acts), |0.02 - 0.01| / 0.02 = 0.5.
    # Step 1: 1 / 2 = 0.5 and 0.5 / 1 = 0.5.
    expected = torch.tensor([[0.35], [0.5]], dtype=torch.float64)
    torch.testing.assert_close(relative_error(truth, surrogate, floor=0.01), expected)
    # Without the floor's effect (a smaller floor) the first ratio is 0.4.
    torch.testing.assert_close(relative_error(truth, surrogate, floor=1e-3)[0, 0],
                               torch.tensor(0.45, dtype=torch.float64))


def test_relative_error_takes_one_floor_per_feature_and_compares_each_sample_with_its_episode():
    truth = torch.tensor([[[0.0, 0.0]]])  # one episode, one step, two features at zero
    surrogate = torch.tensor([[[[0.01, 0.01]], [[0.03, 0.03]]]])  # two samples
    # Per feature floor 0.01 and 0.1: feature 0 -> mean(1, 3) = 2; feature 1 -> mean(0.1, 0.3) = 0.2.
    torch.testing.assert_close(relative_error(truth, surrogate, floor=torch.tensor([0.01, 0.1])),
                               torch.tensor([[2.0, 0.2]], dtype=torch.float64))


def test_the_median_statistic_is_not_swayed_by_one_large_ratio():
    truth = torch.ones(5, 1, 1)
    surrogate = torch.tensor([1.1, 1.2, 0.9, 1.0, 100.0]).reshape(5, 1, 1)
    torch.testing.assert_close(relative_error(truth, surrogate, statistic="median"),
                               torch.tensor([[0.1]], dtype=torch.float64))
    assert float(relative_error(truth, surrogate)) > 19


def test_normalised_mean_difference_matches_a_hand_computed_case():
    truth = torch.tensor([[[2.0, -1.0]], [[4.0, -3.0]]])  # means 3 and -2
    surrogate = torch.tensor([[[3.0, -1.0]], [[4.5, -2.0]]])  # means 3.75 and -1.5
    torch.testing.assert_close(normalised_mean_difference(truth, surrogate),
                               torch.tensor([[0.25, 0.25]], dtype=torch.float64))


# -- bands ----------------------------------------------------------------------------------------

def test_the_band_of_ten_thousand_normal_samples_has_the_normal_percentiles():
    # Standard errors at n = 10,000: 0.010 for the mean, 0.027 for the 2.5/97.5 percentiles;
    # the tolerances are about 4 of them.
    values = normal(10000, 1, 1, seed=9) * 2.0 + 1.0  # N(1, 2^2)
    result = band(values)
    assert abs(float(result.mean) - 1.0) < 0.04
    assert abs(float(result.low) - (1.0 - 2.0 * 1.959964)) < 0.11
    assert abs(float(result.high) - (1.0 + 2.0 * 1.959964)) < 0.11
    half = band(values, level=0.5)  # quartiles: +-0.6745 sigma, standard error about 0.025
    assert abs(float(half.high - half.low) - 2 * 2.0 * 0.674490) < 0.1


def test_plot_bands_writes_a_figure(tmp_path):
    truth = normal(30, 12, 4)
    path = plot_bands(truth, {"model": truth.unsqueeze(1) + 0.1 * normal(30, 3, 12, 4, seed=1)},
                      {0: "x (m)", 3: "vx (m/s)"}, tmp_path / "bands.png", seconds_per_step=0.0667, marks=[6])
    assert path.exists() and path.stat().st_size > 10_000
    with pytest.raises(ValueError, match="column 4"):
        plot_bands(truth, {"model": truth}, {4: "no such feature"}, tmp_path / "bad.png")


# -- non-finite surrogate values --------------------------------------------------------------------

def test_a_non_finite_surrogate_value_is_counted_warned_about_and_left_out():
    truth = normal(20, 3, 2)
    surrogate = truth.unsqueeze(1) + normal(20, 2, 3, 2, seed=1)
    broken = surrogate.clone()
    broken[4, 1, 2, 0] = math.nan
    broken[:, :, 1, 1] = math.inf  # a whole cell diverged
    counts = nonfinite_count(broken)
    assert counts[2, 0] == 1 and counts[1, 1] == 40 and counts.sum() == 41
    with pytest.warns(NonFiniteSurrogateWarning, match=r"41 of 240 .* 1 \(step, feature\) cells"):
        error = relative_error(truth, broken)
    keep = torch.ones(20, 2, dtype=torch.bool)
    keep[4, 1] = False
    expected = ((surrogate[:, :, 2, 0] - truth[:, None, 2, 0]).abs() / truth[:, None, 2, 0].abs().clamp_min(0.01))
    torch.testing.assert_close(error[2, 0], expected[keep].mean())
    assert math.isnan(float(error[1, 1]))
    with pytest.warns(NonFiniteSurrogateWarning):
        divergence = jensen_shannon(truth, broken)
    assert math.isnan(float(divergence[1, 1])) and torch.isfinite(divergence[2, 0])
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # finite input: no warning
        jensen_shannon(truth, surrogate)


# -- bad input -------------------------------------------------------------------------------------

@pytest.mark.parametrize(
    ("call", "message"),
    [
        (lambda t: relative_error(t, t[:, :3]), r"\(4, 3, 2\) differ from truth's \(4, 5, 2\)"),
        (lambda t: jensen_shannon(t, t[:3]), r"\(3, 5, 2\) differ from truth's \(4, 5, 2\)"),
        (lambda t: relative_error(t[0], t[0]), r"truth must be shaped .* got shape \(5, 2\)"),
        (lambda t: relative_error(t[:0], t[:0]), r"truth is empty: shape \(0, 5, 2\)"),
        (lambda t: relative_error(t, t, floor=0.0), "floor must be finite and > 0, got 0.0"),
        (lambda t: relative_error(t, t, floor=torch.tensor([0.01, -1.0])), "got -1.0"),
        (lambda t: relative_error(t, t, floor=[0.01, 0.01, 0.01]), r"one per feature \(2\)"),
        (lambda t: relative_error(t, t, statistic="mode"), "'mode'"),
        (lambda t: jensen_shannon(t, t, bins=1), "bins must be an integer >= 2, got 1"),
        (lambda t: jensen_shannon(t, t, bins=2.5), "got 2.5"),
        (lambda t: band(t, level=1.0), r"level must lie in \(0, 1\), got 1.0"),
        (lambda t: band(t[None, None]), r"values must be shaped .* got shape \(1, 1, 4, 5, 2\)"),
    ],
)
def test_bad_input_raises_naming_the_value(call, message):
    with pytest.raises(ValueError, match=message):
        call(normal(4, 5, 2))


def test_a_non_finite_truth_value_is_an_error_with_its_place():
    truth = normal(4, 5, 2)
    truth[2, 3, 1] = math.nan
    with pytest.raises(ValueError, match=r"1 non-finite values, the first nan at \(episode, step, feature\) = "
                                         r"\(2, 3, 1\)"):
        normalised_mean_difference(truth, normal(4, 5, 2))
