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


def epoch_seed(seed: int, epoch: int, phase: int | None = None) -> int:
    """The seed a run restarts its randomness from at ``epoch`` (real collection), or at a
    later ``phase`` of that epoch (a model-based run's model fit and imagination)."""
    entropy = [seed, epoch] if phase is None else [seed, epoch, phase]
    return int(np.random.SeedSequence(entropy).generate_state(1)[0])


def reseed(seed: int, epoch: int, phase: int) -> torch.Generator:
    """Restarts torch's global randomness for ``phase`` of ``epoch`` and returns a generator
    seeded the same, for the phase's own draws."""
    value = epoch_seed(seed, epoch, phase)
    torch.manual_seed(value)
    return torch.Generator().manual_seed(value)
