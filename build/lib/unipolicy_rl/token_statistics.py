"""Observation statistics and normaliser for padded link tokens: per token feature, real tokens only.

The token counterpart of :mod:`unipolicy_rl.observation_statistics`, and the same protocol: the
statistics merge one epoch at a time, the normaliser stays fixed within an epoch, and
:func:`~unipolicy_rl.observation_statistics.refresh_normalizer` moves it between epochs (with
``preserve``, re-expressing the token networks' input layers so the policy does not change).
Two differences, both for the padding: a padding row is no observation of any feature, so it
enters neither mean nor spread (a robot padded with more empty tokens gets the same
statistics); and padding leaves the normaliser as zeros, whatever ``loc`` is, so the networks
always see the same padding.
"""

from __future__ import annotations

import torch
from tensordict import TensorDictBase
from tensordict.utils import NestedKey
from torchrl.envs.transforms import ObservationNorm

from unipolicy_rl.envs.tokens import TOKEN_MASK, TOKENS
from unipolicy_rl.observation_statistics import ObservationStatistics

__all__ = ["TokenNorm", "TokenObservationStatistics"]


class TokenObservationStatistics(ObservationStatistics):
    """Count, mean and spread of every token feature over the real tokens seen so far.

    ``size`` is the number of features per token ``F``; each real token is one observation.
    """

    def update(self, tokens: torch.Tensor, token_mask: torch.Tensor) -> None:  # type: ignore[override]
        """Merges the real rows of ``tokens`` ``[*, L, F]`` (``token_mask`` ``[*, L]``)."""
        if token_mask.dtype != torch.bool or token_mask.shape != tokens.shape[:-1]:
            raise ValueError(f"token_mask must be bool shaped {tuple(tokens.shape[:-1])} (the tokens' "
                             f"{tuple(tokens.shape)} without features), got {token_mask.dtype} "
                             f"{tuple(token_mask.shape)}")
        super().update(tokens[token_mask])


class TokenNorm(ObservationNorm):
    """TorchRL's ``ObservationNorm`` over the feature dimension of the tokens, padding set to zero.

    ``(tokens - loc) / scale`` with ``loc``/``scale`` ``[F]`` broadcast over the tokens, then
    ``torch.where(token_mask, ., 0)`` (not a product, so a non-finite padding row cannot leak).
    """

    def __init__(self, loc: torch.Tensor, scale: torch.Tensor, *, out_key: NestedKey,
                 tokens_key: NestedKey = TOKENS, mask_key: NestedKey = TOKEN_MASK) -> None:
        super().__init__(loc=loc, scale=scale, standard_normal=True, in_keys=[tokens_key], out_keys=[out_key])
        self.mask_key = mask_key

    def _zero_padding(self, tensordict: TensorDictBase) -> TensorDictBase:
        mask = tensordict.get(self.mask_key, None)
        if mask is None:
            raise KeyError(f"TokenNorm needs the token mask {self.mask_key!r} beside the tokens")
        for out_key in self.out_keys:
            normalized = tensordict.get(out_key)
            zero = torch.zeros((), dtype=normalized.dtype, device=normalized.device)
            tensordict.set(out_key, torch.where(mask.unsqueeze(-1), normalized, zero))
        return tensordict

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        return self._zero_padding(super().forward(tensordict))

    def _call(self, next_tensordict: TensorDictBase) -> TensorDictBase:
        return self._zero_padding(super()._call(next_tensordict))
