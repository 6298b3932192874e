"""Recorded numbers that survive a change of CPU: a few sums of a computation's tensors, compared
within a tolerance, where a hash of their bits would not.

CPUs with other vector units (AVX2, AVX-512) order float sums otherwise, so the bits of the same
TRPO step differ between machines (``ATEN_CPU_CAPABILITY=avx2`` against ``avx512`` moves these
default learner's recorded figures by up to 6e-6 relative); a change to the arithmetic itself moves
them by more than :data:`RELATIVE_TOLERANCE` (a 1% change of ``max_kl`` does). Record what a step
changes beside them (its KL, its step size): they are what a change of the step moves most.
"""

from __future__ import annotations

import torch

RELATIVE_TOLERANCE = 1e-4


def fingerprint(values: list[torch.Tensor]) -> list[float]:
    """The sum of magnitudes and the sum of squares of every number in ``values``: sums without
    cancellation, so float reordering moves them by about its own relative error (a signed sum
    or a random projection cancels to a small number and amplifies it)."""
    flat = torch.cat([value.detach().double().reshape(-1) for value in values])
    return [float(flat.abs().sum()), float(flat.square().sum())]
