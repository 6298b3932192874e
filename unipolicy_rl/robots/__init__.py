"""Robots as data, their URDF export and their PyBullet bodies.

The bodies (:mod:`~unipolicy_rl.robots.pybullet_body`) load on first use (PEP 562): robots as data
(a grammar's parts, a description) import without PyBullet.
"""

from unipolicy_rl.robots.description import Joint, Link, RobotDescription
from unipolicy_rl.robots.urdf import to_urdf, write_urdf
from unipolicy_rl.robots.vertebrate import DEFAULT_ACTUATED, HINGES, standing_height, vertebrate

_BODIES = ("RobotBody", "load_robot")


def __getattr__(name: str):
    if name not in _BODIES:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    from unipolicy_rl.robots import pybullet_body

    value = getattr(pybullet_body, name)
    globals()[name] = value
    return value


__all__ = [
    "DEFAULT_ACTUATED",
    "HINGES",
    "Joint",
    "Link",
    "RobotBody",
    "RobotDescription",
    "load_robot",
    "standing_height",
    "to_urdf",
    "vertebrate",
    "write_urdf",
]
