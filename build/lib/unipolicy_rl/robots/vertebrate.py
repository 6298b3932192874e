"""The thesis robot ("vertebrate"): three body links in a row and four two-joint legs.

RoboGrammar's parts, re-created: body capsules (radius 0.045), a limb mount fixed at the
middle of a body link and turned 90 degrees sideways, then a thigh on a roll joint (a
hinge about the limb axis, which swings the bent leg fore and aft) and a shin on a knee
joint (a hinge perpendicular to the limb, which lifts the foot), the shin bent down by
``knee_angle_deg``. Two roll joints join the body links. That makes ten hinges; the
thesis actuates four of them and locks the other six.

A pair's legs are mirror images as RoboGrammar mirrors them: a hinge's axis has its lateral
component negated on the right leg, so the left knee turns about -y and the right about +y.
That makes this robot a derivation of the grammar (``unipolicy_rl.robots.grammar``,
:data:`~unipolicy_rl.robots.grammar.VERTEBRATE`); a locked hinge's axis does
not reach the URDF, so the default robot, knees locked, is unchanged by it.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

from unipolicy_rl.robots.description import Joint, Link, RobotDescription

BODY_RADIUS = 0.045
LIMB_RADIUS = 0.025
LEGS = ("front_left", "front_right", "rear_left", "rear_right")
HINGES = (
    "body_roll_1",
    "body_roll_2",
    *(f"{leg}_{part}" for leg in LEGS for part in ("hip", "knee")),
)
# The four hip roll joints swing the bent legs fore and aft. Of the choices we searched
# with open-loop sinusoids (four hips, four knees, front hips + rear knees, front hips +
# front knees), four hips walked furthest (the gait's distance today: docs/results.md,
# "Environment throughput").
DEFAULT_ACTUATED = ("front_left_hip", "front_right_hip", "rear_left_hip", "rear_right_hip")


def vertebrate(
    length: float = 0.175,
    density: float = 0.5,
    actuated: Sequence[str] = DEFAULT_ACTUATED,
    knee_angle_deg: float = 60.0,
) -> RobotDescription:
    """Builds the vertebrate with every link of ``length`` (m) and ``density`` (kg/m)."""
    unknown = sorted(set(actuated) - set(HINGES))
    if unknown:
        raise ValueError(f"unknown actuated joint(s) {unknown}; hinges are {list(HINGES)}")
    if len(set(actuated)) != len(actuated):
        raise ValueError(f"actuated joints repeat: {list(actuated)}")
    if not 0.0 < knee_angle_deg < 180.0:
        raise ValueError(f"knee_angle_deg must lie in (0, 180), got {knee_angle_deg!r}")
    actuated = set(actuated)

    links = [Link(f"body_{i}", length, BODY_RADIUS, density) for i in range(3)]
    joints = [
        Joint(f"body_roll_{i}", "hinge", f"body_{i - 1}", f"body_{i}", 1.0, axis=(1.0, 0.0, 0.0),
              actuated=f"body_roll_{i}" in actuated)
        for i in (1, 2)
    ]
    knee_pitch = math.radians(knee_angle_deg)
    for leg in LEGS:
        body = "body_0" if leg.startswith("front") else "body_2"
        # The base is placed turned 180 degrees about z (its +x trails behind the head),
        # so world-left (+y) is the body frame's -y.
        side_yaw = -math.pi / 2 if leg.endswith("left") else math.pi / 2
        knee_axis = (0.0, -1.0, 0.0) if leg.endswith("left") else (0.0, 1.0, 0.0)
        links += [Link(f"{leg}_{part}", length, LIMB_RADIUS, density) for part in ("mount", "thigh", "shin")]
        joints += [
            Joint(f"{leg}_mount", "fixed", body, f"{leg}_mount", 0.5, rpy=(0.0, 0.0, side_yaw)),
            Joint(f"{leg}_hip", "hinge", f"{leg}_mount", f"{leg}_thigh", 1.0, axis=(1.0, 0.0, 0.0),
                  actuated=f"{leg}_hip" in actuated),
            Joint(f"{leg}_knee", "hinge", f"{leg}_thigh", f"{leg}_shin", 1.0, rpy=(0.0, knee_pitch, 0.0),
                  axis=knee_axis, actuated=f"{leg}_knee" in actuated),
        ]
    return RobotDescription("vertebrate", tuple(links), tuple(joints))


def standing_height(description: RobotDescription) -> float:
    """Height of the body axis at which the lowest foot just touches the ground."""
    shin = description.link("front_left_shin")
    knee = description.joint("front_left_knee")
    drop = shin.length * math.sin(knee.rpy[1])
    return max(drop + shin.radius, description.base.radius)
