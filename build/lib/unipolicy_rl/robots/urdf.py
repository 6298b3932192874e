"""Export a :class:`RobotDescription` to URDF, the format PyBullet and most robotics tools read.

The simulated body is built from this same text, so what another tool opens is what we
simulate: locked hinges are written as fixed joints, actuated ones as revolute joints
limited to the action range.
"""

from __future__ import annotations

import math
from pathlib import Path
from xml.sax.saxutils import quoteattr

from unipolicy_rl.robots.description import Joint, Link, RobotDescription

JOINT_RANGE = 1.5  # rad either side of the initial pose, the thesis' action limit


def _vector(values) -> str:
    return " ".join(f"{value:.9g}" for value in values)


def _inertia(link: Link) -> str:
    """Solid cylinder of the capsule's length: close to the capsule, and exact in mass.

    Written in the capsule's own frame (its axis along z, see :func:`_link`).
    """
    mass, radius, length = link.mass, link.radius, link.length
    axial = 0.5 * mass * radius**2
    transverse = mass * (3 * radius**2 + length**2) / 12.0
    return (
        f'<inertia ixx="{transverse:.9g}" iyy="{transverse:.9g}" izz="{axial:.9g}" ixy="0" ixz="0" iyz="0"/>'
    )


def _visuals(link: Link) -> str:
    """A cylinder and two spheres: standard URDF geometry, where <capsule> is a PyBullet extension."""
    centre = _vector((link.length / 2, 0.0, 0.0))
    along_x = _vector((0.0, math.pi / 2, 0.0))
    end = _vector((link.length, 0.0, 0.0))
    return f"""<visual>
      <origin xyz="{centre}" rpy="{along_x}"/>
      <geometry><cylinder radius="{link.radius:.9g}" length="{link.length:.9g}"/></geometry>
    </visual>
    <visual>
      <origin xyz="0 0 0" rpy="0 0 0"/>
      <geometry><sphere radius="{link.radius:.9g}"/></geometry>
    </visual>
    <visual>
      <origin xyz="{end}" rpy="0 0 0"/>
      <geometry><sphere radius="{link.radius:.9g}"/></geometry>
    </visual>
    """


def _link(link: Link, visuals: bool) -> str:
    """A capsule along the link's x axis, its inertial frame the capsule's own frame.

    URDF capsules lie along their frame's z axis, so the collision is turned onto x. The
    inertial frame gets the same turn: when a link's collision frame and inertial frame
    coincide, PyBullet attaches the capsule to the link directly; otherwise it wraps it in
    a one-child compound shape, a slower world to step and a larger one to keep in cache
    (docs/results.md has what removing them gained).
    """
    centre = _vector((link.length / 2, 0.0, 0.0))
    along_x = _vector((0.0, math.pi / 2, 0.0))
    return f"""  <link name={quoteattr(link.name)}>
    <inertial>
      <origin xyz="{centre}" rpy="{along_x}"/>
      <mass value="{link.mass:.9g}"/>
      {_inertia(link)}
    </inertial>
    {_visuals(link) if visuals else ""}<collision>
      <origin xyz="{centre}" rpy="{along_x}"/>
      <geometry><capsule radius="{link.radius:.9g}" length="{link.length:.9g}"/></geometry>
    </collision>
  </link>
"""


def _joint(joint: Joint, parent: Link, max_torque: float) -> str:
    origin = _vector((joint.attach_fraction * parent.length, 0.0, 0.0))
    header = f'<origin xyz="{origin}" rpy="{_vector(joint.rpy)}"/>'
    if joint.kind == "hinge" and joint.actuated:
        norm = math.hypot(*joint.axis)
        axis = _vector(component / norm for component in joint.axis)
        return f"""  <joint name={quoteattr(joint.name)} type="revolute">
    <parent link={quoteattr(joint.parent)}/>
    <child link={quoteattr(joint.child)}/>
    {header}
    <axis xyz="{axis}"/>
    <limit lower="{-JOINT_RANGE}" upper="{JOINT_RANGE}" effort="{max_torque:.9g}" velocity="100"/>
  </joint>
"""
    return f"""  <joint name={quoteattr(joint.name)} type="fixed">
    <parent link={quoteattr(joint.parent)}/>
    <child link={quoteattr(joint.child)}/>
    {header}
  </joint>
"""


def to_urdf(description: RobotDescription, max_torque: float = 1.0, visuals: bool = True) -> str:
    """The robot as URDF text; joint efforts carry ``max_torque`` (N m).

    ``visuals=False`` leaves out the visual geometry: PyBullet builds renderer shapes for
    it even in DIRECT mode, which made loading a robot several times slower, a cost paid at
    every episode reset when the design changes.
    """
    parts = [f'<?xml version="1.0"?>\n<robot name={quoteattr(description.name)}>\n']
    parts += [_link(link, visuals) for link in description.links]
    parts += [_joint(joint, description.link(joint.parent), max_torque) for joint in description.joints]
    parts.append("</robot>\n")
    return "".join(parts)


def write_urdf(description: RobotDescription, path: str | Path, max_torque: float = 1.0) -> Path:
    """Writes the full URDF (with visuals) for other tools to open."""
    path = Path(path)
    path.write_text(to_urdf(description, max_torque))
    return path
