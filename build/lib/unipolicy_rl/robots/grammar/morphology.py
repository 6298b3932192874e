"""A morphology: the choices of one derivation, as a tree of body segments and limbs.

Each robot of the grammar has one leftmost derivation (:mod:`.derivation`), and that
derivation is fixed by a few choices: how many body segments, which carry a leg pair, the
joint between each pair of segments, and each leg pair's links (a joint type and a link
kind each). :class:`Morphology` holds those choices, so robots can be counted, enumerated
and drawn without walking the rewriting engine; :meth:`Morphology.derivation` spells out
the rule names the engine applies.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np

from unipolicy_rl.robots.grammar.rules import rules_for

BODY_JOINT_RULES = rules_for("body_joint")
LIMB_JOINT_RULES = rules_for("limb_joint")
LIMB_LINK_RULES = rules_for("limb_link")


@dataclass(frozen=True)
class LimbLink:
    """One link of a limb: the rule for the joint above it and the rule for its capsule."""

    joint: str
    link: str

    def __post_init__(self) -> None:
        if self.joint not in LIMB_JOINT_RULES:
            raise ValueError(f"unknown limb joint rule {self.joint!r}; rules are {list(LIMB_JOINT_RULES)}")
        if self.link not in LIMB_LINK_RULES:
            raise ValueError(f"unknown limb link rule {self.link!r}; rules are {list(LIMB_LINK_RULES)}")


@dataclass(frozen=True)
class Morphology:
    """Body segments from head to tail: ``limbs[i]`` is segment i's leg (its mirror image is the
    other leg of the pair), empty for a segment without legs; ``body_joints[i]`` joins segments
    i and i + 1."""

    limbs: tuple[tuple[LimbLink, ...], ...]
    body_joints: tuple[str, ...]

    def __post_init__(self) -> None:
        object.__setattr__(self, "limbs", tuple(tuple(limb) for limb in self.limbs))
        object.__setattr__(self, "body_joints", tuple(self.body_joints))
        if not self.limbs:
            raise ValueError("a morphology needs at least one body segment")
        for limb in self.limbs:
            for link in limb:
                if not isinstance(link, LimbLink):
                    raise ValueError(f"a leg is a tuple of LimbLink, got {link!r} in {limb!r}")
        if len(self.body_joints) != len(self.limbs) - 1:
            raise ValueError(f"{len(self.limbs)} body segments need {len(self.limbs) - 1} body joints, "
                             f"got {len(self.body_joints)}: {list(self.body_joints)}")
        for joint in self.body_joints:
            if joint not in BODY_JOINT_RULES:
                raise ValueError(f"unknown body joint rule {joint!r}; rules are {list(BODY_JOINT_RULES)}")

    @property
    def segments(self) -> int:
        return len(self.limbs)

    @property
    def leg_pairs(self) -> int:
        return sum(1 for limb in self.limbs if limb)

    @property
    def limb_links(self) -> tuple[int, ...]:
        """The number of links of each leg pair's legs (mount not counted), head to tail."""
        return tuple(len(limb) for limb in self.limbs if limb)

    @property
    def num_links(self) -> int:
        """Links of the robot it derives: the body segments, and per leg its mount and links."""
        return self.segments + 2 * sum(1 + len(limb) for limb in self.limbs if limb)

    def derivation(self) -> tuple[str, ...]:
        """The leftmost derivation: the structure head to tail (each segment, then its legs'
        links), then the joints in the same order."""
        structure = ["make_robot", "end_head"]
        joints: list[str] = []
        for index, limb in enumerate(self.limbs):
            structure.append("make_body_with_legs" if limb else "make_body_without_legs")
            for position, link in enumerate(limb):
                structure += [link.link] if position == 0 else ["append_limb_link", link.link]
                joints.append(link.joint)
            if limb:
                structure.append("end_limb")
            last = index == len(self.limbs) - 1
            structure.append("end_tail" if last else "append_body")
            if not last:
                joints.append(self.body_joints[index])
        return (*structure, *joints)


def _check_range(name: str, value, lowest: int) -> tuple[int, int]:
    if not (isinstance(value, (tuple, list)) and len(value) == 2 and all(isinstance(v, int) for v in value)
            and lowest <= value[0] <= value[1]):
        raise ValueError(f"{name} must be (min, max) integers with {lowest} <= min <= max, got {value!r}")
    return (int(value[0]), int(value[1]))


@dataclass(frozen=True)
class SizeLimits:
    """Bounds (inclusive) on a morphology's body segments, leg pairs and links per leg."""

    segments: tuple[int, int] = (2, 5)
    leg_pairs: tuple[int, int] = (1, 3)
    limb_links: tuple[int, int] = (1, 3)

    def __post_init__(self) -> None:
        object.__setattr__(self, "segments", _check_range("segments", self.segments, 1))
        object.__setattr__(self, "leg_pairs", _check_range("leg_pairs", self.leg_pairs, 0))
        object.__setattr__(self, "limb_links", _check_range("limb_links", self.limb_links, 1))
        if self.leg_pairs[0] > self.segments[1]:
            raise ValueError(f"leg_pairs {self.leg_pairs} needs more body segments than segments "
                             f"{self.segments} allows (one leg pair per segment)")

    @property
    def max_links(self) -> int:
        """The most links a robot within these limits has (:attr:`Morphology.num_links`): the
        most segments, as many of them as may carry legs, each leg as long as allowed."""
        pairs = min(self.leg_pairs[1], self.segments[1])
        return self.segments[1] + 2 * pairs * (1 + self.limb_links[1])

    def admits(self, morphology: Morphology) -> bool:
        return not self.violations(morphology)

    def violations(self, morphology: Morphology) -> list[str]:
        """What about ``morphology`` lies outside these limits (empty when nothing does)."""
        found = []
        if not self.segments[0] <= morphology.segments <= self.segments[1]:
            found.append(f"{morphology.segments} body segments, outside segments {self.segments}")
        if not self.leg_pairs[0] <= morphology.leg_pairs <= self.leg_pairs[1]:
            found.append(f"{morphology.leg_pairs} leg pairs, outside leg_pairs {self.leg_pairs}")
        for links in morphology.limb_links:
            if not self.limb_links[0] <= links <= self.limb_links[1]:
                found.append(f"a leg of {links} links, outside limb_links {self.limb_links}")
        return found

    def check(self, morphology: Morphology) -> None:
        found = self.violations(morphology)
        if found:
            raise ValueError(f"morphology out of range: {'; '.join(found)}")

    def pair_counts(self, segments: int) -> range:
        """The numbers of leg pairs a robot of ``segments`` body segments may have."""
        return range(self.leg_pairs[0], min(self.leg_pairs[1], segments) + 1)

    def segment_counts(self) -> range:
        """The numbers of body segments a robot may have (enough for the fewest leg pairs)."""
        return range(max(self.segments[0], self.leg_pairs[0]), self.segments[1] + 1)


def _limbs(limits: SizeLimits) -> Iterator[tuple[LimbLink, ...]]:
    choices = [LimbLink(joint, link) for joint in LIMB_JOINT_RULES for link in LIMB_LINK_RULES]
    for count in range(limits.limb_links[0], limits.limb_links[1] + 1):
        yield from itertools.product(choices, repeat=count)


def count_morphologies(limits: SizeLimits, segments: int | None = None, leg_pairs: int | None = None) -> int:
    """How many morphologies (= derivations) lie within ``limits``, optionally of one size only."""
    per_link = len(LIMB_JOINT_RULES) * len(LIMB_LINK_RULES)
    limbs = sum(per_link**count for count in range(limits.limb_links[0], limits.limb_links[1] + 1))
    total = 0
    for n in limits.segment_counts():
        for pairs in limits.pair_counts(n):
            if (segments is None or n == segments) and (leg_pairs is None or pairs == leg_pairs):
                total += math.comb(n, pairs) * limbs**pairs * len(BODY_JOINT_RULES) ** (n - 1)
    return total


def enumerate_morphologies(limits: SizeLimits) -> Iterator[Morphology]:
    """Every morphology within ``limits``, lazily, in a fixed order (fewer segments, then fewer
    leg pairs first). The count grows fast (:func:`count_morphologies`); take a slice."""
    limb_choices = list(_limbs(limits))
    for n in limits.segment_counts():
        for pairs in limits.pair_counts(n):
            for legged in itertools.combinations(range(n), pairs):
                for body_joints in itertools.product(BODY_JOINT_RULES, repeat=n - 1):
                    for limbs in itertools.product(limb_choices, repeat=pairs):
                        chosen = dict(zip(legged, limbs, strict=True))
                        yield Morphology(tuple(chosen.get(i, ()) for i in range(n)), body_joints)


def sample_morphology(rng: np.random.Generator, limits: SizeLimits) -> Morphology:
    """One morphology drawn level by level: the number of segments, then of leg pairs, uniformly
    among those the limits allow; which segments carry legs, the body joints, each leg's number
    of links and each link's joint and kind, uniformly. Small robots are thus as likely as
    large ones, though there are far fewer of them."""
    n = int(rng.choice(list(limits.segment_counts())))
    pairs = int(rng.choice(list(limits.pair_counts(n))))
    legged = set(rng.choice(n, size=pairs, replace=False).tolist())
    body_joints = tuple(BODY_JOINT_RULES[int(i)] for i in rng.integers(len(BODY_JOINT_RULES), size=n - 1))
    limbs = []
    for index in range(n):
        if index not in legged:
            limbs.append(())
            continue
        count = int(rng.integers(limits.limb_links[0], limits.limb_links[1] + 1))
        limbs.append(tuple(LimbLink(LIMB_JOINT_RULES[int(rng.integers(len(LIMB_JOINT_RULES)))],
                                    LIMB_LINK_RULES[int(rng.integers(len(LIMB_LINK_RULES)))])
                           for _ in range(count)))
    return Morphology(tuple(limbs), body_joints)


_THESIS_LEG = (LimbLink("make_axial_roll_limb_joint", "make_long_limb_link"),
               LimbLink("make_obtuse_lift_limb_joint", "make_long_limb_link"))
# The thesis robot (unipolicy_rl.robots.vertebrate): three segments joined by roll joints, a
# leg pair on the first and the last, each leg a hip (axial roll) and a knee bent down 60 degrees.
VERTEBRATE = Morphology((_THESIS_LEG, (), _THESIS_LEG), ("make_roll_body_joint", "make_roll_body_joint"))
