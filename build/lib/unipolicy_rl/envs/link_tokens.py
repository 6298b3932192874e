"""The numbers of a link token (:data:`~unipolicy_rl.envs.tokens.TOKEN_FEATURES`), from a robot's build and state.

Split in two as the numbers are: what a robot's build fixes (its tree, which joints are driven,
hinge axes, kinds, sizes) is worked out once per episode by :func:`robot_tokens`; what moves is
worked out for the whole batch at once each step by :func:`moving_features`, in numpy, so a step
costs one vectorised pass whatever the mix of robots.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from unipolicy_rl.envs.tokens import FEATURE_INDEX, TOKEN_SIZE
from unipolicy_rl.robots.description import RobotDescription
from unipolicy_rl.robots.grammar.parts import LINK_KINDS

# Features that change every step come first, then those the build fixes.
MOVING = slice(0, FEATURE_INDEX["axis_x"])
BUILT = slice(FEATURE_INDEX["axis_x"], TOKEN_SIZE)
MOVING_SIZE = MOVING.stop
# Per link, what the simulation reads: position (3), quaternion xyzw (4), linear and angular velocity (3 + 3).
LINK_STATE_SIZE = 13


@dataclass(frozen=True, eq=False)
class RobotTokens:
    """What a robot's build fixes about its tokens, for its ``n`` links (the base first).

    ``parents``: each link's parent index (-1 for the base); ``action_mask``: True where the
    link's parent joint is driven; ``driven_links``: the links whose parent joint is driven, in
    the description's actuated-joint order (the order PyBullet's motors take targets);
    ``built``: (n, len(BUILT)) the build's features.
    """

    parents: np.ndarray
    action_mask: np.ndarray
    driven_links: np.ndarray
    built: np.ndarray

    @property
    def num_links(self) -> int:
        return len(self.parents)


def robot_tokens(description: RobotDescription, link_kinds: tuple[str, ...], sizes: RobotDescription) -> RobotTokens:
    """The build's part of the tokens of ``description`` (link kinds as :class:`PartKinds` names
    them). Sizes are read from ``sizes``, the same robot at the design the policy is told of."""
    n = len(description.links)
    if len(link_kinds) != n or len(sizes.links) != n:
        raise ValueError(f"{description.name!r} has {n} links but {len(link_kinds)} link kinds and "
                         f"{len(sizes.links)} sized links")
    parent_joint = {joint.child: joint for joint in description.joints}
    parents = np.full(n, -1, dtype=np.int64)
    action_mask = np.zeros(n, dtype=bool)
    built = np.zeros((n, BUILT.stop - BUILT.start))
    kinds = list(LINK_KINDS)

    def column(name: str) -> int:
        return FEATURE_INDEX[name] - BUILT.start

    for index, link in enumerate(description.links):
        kind = link_kinds[index]
        if kind not in LINK_KINDS:
            raise ValueError(f"link {link.name!r}: unknown link kind {kind!r}; kinds are {kinds}")
        built[index, column(f"kind_{kind}")] = 1.0
        sized = sizes.links[index]
        built[index, [column("length"), column("radius"), column("mass")]] = (sized.length, sized.radius, sized.mass)
        joint = parent_joint.get(link.name)
        if joint is None:
            continue
        parents[index] = description.link_index(joint.parent)
        if joint.actuated:  # a locked hinge is a fixed joint in the simulation: no axis, no angle
            action_mask[index] = True
            built[index, column("actuated")] = 1.0
            axis = np.asarray(joint.axis, dtype=float)
            built[index, [column("axis_x"), column("axis_y"), column("axis_z")]] = axis / np.linalg.norm(axis)
    driven = np.array([description.link_index(joint.child) for joint in description.actuated_joints], dtype=np.int64)
    return RobotTokens(parents, action_mask, driven, built)


def quaternion_matrices(quaternions: np.ndarray) -> np.ndarray:
    """Rotation matrices (..., 3, 3) of unit quaternions (..., 4) in PyBullet's (x, y, z, w) order."""
    x, y, z, w = np.moveaxis(quaternions, -1, 0)
    return np.stack([
        np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)], -1),
        np.stack([2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)], -1),
        np.stack([2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)], -1),
    ], -2)


def moving_features(link_states: np.ndarray, joints: np.ndarray, start_xy: np.ndarray,
                    base_inertial_rotations: np.ndarray) -> np.ndarray:
    """The moving part of every token, (N, L, MOVING_SIZE), from the links' world states
    (N, L, LINK_STATE_SIZE; slot 0 the base, whose orientation is its inertial frame's, which is
    ``base_inertial_rotations`` (N, 3, 3) in its link frame), their parent joints' (angle, rate)
    (N, L, 2) and where each base started (N, 2). Padding rows come out as garbage; the caller
    zeroes them."""
    positions, quaternions = link_states[..., 0:3], link_states[..., 3:7]
    linear, angular = link_states[..., 7:10], link_states[..., 10:13]
    rotations = quaternion_matrices(quaternions)
    base = rotations[:, 0] @ np.swapaxes(base_inertial_rotations, -1, -2)
    # A link's orientation relative to the base, R_base^T R_link; the root keeps its world orientation.
    relative = np.einsum("nji,nljk->nlik", base, rotations)
    relative[:, 0] = base
    orientation = np.concatenate([relative[..., :, 0], relative[..., :, 1]], axis=-1)
    offsets = positions - positions[:, :1]
    offsets[:, 0] = positions[:, 0]
    offsets[:, 0, :2] -= start_xy
    return np.concatenate([offsets, linear, orientation, angular, joints], axis=-1)
