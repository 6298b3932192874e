"""Robot designs (link length and density) and the distributions episodes draw them from."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

# The thesis' uncertain design: l ~ U(0.15, 0.20) m and rho ~ U(0.4, 0.6) kg/m. SE trains on
# it and the evaluation grid covers it. conf/config.yaml's ``design_space`` holds the same
# numbers for Hydra runs (tests/test_train.py checks they agree).
SE_LENGTH_RANGE = (0.15, 0.20)
SE_DENSITY_RANGE = (0.4, 0.6)


def _check_positive(name: str, value: float) -> None:
    if not (isinstance(value, (int, float)) and math.isfinite(value) and value > 0):
        raise ValueError(f"{name} must be a positive finite number, got {value!r}")


@dataclass(frozen=True)
class Design:
    """One robot build: every link has this ``length`` (m) and ``density`` (kg per m of link)."""

    length: float
    density: float

    def __post_init__(self) -> None:
        _check_positive("design length", self.length)
        _check_positive("design density", self.density)


@dataclass(frozen=True)
class DesignDistribution:
    """Independent uniform length and density; a zero-width range is a deterministic design.

    DE is ``DesignDistribution.fixed(0.175, 0.5)``; SE is the default, the thesis ranges
    :data:`SE_LENGTH_RANGE` and :data:`SE_DENSITY_RANGE`.
    """

    length_range: tuple[float, float] = SE_LENGTH_RANGE
    density_range: tuple[float, float] = SE_DENSITY_RANGE

    def __post_init__(self) -> None:
        for name, (low, high) in (("length", self.length_range), ("density", self.density_range)):
            _check_positive(f"{name} range lower bound", low)
            _check_positive(f"{name} range upper bound", high)
            if low > high:
                raise ValueError(f"{name} range is empty: lower bound {low!r} > upper bound {high!r}")
        object.__setattr__(self, "length_range", tuple(float(v) for v in self.length_range))
        object.__setattr__(self, "density_range", tuple(float(v) for v in self.density_range))

    @classmethod
    def fixed(cls, length: float, density: float) -> DesignDistribution:
        return cls((length, length), (density, density))

    @property
    def is_deterministic(self) -> bool:
        return self.length_range[0] == self.length_range[1] and self.density_range[0] == self.density_range[1]

    @property
    def mean(self) -> Design:
        return Design(sum(self.length_range) / 2, sum(self.density_range) / 2)

    def sample(self, rng: np.random.Generator) -> Design:
        # Always draw both numbers so DE and SE consume the generator alike.
        length = rng.uniform(*self.length_range)
        density = rng.uniform(*self.density_range)
        return Design(float(length), float(density))

    def grid(self, points_per_axis: int) -> list[Design]:
        """Evenly spaced designs over both ranges, length-major, for evaluation."""
        if points_per_axis < 1:
            raise ValueError(f"points_per_axis must be >= 1, got {points_per_axis!r}")
        lengths = np.linspace(*self.length_range, points_per_axis)
        densities = np.linspace(*self.density_range, points_per_axis)
        return [Design(float(length), float(density)) for length in lengths for density in densities]
