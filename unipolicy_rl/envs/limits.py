"""Where a state stops being physics: the blow-up limit and its check, without PyBullet.

The real walker and every world model's imagined env share the check, so a prediction the real
env would call a fault is one in imagination too; a world model of another env sets its own
limit (:func:`healthy_rows`' ``limit``).
"""

from __future__ import annotations

# Positions beyond this (m) or speeds beyond this (m/s) mean the solver has blown up.
EXPLOSION_LIMIT = 100.0


def healthy_rows(observations, limit: float = EXPLOSION_LIMIT):
    """True for each observation (last axis) that is finite and within ``limit``; a numpy array
    (the real env) or a torch tensor (a world model's prediction) of the same type."""
    # One comparison covers both: NaN and inf compare False.
    return (abs(observations) < limit).all(-1)
