"""Where a run restarts its randomness: every real epoch, and every later phase of an epoch.

Each phase draws from its own seed, a function of the run's seed, the epoch and the phase, so a
phase's randomness does not depend on how much the phases before it drew, and a run resumed
from a checkpoint continues exactly as the uninterrupted run would.
"""

from __future__ import annotations

import numpy as np
import torch

# Phases of an epoch after its real collection, each reseeded.
MODEL_FIT, IMAGINATION = 1, 2


def epoch_seed(seed: int, epoch: int, phase: int | None = None, part: int | None = None) -> int:
    """The seed a run restarts its randomness from at ``epoch`` (real collection), or at a
    later ``phase`` of that epoch (a model-based run's model fit and imagination), or at its
    ``part``-th repeat within the epoch (``imagination.refit_every``: the refits while the epoch
    is collected, each with its own seed; the one after the epoch has none)."""
    entropy = [seed, epoch] if phase is None else [seed, epoch, phase]
    if part is not None:
        if phase is None:
            raise ValueError(f"part={part} numbers the repeats of a phase: give the phase")
        entropy.append(part)
    return int(np.random.SeedSequence(entropy).generate_state(1)[0])


def reseed(seed: int, epoch: int, phase: int, part: int | None = None) -> torch.Generator:
    """Restarts torch's global randomness for ``phase`` of ``epoch`` (its ``part``-th repeat
    within the epoch, where it has several) and returns a generator seeded the same, for the
    phase's own draws."""
    value = epoch_seed(seed, epoch, phase, part)
    torch.manual_seed(value)
    return torch.Generator().manual_seed(value)
