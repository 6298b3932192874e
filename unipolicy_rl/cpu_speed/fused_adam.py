"""Adam with torch's fused kernel wherever the parameters' device has one.

The fused kernel updates each parameter in one pass where the default CPU path runs about ten
element-wise operations per tensor; the optimisers here step small networks thousands of times
per epoch, so that share is large: a whole fit step of the default ensemble takes 0.91x the time
(``benchmarks/fit_precision.py``, ``fit_fused_adam_ratio``). The update is
Adam's own; only the order of its floating-point operations differs. The world model's fits and
TRPO's critic fit use it; the off-policy learners keep torch's default kernel, since their steps
gained nothing from it (SAC 67-69 gradient steps/s either way, ``benchmarks/learner_speed.py``).
"""

from __future__ import annotations

from collections.abc import Iterable

import torch

# Devices with a fused Adam kernel in torch; others (torch lists more in a private table) take the
# default kernel.
FUSED_DEVICES = ("cpu", "cuda")


def adam(params: Iterable[torch.Tensor], **settings) -> torch.optim.Adam:
    """``torch.optim.Adam(params, **settings)`` on the fused kernel where every parameter is a real
    floating-point tensor on a device of :data:`FUSED_DEVICES`, on torch's default kernel otherwise
    (torch would raise at the first step, not at construction)."""
    params = list(params)
    fused = all(p.device.type in FUSED_DEVICES and p.is_floating_point() for p in params)
    return torch.optim.Adam(params, fused=fused or None, **settings)
