"""Robots as data, their URDF export and their PyBullet bodies."""

from unipolicy_rl.robots.description import Joint, Link, RobotDescription
from unipolicy_rl.robots.pybullet_body import RobotBody, load_robot
from unipolicy_rl.robots.urdf import to_urdf, write_urdf
from unipolicy_rl.robots.vertebrate import DEFAULT_ACTUATED, HINGES, standing_height, vertebrate

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
