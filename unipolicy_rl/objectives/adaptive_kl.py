"""The imagined updates' trust region, shrunk as the world model's error on fresh states rises
(``imagination.adaptive_kl``).

TRPO's bound ``algo.max_kl`` says how far one update may move the policy on data it can trust.
Imagined data are only as good as the model on the states the policy now reaches, and that is
measured every epoch, before the fit, on the epoch's new real transitions:
``model/fresh_error`` (:mod:`unipolicy_rl.world_models.fresh_error`, the share of the real one-step
change the model left unexplained). The rule scales the bound by how much worse than a reference
that error is, trusting the imagined data in proportion to the model's accuracy where it matters::

    bound = max(floor, max_kl * min(1, reference / fresh_error))

so an epoch whose model is at least as good as ``reference`` keeps ``max_kl``, and one twice as
bad takes half of it, never less than ``floor``. The first epoch has no fresh error (no model
before it) and keeps ``max_kl``; a non-finite error (a model that predicts NaN) takes ``floor``.
The real updates (``imagination.train_on_real``) keep ``max_kl``: their data are the robot's.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass

from unipolicy_rl.metric_columns import IMAGINED_MAX_KL


def _positive(name: str, value) -> None:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not (math.isfinite(value) and value > 0):
        raise ValueError(f"adaptive_kl.{name} must be a positive number, got {value!r}")


@dataclass(frozen=True)
class AdaptiveKL:
    """``bound = max(floor, max_kl * min(1, reference / fresh_error))`` for the imagined updates.

    Args:
        reference: the fresh error (``model/fresh_error``) at and below which the bound is
            ``max_kl``; None: the rule is off (every update takes ``max_kl``).
        floor: the smallest bound, > 0 (needed when ``reference`` is set).
    """

    reference: float | None = None
    floor: float | None = None

    def __post_init__(self) -> None:
        if self.reference is None:
            if self.floor is not None:
                raise ValueError(f"adaptive_kl.floor={self.floor!r} without adaptive_kl.reference: set both, "
                                 "or neither (off)")
            return
        _positive("reference", self.reference)
        if self.floor is None:
            raise ValueError("adaptive_kl.reference is set: adaptive_kl.floor must be a positive number too "
                             "(the smallest bound)")
        _positive("floor", self.floor)

    @property
    def on(self) -> bool:
        return self.reference is not None

    def bound(self, max_kl: float, fresh_error: float | None) -> float:
        """The imagined updates' KL bound, given ``max_kl`` and the epoch's fresh error (None: not measured)."""
        if not self.on or fresh_error is None:
            return max_kl
        if not math.isfinite(fresh_error):
            return self.floor
        scale = 1.0 if fresh_error <= self.reference else self.reference / fresh_error
        return max(self.floor, max_kl * scale)


@contextmanager
def imagined_trust_region(rule: AdaptiveKL, learner, fresh_error: float | None) -> Iterator[dict[str, float]]:
    """Within the block, ``learner``'s TRPO steps (``learner.updater.trust_region``) take the rule's
    bound; yields the metrics to log (the bound), empty with the rule off, which touches nothing."""
    if not rule.on:
        yield {}
        return
    updater = learner.updater
    configured = updater.trust_region
    bound = rule.bound(configured.max_kl, fresh_error)
    updater.trust_region = dataclasses.replace(configured, max_kl=bound)
    try:
        yield {IMAGINED_MAX_KL: bound}
    finally:
        updater.trust_region = configured
