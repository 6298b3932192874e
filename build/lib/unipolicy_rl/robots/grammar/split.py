"""A fixed, seeded split of the grammar's standing robots into training and held-out morphologies.

Zero-shot transfer is measured on two kinds of held-out robots: unseen morphologies of the
training sizes, and robots larger than any training robot (more body segments or more leg
pairs), the harder test. The same seed and settings always give the same split.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from unipolicy_rl.robots.grammar.build import describe
from unipolicy_rl.robots.grammar.derivation import derive
from unipolicy_rl.robots.grammar.morphology import Morphology, SizeLimits, sample_morphology
from unipolicy_rl.robots.grammar.standing import stands

TRAIN_LIMITS = SizeLimits(segments=(2, 4), leg_pairs=(1, 2), limb_links=(1, 3))
HELD_OUT_LIMITS = SizeLimits(segments=(2, 5), leg_pairs=(1, 3), limb_links=(1, 3))


def stands_at(morphology: Morphology, lengths: Sequence[float]) -> bool:
    """Whether the robot stands at every design length in ``lengths`` (density does not matter:
    it scales every link's mass alike)."""
    graph = derive(morphology.derivation())
    return all(stands(describe(graph, length=length)) for length in lengths)


@dataclass(frozen=True)
class MorphologySplit:
    """Training and held-out morphologies, as :func:`split_morphologies` drew them from ``seed``."""

    seed: int
    train: tuple[Morphology, ...]
    held_out: tuple[Morphology, ...]

    def is_larger(self, morphology: Morphology) -> bool:
        """More body segments or more leg pairs than any training robot."""
        return (morphology.segments > max(m.segments for m in self.train)
                or morphology.leg_pairs > max(m.leg_pairs for m in self.train))

    @property
    def larger_held_out(self) -> tuple[Morphology, ...]:
        return tuple(m for m in self.held_out if self.is_larger(m))


def _draw(rng: np.random.Generator, limits: SizeLimits, count: int, accept: Callable[[Morphology], bool],
          lengths: Sequence[float], taken: set[Morphology], max_draws: int, what: str) -> list[Morphology]:
    found: list[Morphology] = []
    for _ in range(max_draws):
        if len(found) == count:
            return found
        candidate = sample_morphology(rng, limits)
        if candidate in taken or not accept(candidate) or not stands_at(candidate, lengths):
            continue
        taken.add(candidate)
        found.append(candidate)
    if len(found) == count:
        return found
    raise ValueError(f"found only {len(found)} of {count} standing {what} robots in {max_draws} draws; "
                     f"widen the limits or raise max_draws")


def split_morphologies(
    seed: int,
    lengths: Sequence[float],
    train_size: int = 32,
    held_out_size: int = 16,
    larger_share: float = 0.5,
    train_limits: SizeLimits = TRAIN_LIMITS,
    held_out_limits: SizeLimits = HELD_OUT_LIMITS,
    max_draws: int = 20_000,
) -> MorphologySplit:
    """``train_size`` standing robots drawn within ``train_limits`` and ``held_out_size`` others:
    ``larger_share`` of them (at least one) within ``held_out_limits`` but larger than the
    training limits allow, the rest unseen robots within ``train_limits``.

    Every robot must stand at each length of ``lengths`` (pass the ends of the design range).
    """
    if train_size < 1 or held_out_size < 1:
        raise ValueError(f"a split needs robots on both sides, got train_size={train_size!r}, "
                         f"held_out_size={held_out_size!r}")
    if not 0.0 <= larger_share <= 1.0:
        raise ValueError(f"larger_share must lie in [0, 1], got {larger_share!r}")
    if not lengths or any(not (math.isfinite(length) and length > 0) for length in lengths):
        raise ValueError(f"lengths must be positive design lengths, got {lengths!r}")
    if (held_out_limits.segments[1] <= train_limits.segments[1]
            and held_out_limits.leg_pairs[1] <= train_limits.leg_pairs[1]):
        raise ValueError(f"held_out_limits {held_out_limits} allow no robot larger than train_limits "
                         f"{train_limits}: raise its segments or leg_pairs maximum")

    def larger(morphology: Morphology) -> bool:
        return (morphology.segments > train_limits.segments[1] or morphology.leg_pairs > train_limits.leg_pairs[1])

    rng = np.random.default_rng(seed)
    taken: set[Morphology] = set()
    train = _draw(rng, train_limits, train_size, lambda m: True, lengths, taken, max_draws, "training")
    larger_count = max(1, round(larger_share * held_out_size))
    held_out = _draw(rng, held_out_limits, larger_count, larger, lengths, taken, max_draws, "larger held-out")
    held_out += _draw(rng, train_limits, held_out_size - larger_count, lambda m: True, lengths, taken, max_draws,
                      "held-out")
    return MorphologySplit(seed, tuple(train), tuple(held_out))
