"""How close a surrogate's trajectories are to the real ones, time step by time step (thesis §5.1-5.2).

Every measure compares ground truth ``[episodes, steps, features]`` with the surrogate's
trajectories of the same starts, designs and actions: ``[episodes, steps, features]``, or
``[episodes, samples, steps, features]`` when a stochastic surrogate (a drawn member, sampled
noise) is rolled out several times per episode. Each returns one figure per time step and
feature, ``[steps, features]``, so a caller reads off any horizon and any coordinate:

* :func:`jensen_shannon`: the Jensen-Shannon divergence, in bits, between the distribution of
  a coordinate over the real episodes and over the surrogate's trajectories (a distribution
  measure: it asks whether the surrogate spreads as the real robots do, not whether each
  trajectory is right);
* :func:`relative_error`: |s - s_hat| / max(|s|, floor) averaged over episodes (and samples),
  the thesis' eq. 5.2 with its floors (1 cm for positions, 1 cm/s for velocities), so a state
  that passes near zero does not blow the ratio up;
* :func:`normalised_mean_difference`: |mean(s_hat) - mean(s)| / |mean(s)|, the thesis' eq. 5.3;
* :func:`band`: the mean and the central band (95%: the 2.5 and 97.5 percentiles) per step,
  and :func:`plot_bands` to draw real against surrogate.

Non-finite values: ground truth must be finite (drop episodes with a physics fault first), so
a non-finite truth value is a ValueError. A non-finite surrogate value is a model failure to
report, not a reason to lose every figure: it is left out of the figures of its (step,
feature) and counted in a :class:`NonFiniteSurrogateWarning` (:func:`nonfinite_count` gives
the counts). Where no finite surrogate value is left at a (step, feature), the figure there
is NaN, and the warning says how many such cells there are.
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import NamedTuple

import torch

# Thesis eq. 5.2's floor on |s|: 1 cm for positions and 1 cm/s for velocities, the same number in SI units.
THESIS_FLOOR = 0.01
DEFAULT_BINS = 10
STATISTICS = ("mean", "median")
QUANTILE_LIMIT = 2**24  # torch.quantile's largest input


class NonFiniteSurrogateWarning(RuntimeWarning):
    """Some surrogate values were NaN or infinite and were left out of the figures."""


class Band(NamedTuple):
    """Per-step mean and central band of a coordinate, each ``[steps, features]``."""

    mean: torch.Tensor
    low: torch.Tensor
    high: torch.Tensor


# -- checks ---------------------------------------------------------------------------------

def _tensor(values, name: str) -> torch.Tensor:
    values = torch.as_tensor(values)
    if not (values.is_floating_point() or values.dtype in (torch.int32, torch.int64)):
        raise ValueError(f"{name} must hold real numbers, got dtype {values.dtype}")
    return values.to(torch.float64)


def _check_nonempty(values: torch.Tensor, name: str, dims: tuple[int, ...], layout: str) -> None:
    if values.dim() not in dims:
        raise ValueError(f"{name} must be shaped {layout}, got shape {tuple(values.shape)}")
    if values.numel() == 0:
        raise ValueError(f"{name} is empty: shape {tuple(values.shape)}")


def _samples(values, name: str) -> torch.Tensor:
    """``values`` as ``[episodes, samples, steps, features]`` (one sample when 3-D)."""
    values = _tensor(values, name)
    _check_nonempty(values, name, (3, 4), "[episodes, steps, features] or [episodes, samples, steps, features]")
    return values.unsqueeze(1) if values.dim() == 3 else values


def check_trajectories(truth, surrogate) -> tuple[torch.Tensor, torch.Tensor]:
    """Validated ``(truth [E, T, F], surrogate [E, S, T, F])`` in float64.

    Raises a ValueError naming the bad value for: a shape other than the documented ones, an
    empty tensor, a surrogate whose episodes, steps or features differ from the truth's, and a
    non-finite truth value (ground truth has no excuse; a surrogate's are counted instead).
    """
    truth = _tensor(truth, "truth")
    _check_nonempty(truth, "truth", (3,), "[episodes, steps, features]")
    surrogate = _samples(surrogate, "surrogate")
    expected = (truth.shape[0], *truth.shape[1:])
    got = (surrogate.shape[0], *surrogate.shape[2:])
    if got != expected:
        raise ValueError(f"surrogate's (episodes, steps, features) {got} differ from truth's {expected} "
                         f"(surrogate shape {tuple(surrogate.shape)}, truth shape {tuple(truth.shape)})")
    bad = ~torch.isfinite(truth)
    if bad.any():
        episode, step, feature = (int(i) for i in bad.nonzero()[0])
        first = float(truth[episode, step, feature])
        raise ValueError(f"truth has {int(bad.sum())} non-finite values, the first {first} at (episode, step, "
                         f"feature) = ({episode}, {step}, {feature}): drop faulted episodes first")
    return truth, surrogate


def _check_floor(floor, features: int) -> torch.Tensor:
    """The floor as a float64 tensor broadcastable to ``[..., features]``; every entry finite and > 0."""
    floor = torch.as_tensor(floor, dtype=torch.float64)
    if floor.dim() > 1 or (floor.dim() == 1 and floor.numel() != features):
        raise ValueError(f"floor must be a number or one per feature ({features}), got shape {tuple(floor.shape)}")
    bad = ~(torch.isfinite(floor) & (floor > 0))
    if bad.any():
        raise ValueError(f"floor must be finite and > 0, got {floor.flatten()[bad.flatten()][0].item()!r}")
    return floor


def _finite(surrogate: torch.Tensor) -> torch.Tensor:
    """The finite mask of ``surrogate``; warns with the count of values left out."""
    finite = torch.isfinite(surrogate)
    if not finite.all():
        empty = int((~finite.flatten(0, 1).any(0)).sum())
        warnings.warn(f"{int((~finite).sum())} of {surrogate.numel()} surrogate values are not finite and are left "
                      f"out; {empty} (step, feature) cells have no finite value left (their figures are NaN)",
                      NonFiniteSurrogateWarning, stacklevel=3)
    return finite


def nonfinite_count(surrogate) -> torch.Tensor:
    """``[steps, features]``: how many surrogate values (over episodes and samples) are NaN or infinite."""
    surrogate = _samples(surrogate, "surrogate")
    return (~torch.isfinite(surrogate)).flatten(0, 1).sum(0)


# -- Jensen-Shannon divergence ---------------------------------------------------------------

def jensen_shannon(truth, surrogate, bins: int = DEFAULT_BINS) -> torch.Tensor:
    """``[steps, features]``: the Jensen-Shannon divergence in bits (so in [0, 1]) between the
    real episodes' distribution of each coordinate and the surrogate's, per time step.

    Both samples are histogrammed on one shared binning per (step, feature): ``bins`` bins of
    equal mass under the mixture M = (P + Q) / 2 of the two empirical distributions (the real
    episodes weighted 1 / (2 episodes), the surrogate's values 1 / (2 values)), edges halfway
    between neighbouring values. Why these bins:

    * shared: JSD compares two distributions on one partition; separate binnings would not;
    * equal mass under M rather than equal width: one diverged surrogate sample far away
      would stretch equal-width bins until all real data fell in one bin and the divergence
      read near 0; here an outlier only moves the last edge. Every bin also holds about
      1/``bins`` of M, so the estimate's noise is spread evenly;
    * M rather than the pooled values: with many more surrogate samples than episodes, pooled
      quantiles would be the surrogate's own and the real sample would fall in few bins.

    Any binning can only lose information, so the figure is a lower bound of the divergence
    between the underlying distributions, apart from the plug-in estimate's positive bias at
    small samples: about (bins - 1) (1/n + 1/m) / (8 ln 2) bits for two samples of sizes n and m
    from one distribution (0.018 bits at 10 bins, 100 episodes, 1,000 surrogate values).
    Identical samples give 0; samples that do not overlap give 1 with an even ``bins`` (the
    median of M is an edge); with an odd ``bins`` the middle bin may hold both.
    """
    truth, surrogate = check_trajectories(truth, surrogate)
    if isinstance(bins, bool) or not isinstance(bins, int) or bins < 2:
        raise ValueError(f"bins must be an integer >= 2, got {bins!r}")
    finite = _finite(surrogate)
    steps, features = truth.shape[1:]
    real = truth.permute(1, 2, 0).reshape(steps * features, -1)  # [cells, episodes]
    model = surrogate.flatten(0, 1).permute(1, 2, 0).reshape(steps * features, -1)  # [cells, values]
    kept = finite.flatten(0, 1).permute(1, 2, 0).reshape(steps * features, -1)
    model = torch.where(kept, model, math.inf)  # left out: sorted last, weight 0
    p, q = _histograms(real, model, kept, bins)
    divergence = 0.5 * _kl_bits(p, 0.5 * (p + q)) + 0.5 * _kl_bits(q, 0.5 * (p + q))
    divergence = divergence.clamp(0.0, 1.0)  # rounding only
    divergence[kept.sum(-1) == 0] = math.nan
    return divergence.reshape(steps, features)


def _histograms(real: torch.Tensor, model: torch.Tensor, kept: torch.Tensor,
                bins: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Probabilities ``[cells, bins]`` of both samples on bins of equal mass under their mixture."""
    n = real.shape[-1]
    m = kept.sum(-1, keepdim=True)  # finite surrogate values per cell
    # Integer weights (m per real value, n per surrogate value) so the mixture's cumulative
    # mass is exact and an edge that should fall between two samples does not drift by rounding.
    weights = torch.cat([m.expand(-1, n), kept.long() * n], -1)
    values, order = torch.cat([real, model], -1).sort(-1)
    mass = weights.gather(-1, order).cumsum(-1) * bins
    targets = torch.arange(1, bins, dtype=torch.long) * (2 * n * m)  # j / bins of the total 2 n m
    below = torch.searchsorted(mass, targets)  # first index reaching each quantile
    upper = (below + 1).clamp_max(values.shape[-1] - 1)
    edges = 0.5 * (values.gather(-1, below) + values.gather(-1, upper))  # +inf past the last finite value
    p = _counts(real, torch.ones_like(real), edges) / n
    q = _counts(model, kept.to(real.dtype), edges) / m.clamp_min(1)
    return p, q


def _counts(values: torch.Tensor, weights: torch.Tensor, edges: torch.Tensor) -> torch.Tensor:
    """Weighted counts ``[cells, bins]``; a value equal to an edge goes to the bin below it."""
    index = torch.searchsorted(edges.contiguous(), values.contiguous())
    return torch.zeros(values.shape[0], edges.shape[-1] + 1, dtype=values.dtype).scatter_add_(-1, index, weights)


def _kl_bits(p: torch.Tensor, mixture: torch.Tensor) -> torch.Tensor:
    """KL(p || mixture) in bits, with 0 log 0 = 0 (where p > 0, mixture >= p / 2 > 0)."""
    ratio = p / torch.where(p > 0, mixture, 1.0)
    return torch.where(p > 0, p * torch.log2(torch.where(p > 0, ratio, 1.0)), 0.0).sum(-1)


# -- errors against the real trajectory -------------------------------------------------------

def relative_error(truth, surrogate, floor=THESIS_FLOOR, statistic: str = "mean") -> torch.Tensor:
    """``[steps, features]``: |s - s_hat| / max(|s|, floor) over episodes and samples (thesis eq. 5.2).

    ``floor`` is one number or one per feature (the thesis: 1 cm for positions, 1 cm/s for
    velocities, :data:`THESIS_FLOOR` in SI units): below it the true value is treated as that
    small, so a coordinate crossing zero does not turn a millimetre into an infinite error.
    ``statistic`` is ``mean`` (eq. 5.2) or ``median`` (less swayed by the few steps where the
    truth sits near the floor). Each surrogate sample is compared with its episode's truth, so
    with samples this is the error of one imagined trajectory, as training meets it.
    """
    truth, surrogate = check_trajectories(truth, surrogate)
    if statistic not in STATISTICS:
        raise ValueError(f"statistic must be one of {STATISTICS}, got {statistic!r}")
    floor = _check_floor(floor, truth.shape[-1])
    finite = _finite(surrogate)
    ratio = (surrogate - truth.unsqueeze(1)).abs() / truth.abs().clamp_min(floor).unsqueeze(1)
    ratio = torch.where(finite, ratio, math.nan).flatten(0, 1)
    return ratio.nanmean(0) if statistic == "mean" else _nanquantile(ratio, torch.tensor([0.5]))[0]


def normalised_mean_difference(truth, surrogate) -> torch.Tensor:
    """``[steps, features]``: |mean of the surrogate - mean of the truth| / |mean of the truth|
    over episodes (and samples), the thesis' eq. 5.3.

    As in the thesis there is no floor: a coordinate whose real mean is near zero gets a large
    figure (infinite at exactly zero), which is why a summary over coordinates should use the median.
    """
    truth, surrogate = check_trajectories(truth, surrogate)
    finite = _finite(surrogate)
    predicted = torch.where(finite, surrogate, math.nan).flatten(0, 1).nanmean(0)
    real = truth.mean(0)
    return (predicted - real).abs() / real.abs()


# -- bands and their plot -----------------------------------------------------------------------

def band(values, level: float = 0.95) -> Band:
    """Mean and central ``level`` band (95%: the 2.5 and 97.5 percentiles) per step and feature,
    over episodes (and samples); non-finite values are left out with a warning."""
    values = _samples(values, "values")
    if not 0 < level < 1:
        raise ValueError(f"level must lie in (0, 1), got {level!r}")
    finite = _finite(values)
    kept = torch.where(finite, values, math.nan).flatten(0, 1)
    low, high = _nanquantile(kept, torch.tensor([(1 - level) / 2, (1 + level) / 2]))
    return Band(kept.nanmean(0), low, high)


def _nanquantile(values: torch.Tensor, q: torch.Tensor) -> torch.Tensor:
    """``[len(q), steps, features]`` quantiles over the first dimension of ``[N, steps, features]``,
    NaN left out. torch refuses quantiles of inputs over 2**24 values, so the cells go in chunks."""
    flat = values.flatten(1)
    chunk = max(1, QUANTILE_LIMIT // flat.shape[0])
    parts = [part.nanquantile(q.to(values.dtype), dim=0) for part in flat.split(chunk, dim=1)]
    return torch.cat(parts, -1).unflatten(-1, values.shape[1:])


def plot_bands(truth, surrogates: Mapping[str, torch.Tensor], columns: Mapping[int, str], out_path: str | Path,
               seconds_per_step: float | None = None, marks: Sequence[int] = (), title: str = "") -> Path:
    """Real against surrogate mean and 95% band over time: one row per coordinate in ``columns``
    (feature index -> axis label), one column of panels per surrogate; returns the PNG's path.

    Each panel's y range is the real band's, widened by half its span on each side, so a
    surrogate that drifts off shows as leaving the panel instead of flattening the real data
    into a line. ``marks`` are steps drawn as dotted lines (a training horizon, say). Drawn
    with matplotlib's object API (Agg), as :mod:`unipolicy_rl.evaluation.plots` is, so the
    caller's backend is never switched.
    """
    # Imported here: training imports this package and should not pay for matplotlib.
    from matplotlib.figure import Figure

    if not surrogates:
        raise ValueError("surrogates is empty: nothing to plot")
    if not columns:
        raise ValueError("columns is empty: name at least one feature to plot")
    real = band(check_trajectories(truth, next(iter(surrogates.values())))[0])
    fitted = {name: band(check_trajectories(truth, values)[1]) for name, values in surrogates.items()}
    steps, features = real.mean.shape
    for column in columns:
        if not 0 <= column < features:
            raise ValueError(f"column {column!r} is not a feature index in [0, {features})")
    seconds = (torch.arange(steps, dtype=torch.float64) * (seconds_per_step or 1.0)).numpy()
    figure = Figure(figsize=(4 * len(fitted), 2.7 * len(columns)))
    axes = figure.subplots(len(columns), len(fitted), sharex=True, squeeze=False)
    for column_index, (name, modelled) in enumerate(fitted.items()):
        for row, (feature, label) in enumerate(columns.items()):
            axis = axes[row, column_index]
            _draw_band(axis, seconds, real, feature, "0.4", "real")
            _draw_band(axis, seconds, modelled, feature, f"C{column_index}", name)
            low, high = float(real.low[:, feature].min()), float(real.high[:, feature].max())
            span = max(high - low, 1e-9)
            axis.set_ylim(low - 0.5 * span, high + 0.5 * span)
            for step in marks:
                axis.axvline(float(seconds[step]), color="k", linestyle=":", linewidth=1)
            axis.set_ylabel(label if column_index == 0 else "")
            axis.grid(alpha=0.3)
            if row == 0:
                axis.set_title(name)
                axis.legend(loc="upper left", fontsize=7)
        axes[-1, column_index].set_xlabel("time from the start (s)" if seconds_per_step else "step")
    if title:
        figure.suptitle(title, fontsize=10)
    figure.tight_layout()
    out_path = Path(out_path)
    out_path.parent.mkdir(parents=True, exist_ok=True)
    figure.savefig(out_path, dpi=120)
    return out_path


def _draw_band(axis, seconds, values: Band, feature: int, colour: str, label: str) -> None:
    axis.fill_between(seconds, values.low[:, feature].numpy(), values.high[:, feature].numpy(), color=colour,
                      alpha=0.25, linewidth=0)
    axis.plot(seconds, values.mean[:, feature].numpy(), color=colour, label=f"{label}: mean, 95% band")
