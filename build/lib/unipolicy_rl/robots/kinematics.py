"""Where a robot's links lie with every joint at zero, computed from its description alone.

Placing a robot on the ground, checking it for self-collision and finding what it stands on
all need the rest pose; computing it from the description (as the URDF defines the frames)
needs no physics client, so a filter over thousands of candidate robots stays cheap.
"""

from __future__ import annotations

import numpy as np

from unipolicy_rl.robots.description import RobotDescription


def rpy_matrix(rpy: tuple[float, float, float]) -> np.ndarray:
    """URDF's fixed-axis roll, pitch, yaw: ``Rz(yaw) @ Ry(pitch) @ Rx(roll)``."""
    roll, pitch, yaw = rpy
    cr, sr, cp, sp, cy, sy = np.cos(roll), np.sin(roll), np.cos(pitch), np.sin(pitch), np.cos(yaw), np.sin(yaw)
    rx = np.array([[1.0, 0.0, 0.0], [0.0, cr, -sr], [0.0, sr, cr]])
    ry = np.array([[cp, 0.0, sp], [0.0, 1.0, 0.0], [-sp, 0.0, cp]])
    rz = np.array([[cy, -sy, 0.0], [sy, cy, 0.0], [0.0, 0.0, 1.0]])
    return rz @ ry @ rx


def rest_frames(description: RobotDescription) -> tuple[np.ndarray, np.ndarray]:
    """Each link's frame origin (n, 3) and rotation (n, 3, 3) in the base's frame, joints at zero,
    in the description's link order."""
    parent_joint = {joint.child: joint for joint in description.joints}
    origins = np.zeros((len(description.links), 3))
    rotations = np.repeat(np.eye(3)[None], len(description.links), axis=0)
    for index, link in enumerate(description.links[1:], start=1):
        joint = parent_joint[link.name]
        parent = description.link_index(joint.parent)
        offset = np.array([joint.attach_fraction * description.links[parent].length, 0.0, 0.0])
        origins[index] = origins[parent] + rotations[parent] @ offset
        rotations[index] = rotations[parent] @ rpy_matrix(joint.rpy)
    return origins, rotations


def rest_segments(description: RobotDescription) -> tuple[np.ndarray, np.ndarray]:
    """Each capsule's two sphere centres, ``(starts, ends)`` of shape (n, 3), joints at zero."""
    origins, rotations = rest_frames(description)
    lengths = np.array([link.length for link in description.links])
    return origins, origins + rotations[:, :, 0] * lengths[:, None]


def rest_height(description: RobotDescription) -> float:
    """Height of the base's frame at which the robot at rest just touches the ground: minus the
    lowest point of any capsule (the base's frame is turned about z only, so heights are kept)."""
    starts, ends = rest_segments(description)
    radii = np.array([link.radius for link in description.links])
    return float(-(np.minimum(starts[:, 2], ends[:, 2]) - radii).min())
