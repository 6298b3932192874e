"""A robot described as plain data: capsule links joined by fixed or hinge joints.

Keeping the robot as data (rather than as PyBullet calls) lets one description be
validated once, exported to URDF for other tools, and rebuilt in PyBullet with a new
link length and density at every episode.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Literal

JointKind = Literal["fixed", "hinge"]


@dataclass(frozen=True)
class Link:
    """A capsule that extends along its own +x axis from its joint.

    ``length`` is the distance between the two sphere centres, as in RoboGrammar;
    ``density`` is mass per unit length, so ``mass = density * length``.
    """

    name: str
    length: float
    radius: float
    density: float

    def __post_init__(self) -> None:
        for attribute in ("length", "radius", "density"):
            value = getattr(self, attribute)
            if not (isinstance(value, (int, float)) and math.isfinite(value) and value > 0):
                raise ValueError(f"link {self.name!r}: {attribute} must be a positive finite number, got {value!r}")

    @property
    def mass(self) -> float:
        return self.density * self.length


@dataclass(frozen=True)
class Joint:
    """Connects ``child`` to ``parent``.

    The child's frame sits at ``attach_fraction`` of the parent's length along the
    parent's axis, rotated by ``rpy`` (roll, pitch, yaw in radians) from the parent's
    frame. A hinge turns about ``axis``, given in the child's frame. A hinge that is not
    ``actuated`` is locked at its initial pose.
    """

    name: str
    kind: JointKind
    parent: str
    child: str
    attach_fraction: float = 1.0
    rpy: tuple[float, float, float] = (0.0, 0.0, 0.0)
    axis: tuple[float, float, float] = (1.0, 0.0, 0.0)
    actuated: bool = False

    def __post_init__(self) -> None:
        if self.kind not in ("fixed", "hinge"):
            raise ValueError(f"joint {self.name!r}: kind must be 'fixed' or 'hinge', got {self.kind!r}")
        if not 0.0 <= self.attach_fraction <= 1.0:
            raise ValueError(f"joint {self.name!r}: attach_fraction must lie in [0, 1], got {self.attach_fraction!r}")
        if self.kind == "fixed" and self.actuated:
            raise ValueError(f"joint {self.name!r}: a fixed joint cannot be actuated")
        if math.hypot(*self.axis) == 0.0:
            raise ValueError(f"joint {self.name!r}: axis must be non-zero, got {self.axis!r}")


@dataclass(frozen=True)
class RobotDescription:
    """A kinematic tree: ``links[0]`` is the base (the head); every other link has one parent joint."""

    name: str
    links: tuple[Link, ...]
    joints: tuple[Joint, ...]
    _index: dict[str, int] = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        if not self.links:
            raise ValueError("a robot needs at least one link")
        names = [link.name for link in self.links]
        if len(set(names)) != len(names):
            raise ValueError(f"link names must be unique, got {names}")
        index = {name: i for i, name in enumerate(names)}
        seen_children: set[str] = set()
        for joint in self.joints:
            for end in (joint.parent, joint.child):
                if end not in index:
                    raise ValueError(f"joint {joint.name!r} names unknown link {end!r}")
            if index[joint.parent] >= index[joint.child]:
                raise ValueError(
                    f"joint {joint.name!r}: parent {joint.parent!r} must come before child {joint.child!r}"
                )
            if joint.child in seen_children:
                raise ValueError(f"link {joint.child!r} has more than one parent joint")
            seen_children.add(joint.child)
        orphans = set(names[1:]) - seen_children
        if orphans:
            raise ValueError(f"links without a parent joint: {sorted(orphans)}")
        joint_names = [joint.name for joint in self.joints]
        if len(set(joint_names)) != len(joint_names):
            raise ValueError(f"joint names must be unique, got {joint_names}")
        object.__setattr__(self, "_index", index)

    @property
    def base(self) -> Link:
        return self.links[0]

    def link(self, name: str) -> Link:
        if name not in self._index:
            raise ValueError(f"unknown link {name!r}; links are {[link.name for link in self.links]}")
        return self.links[self._index[name]]

    def link_index(self, name: str) -> int:
        self.link(name)
        return self._index[name]

    def joint(self, name: str) -> Joint:
        for joint in self.joints:
            if joint.name == name:
                return joint
        raise ValueError(f"unknown joint {name!r}; joints are {[joint.name for joint in self.joints]}")

    @property
    def hinges(self) -> tuple[Joint, ...]:
        return tuple(joint for joint in self.joints if joint.kind == "hinge")

    @property
    def actuated_joints(self) -> tuple[Joint, ...]:
        return tuple(joint for joint in self.joints if joint.actuated)

    @property
    def total_mass(self) -> float:
        return sum(link.mass for link in self.links)
