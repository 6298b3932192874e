"""The terminal parts a grammar rule puts into a robot: link kinds and joints.

RoboGrammar writes its parts in a y-up frame (gravity along -y, a limb's lateral axis is z);
our robots live in PyBullet's z-up frame. :func:`robogrammar_joint` turns a joint written
with RoboGrammar's attributes into ours, so the rule data can be read side by side with
RoboGrammar's rule file and the conversion is made in one place.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from unipolicy_rl.robots.description import JointKind


@dataclass(frozen=True)
class LinkKind:
    """A capsule kind; a design (l, rho) sizes it: ``length = length_factor * l``, ``density = density_factor * rho``.

    The factors keep the proportions between kinds while the design stays uncertain, as the
    thesis' robot shares one ``l`` and one ``rho`` among its links.
    """

    name: str
    length_factor: float
    radius: float
    density_factor: float = 1.0

    def __post_init__(self) -> None:
        for attribute in ("length_factor", "radius", "density_factor"):
            value = getattr(self, attribute)
            if not (isinstance(value, (int, float)) and math.isfinite(value) and value > 0):
                raise ValueError(f"link kind {self.name!r}: {attribute} must be positive and finite, got {value!r}")


# RoboGrammar's capsules (grammar_apr30.dot): body 0.15 x r 0.045, limb mount 0.10 x r 0.025,
# normal limb link 0.10 x r 0.025, long limb link 0.15 x r 0.025. Lengths are relative to the
# body's, the design's l. One deviation, the thesis': its legs hang from a mount as long as every
# other link (RoboGrammar's is 0.10), so the thesis robot is a derivation of the grammar. Densities
# follow the thesis too (one rho for all links; RoboGrammar's body is three times as dense).
LINK_KINDS: dict[str, LinkKind] = {
    kind.name: kind
    for kind in (
        LinkKind("body", 1.0, 0.045),
        LinkKind("limb_mount", 1.0, 0.025),
        LinkKind("normal_limb_link", 0.10 / 0.15, 0.025),
        LinkKind("long_limb_link", 1.0, 0.025),
    )
}


def link_kind(name: str) -> LinkKind:
    if name not in LINK_KINDS:
        raise ValueError(f"unknown link kind {name!r}; kinds are {sorted(LINK_KINDS)}")
    return LINK_KINDS[name]


@dataclass(frozen=True)
class JointPart:
    """A joint as a rule writes it, in our frame (see :class:`unipolicy_rl.robots.description.Joint`).

    ``name`` is the joint's type in the rule set (``roll``, ``obtuse_lift``, ...); it names
    the joints built from it.
    """

    name: str
    kind: JointKind
    attach_fraction: float = 1.0
    rpy: tuple[float, float, float] = (0.0, 0.0, 0.0)
    axis: tuple[float, float, float] = (1.0, 0.0, 0.0)

    def mirrored(self) -> JointPart:
        """The same joint on the other side of the robot's xz plane (y -> -y).

        RoboGrammar mirrors a leg across its own xy plane, its lateral axis being z; in our
        frame the lateral axis is y. A turn ``R`` becomes ``S R S`` with ``S = diag(1, -1, 1)``,
        which negates roll and yaw and keeps pitch; the hinge axis, written in the child's
        frame, has its y negated (RoboGrammar negates the lateral component likewise).
        """
        roll, pitch, yaw = self.rpy
        x, y, z = self.axis
        # 0.0 - v rather than -v: a mirrored zero stays 0.0 (URDF text writes -0.0 as "-0").
        return JointPart(self.name, self.kind, self.attach_fraction, (0.0 - roll, pitch, 0.0 - yaw), (x, 0.0 - y, z))


def _from_y_up(vector: tuple[float, float, float]) -> tuple[float, float, float]:
    """RoboGrammar's (x, y up, z lateral) to ours (x, y lateral, z up): a quarter turn about x."""
    x, y, z = vector
    return (float(x), float(-z), float(y))


def robogrammar_joint(
    name: str,
    kind: JointKind,
    offset: float = 1.0,
    axis_angle: tuple[float, float, float, float] | None = None,
    joint_axis: tuple[float, float, float] = (1.0, 0.0, 0.0),
) -> JointPart:
    """A joint from RoboGrammar's edge attributes (``offset``, ``axis_angle`` in degrees, ``joint_axis``).

    RoboGrammar hands ``axis_angle`` to Bullet as the rotation from the parent's frame into the
    child's, so the child is turned by minus that angle. Every turn in the rule set is about a
    coordinate axis, which maps to one of roll, pitch or yaw exactly. A fixed joint has no
    axis; it keeps :class:`Joint`'s default so descriptions compare equal.
    """
    rpy = (0.0, 0.0, 0.0)
    if axis_angle is not None:
        *turn_axis, degrees = axis_angle
        ours = _from_y_up(tuple(turn_axis))
        nonzero = [i for i, component in enumerate(ours) if component != 0.0]
        if len(nonzero) != 1 or abs(ours[nonzero[0]]) != 1.0:
            raise ValueError(f"joint {name!r}: axis_angle must turn about a coordinate axis, got {axis_angle!r}")
        angles = [0.0, 0.0, 0.0]
        angles[nonzero[0]] = -ours[nonzero[0]] * math.radians(degrees)
        rpy = tuple(angles)
    axis = _from_y_up(joint_axis) if kind == "hinge" else (1.0, 0.0, 0.0)
    return JointPart(name, kind, offset, rpy, axis)
