"""Running mean and spread of observations, merged one epoch at a time.

The policy normalises its input with TorchRL's ``ObservationNorm``, whose ``loc`` and
``scale`` stay fixed for a whole epoch and are refreshed from these statistics between
epochs, as OpenAI baselines' TRPO did. A fixed normaliser keeps the behaviour policy one
function per epoch (what the importance ratios and the trust region assume), lets it run
inside the collector's worker processes with the policy weights, and costs a subtraction and
a division per step instead of a statistics update in every env step.
"""

from __future__ import annotations

import torch
from torchrl.envs.transforms import ObservationNorm

# A coordinate that has not varied yet (or never does) is divided by this, not by ~0.
MIN_SCALE = 1e-3


class ObservationStatistics:
    """Count, mean and sum of squared deviations of every observation seen so far.

    Batches merge exactly (Chan et al.'s parallel update, in float64), so the result does
    not depend on how the observations were split into epochs.
    """

    def __init__(self, size: int) -> None:
        if not (isinstance(size, int) and size >= 1):
            raise ValueError(f"size must be a positive integer, got {size!r}")
        self.size = size
        self.count = 0
        self.mean = torch.zeros(size, dtype=torch.float64)
        self.squared_deviations = torch.zeros(size, dtype=torch.float64)

    def update(self, observations: torch.Tensor) -> None:
        """Merges a batch shaped ``[..., size]``."""
        if observations.shape[-1:] != (self.size,):
            raise ValueError(f"observations must end in size {self.size}, got shape {tuple(observations.shape)}")
        rows = observations.reshape(-1, self.size).to(torch.float64)
        if not torch.isfinite(rows).all():
            raise ValueError("observations must be finite")
        n = rows.shape[0]
        if n == 0:
            return
        batch_mean = rows.mean(0)
        batch_deviations = ((rows - batch_mean) ** 2).sum(0)
        total = self.count + n
        delta = batch_mean - self.mean
        self.mean = self.mean + delta * (n / total)
        self.squared_deviations = self.squared_deviations + batch_deviations + delta**2 * (self.count * n / total)
        self.count = total

    @property
    def loc(self) -> torch.Tensor:
        return self.mean.to(torch.float32)

    @property
    def scale(self) -> torch.Tensor:
        """Standard deviation (population), floored at :data:`MIN_SCALE`; ones before any data."""
        if self.count == 0:
            return torch.ones(self.size)
        return (self.squared_deviations / self.count).sqrt().clamp_min(MIN_SCALE).to(torch.float32)

    def copy_to(self, normalizer: ObservationNorm) -> None:
        """Writes ``loc`` and ``scale`` into ``normalizer`` in place (so shared copies see them)."""
        normalizer.loc.copy_(self.loc)
        normalizer.scale.copy_(self.scale)

    def state_dict(self) -> dict:
        return {"count": self.count, "mean": self.mean.clone(), "squared_deviations": self.squared_deviations.clone()}

    def load_state_dict(self, state: dict) -> None:
        if state["mean"].shape != (self.size,):
            raise ValueError(f"statistics are for size {tuple(state['mean'].shape)}, expected ({self.size},)")
        self.count = int(state["count"])
        self.mean = state["mean"].to(torch.float64).clone()
        self.squared_deviations = state["squared_deviations"].to(torch.float64).clone()
