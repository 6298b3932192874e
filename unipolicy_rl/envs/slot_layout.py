"""Which token slot each link of a grammar robot takes: packed in link order, or at a place its
role in the body fixes.

A padded MLP ties its weights to slots. Packed, the description's link order (body segments head
to tail, then each leg pair's legs, each from its mount out) starts a robot's first leg at slot 3
when it has three body segments and at slot 4 when it has four, and shifts every later leg by the
length of the legs before it: the same weights read a hip on one robot and a knee on the next,
and a robot the policy never saw fills its slots with links none of the training robots had
there. The structural layout fixes each link's slot by what it is: body segment ``i`` at slot
``i``; then a block of ``leg_slots`` per leg, leg pair ``k``'s left leg first and its right leg
next, each leg's mount at the block's start and its ``j``-th link ``j`` slots on. Every robot
puts its first pair's hips where every other robot puts theirs; a segment or leg link it lacks
leaves a gap of padding.

The reward reads the root's token at slot 0 in both layouts (the head segment, ``body_0``). A
transformer over the tokens sees the layout only through its optional slot vectors and reads the
body graph from ``token_parent``, which follows the links wherever they sit.
"""

from __future__ import annotations

import re
from collections.abc import Iterable, Sequence
from dataclasses import dataclass

import numpy as np

TOKEN_LAYOUTS = ("packed", "structural")

# The link names :func:`unipolicy_rl.robots.grammar.describe` gives (its docstring is the contract).
_BODY = re.compile(r"body_(\d+)")
_LEG = re.compile(r"leg_(\d+)_(left|right)_(?:mount|link_(\d+))")
_SIDES = {"left": 0, "right": 1}


@dataclass(frozen=True)
class StructuralLayout:
    """Slots by role: ``body_slots`` for body segments (head first), then ``leg_slots`` per leg
    (its mount and up to ``leg_slots - 1`` links), pair by pair, left leg before right."""

    body_slots: int
    leg_slots: int

    def __post_init__(self) -> None:
        for name in ("body_slots", "leg_slots"):
            value = getattr(self, name)
            if not (isinstance(value, (int, np.integer)) and not isinstance(value, bool) and value >= 1):
                raise ValueError(f"{name} must be a positive integer, got {value!r}")

    @classmethod
    def covering(cls, limits: Iterable) -> StructuralLayout:
        """The layout every robot within any of ``limits`` (:class:`~unipolicy_rl.robots.grammar.SizeLimits`)
        fits: as many body slots as the most segments, a leg block for a mount and the longest leg."""
        limits = list(limits)
        if not limits:
            raise ValueError("a structural layout needs at least one SizeLimits to cover")
        return cls(max(limit.segments[1] for limit in limits), 1 + max(limit.limb_links[1] for limit in limits))

    def slots_needed(self, leg_pairs: int) -> int:
        """Token slots a robot of up to ``leg_pairs`` leg pairs may need."""
        return self.body_slots + 2 * leg_pairs * self.leg_slots

    def slots(self, link_names: Sequence[str]) -> np.ndarray:
        """``[n]`` int64: the slot of each link, in the description's link order."""
        slots = np.empty(len(link_names), dtype=np.int64)
        for index, name in enumerate(link_names):
            if body := _BODY.fullmatch(name):
                segment = int(body.group(1))
                if segment >= self.body_slots:
                    raise ValueError(f"link {name!r} is body segment {segment + 1}; the layout has "
                                     f"body_slots={self.body_slots}")
                slots[index] = segment
            elif leg := _LEG.fullmatch(name):
                pair, side, depth = int(leg.group(1)), _SIDES[leg.group(2)], int(leg.group(3) or 0)
                if depth >= self.leg_slots:
                    raise ValueError(f"link {name!r} is link {depth} of its leg; the layout has "
                                     f"leg_slots={self.leg_slots} (a mount and {self.leg_slots - 1} links)")
                slots[index] = self.body_slots + (2 * pair + side) * self.leg_slots + depth
            else:
                raise ValueError(f"link {name!r} is neither a body segment (body_<i>) nor a leg link "
                                 "(leg_<k>_<left|right>_mount, leg_<k>_<left|right>_link_<j>)")
        if len(set(slots.tolist())) != len(slots):
            raise ValueError(f"links {list(link_names)} share slots {slots.tolist()}")
        return slots


def packed_slots(num_links: int) -> np.ndarray:
    """``[n]`` int64: link ``i`` at slot ``i``."""
    return np.arange(num_links, dtype=np.int64)
