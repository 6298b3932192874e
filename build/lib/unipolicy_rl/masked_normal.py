"""A factorised Gaussian over padded action slots, of which only the masked-in ones exist.

A robot of any morphology is driven through an action ``[*, L]`` padded to the largest robot,
with ``ACTION_MASK`` saying which slots are real joints (:mod:`unipolicy_rl.envs.tokens`). The
env ignores the other slots, so a learner must too: their log-probability, entropy and KL must
count for nothing, or a robot padded with more empty slots would get another importance ratio,
another entropy and another trust region than the same robot padded with fewer.

The mask is a parameter of the distribution, as in TorchRL's ``MaskedCategorical`` (its actor
reads ``in_keys={"logits": ..., "mask": "action_mask"}``): everything built on the distribution
(the log-probability the actor stores at collection, :class:`~unipolicy_rl.objectives.TRPOLoss`'s
ratio, entropy and KL, the natural-gradient step's Fisher product and line search, the KL a
normaliser refresh logs) then counts real joints only, with no special case in any of them.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch.distributions.kl import kl_divergence, register_kl
from torchrl.modules import IndependentNormal

__all__ = ["MaskedIndependentNormal"]


class MaskedIndependentNormal(IndependentNormal):
    """``IndependentNormal(loc, scale)`` over the last dimension, restricted to ``mask``'s slots.

    Args:
        loc, scale: ``[*, L]`` per-slot mean and standard deviation (any finite values on
            masked-out slots: they are never used).
        mask: ``[*, L]`` bool, True for a real slot.

    Per sample, ``log_prob``, ``entropy`` and the KL to another such distribution sum over the
    real slots only; what is stored in a masked-out slot of the value (an action the env never
    applied) changes nothing. Samples, the mean and the mode are 0 on masked-out slots, so the
    padding of collected actions is deterministic.
    """

    def __init__(self, loc: torch.Tensor, scale: torch.Tensor, mask: torch.Tensor | None = None, **kwargs) -> None:
        if mask is None:
            raise ValueError("MaskedIndependentNormal needs the action mask (the batch has no 'action_mask' entry?)")
        if mask.dtype != torch.bool or mask.shape != loc.shape:
            raise ValueError(f"the action mask must be bool shaped like loc {tuple(loc.shape)}, got "
                             f"{mask.dtype} {tuple(mask.shape)}")
        self.mask = mask
        super().__init__(loc, scale, **kwargs)

    def _real(self, per_slot: torch.Tensor) -> torch.Tensor:
        """Zero on masked-out slots (``where``, not a product: a NaN there must not leak)."""
        return torch.where(self.mask, per_slot, torch.zeros((), dtype=per_slot.dtype, device=per_slot.device))

    def log_prob(self, value: torch.Tensor) -> torch.Tensor:
        # Masked-out slots are replaced by 0 before the density, so a non-finite value stored
        # there cannot turn the (discarded) term or its gradient into NaN.
        per_slot = self.base_dist.log_prob(self._real(value))
        return self._real(per_slot).sum(-1)

    def entropy(self) -> torch.Tensor:
        return self._real(self.base_dist.entropy()).sum(-1)

    def sample(self, sample_shape: Sequence[int] = ()) -> torch.Tensor:
        return self._real(super().sample(torch.Size(sample_shape)))

    def rsample(self, sample_shape: Sequence[int] = ()) -> torch.Tensor:
        return self._real(super().rsample(torch.Size(sample_shape)))

    @property
    def mean(self) -> torch.Tensor:
        return self._real(self.base_dist.mean)

    @property
    def mode(self) -> torch.Tensor:
        return self.mean

    @property
    def deterministic_sample(self) -> torch.Tensor:
        return self.mean


@register_kl(MaskedIndependentNormal, MaskedIndependentNormal)
def _kl_masked_normal(p: MaskedIndependentNormal, q: MaskedIndependentNormal) -> torch.Tensor:
    """Per sample ``KL(p || q)`` summed over the real slots; both must mask the same slots (the
    same robots), else the KL between them is not defined."""
    if not torch.equal(p.mask, q.mask):
        raise ValueError("KL between masked normals with different action masks: they describe different robots")
    return p._real(kl_divergence(p.base_dist, q.base_dist)).sum(-1)
