"""Which robots stand: no self-collision at rest, and the centre of mass over the support polygon.

A robot is judged in its rest pose (every joint at zero) lowered until its lowest point
touches the ground, as RoboGrammar places a robot before simulating it. The support polygon
is the convex hull of the capsule ends that touch the ground; a robot stands when its centre
of mass lies inside it, at least a margin from its edge. A robot that rests on a line (a
straight body with its legs stretched out level) has no support area and does not stand.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from unipolicy_rl.robots.description import RobotDescription
from unipolicy_rl.robots.kinematics import rest_segments

# Ends this close to the lowest point (m) count as touching the ground.
CONTACT_TOLERANCE = 1e-3
# How far inside the support polygon the centre of mass must lie (m).
SUPPORT_MARGIN = 0.01


def segment_distances(p0: np.ndarray, p1: np.ndarray, q0: np.ndarray, q1: np.ndarray) -> np.ndarray:
    """Shortest distances between segments ``p0[k]-p1[k]`` and ``q0[k]-q1[k]`` (arrays (m, 3)).

    The closest points' parameters on each segment, clamped to the segment (Ericson,
    Real-Time Collision Detection, 5.1.9), for all pairs at once.
    """
    d1, d2, r = p1 - p0, q1 - q0, p0 - q0
    a, e = np.einsum("ij,ij->i", d1, d1), np.einsum("ij,ij->i", d2, d2)
    b, c, f = np.einsum("ij,ij->i", d1, d2), np.einsum("ij,ij->i", d1, r), np.einsum("ij,ij->i", d2, r)
    denominator = a * e - b * b
    parallel = denominator <= 1e-12 * a * e
    s = np.where(parallel, 0.0, np.clip((b * f - c * e) / np.where(parallel, 1.0, denominator), 0.0, 1.0))
    t = (b * s + f) / e
    s = np.where(t < 0.0, np.clip(-c / a, 0.0, 1.0), np.where(t > 1.0, np.clip((b - c) / a, 0.0, 1.0), s))
    t = np.clip(t, 0.0, 1.0)
    return np.linalg.norm(p0 + d1 * s[:, None] - q0 - d2 * t[:, None], axis=1)


def self_collisions(description: RobotDescription) -> tuple[tuple[str, str], ...]:
    """Pairs of links whose capsules overlap at rest.

    A link overlaps its parent at their joint by construction, and links joined to one parent
    at one point (a leg pair's mounts) overlap there; neither counts.
    """
    starts, ends = rest_segments(description)
    names = [link.name for link in description.links]
    radii = np.array([link.radius for link in description.links])
    joined = {frozenset((joint.parent, joint.child)) for joint in description.joints}
    anchors = {joint.child: (joint.parent, joint.attach_fraction) for joint in description.joints}
    pairs = np.array([(i, j) for i in range(len(names)) for j in range(i + 1, len(names))
                      if frozenset((names[i], names[j])) not in joined
                      and not (names[i] in anchors and anchors[names[i]] == anchors.get(names[j]))]).reshape(-1, 2)
    first, second = pairs[:, 0], pairs[:, 1]
    distances = segment_distances(starts[first], ends[first], starts[second], ends[second])
    overlapping = distances < radii[first] + radii[second] - 1e-9
    return tuple((names[i], names[j]) for i, j in pairs[overlapping])


def _convex_hull(points: np.ndarray) -> np.ndarray:
    """Counter-clockwise hull vertices of 2-D points (Andrew's monotone chain)."""
    unique = sorted({(round(float(x), 9), round(float(y), 9)) for x, y in points})
    if len(unique) < 3:
        return np.array(unique).reshape(-1, 2)

    def half(sequence):
        chain: list[tuple[float, float]] = []
        for point in sequence:
            while len(chain) >= 2 and ((chain[-1][0] - chain[-2][0]) * (point[1] - chain[-2][1])
                                       - (chain[-1][1] - chain[-2][1]) * (point[0] - chain[-2][0])) <= 0:
                chain.pop()
            chain.append(point)
        return chain[:-1]

    return np.array(half(unique) + half(reversed(unique)))


@dataclass(frozen=True, eq=False)
class Stance:
    """How a robot rests: its self-collisions, its support polygon and its centre of mass on the ground."""

    collisions: tuple[tuple[str, str], ...]
    support: np.ndarray  # (k, 2) hull vertices, counter-clockwise
    centre_of_mass: np.ndarray  # (2,)
    support_margin: float  # signed distance of the centre of mass inside the support (m); -inf without area

    def stands(self, margin: float = SUPPORT_MARGIN) -> bool:
        return not self.collisions and self.support_margin >= margin

    def failure(self, margin: float = SUPPORT_MARGIN) -> str | None:
        """Why the robot does not stand (None when it does), for reports."""
        if self.collisions:
            return f"self-collision {self.collisions[0]}"
        if not math.isfinite(self.support_margin):
            return "rests on a point or a line"
        if self.support_margin < margin:
            return f"centre of mass {self.support_margin:+.3f} m from the support edge"
        return None


def _support(description: RobotDescription, contact_tolerance: float) -> tuple[np.ndarray, np.ndarray, float]:
    """The support polygon, the centre of mass on the ground and its signed margin (see :class:`Stance`)."""
    starts, ends = rest_segments(description)
    radii = np.array([link.radius for link in description.links])
    masses = np.array([link.mass for link in description.links])
    bottoms = np.concatenate([starts[:, 2] - radii, ends[:, 2] - radii])
    touching = bottoms <= bottoms.min() + contact_tolerance
    contacts = np.concatenate([starts[:, :2], ends[:, :2]])[touching]
    centre = (masses[:, None] * (starts + ends)[:, :2] / 2).sum(0) / masses.sum()
    hull = _convex_hull(contacts)
    margin = -math.inf
    if len(hull) >= 3:
        edges = np.roll(hull, -1, axis=0) - hull
        area = 0.5 * float(np.sum(hull[:, 0] * np.roll(hull[:, 1], -1) - np.roll(hull[:, 0], -1) * hull[:, 1]))
        if area > 1e-6:
            to_centre = centre - hull
            cross = edges[:, 0] * to_centre[:, 1] - edges[:, 1] * to_centre[:, 0]
            margin = float(np.min(cross / np.linalg.norm(edges, axis=1)))
    return hull, centre, margin


def stance(description: RobotDescription, contact_tolerance: float = CONTACT_TOLERANCE) -> Stance:
    """The robot's rest stance (see the module docstring), in the base's frame."""
    hull, centre, margin = _support(description, contact_tolerance)
    return Stance(self_collisions(description), hull, centre, margin)


def stands(description: RobotDescription, margin: float = SUPPORT_MARGIN,
           contact_tolerance: float = CONTACT_TOLERANCE) -> bool:
    """Whether the robot stands; cheaper than :func:`stance`, it looks for collisions only when
    the support holds (most robots of the grammar fail on their support)."""
    return _support(description, contact_tolerance)[2] >= margin and not self_collisions(description)
