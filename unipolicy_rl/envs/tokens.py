"""The keys a robot of any morphology is observed and driven through: one token per link, padded.

Robots of different grammar derivations have different numbers of links and joints, so a batch
of them cannot share the flat ``observation`` / ``action`` of one topology. Instead each robot is
a sequence of link tokens padded to the largest robot the run may meet, with masks saying which
slots are real. These names are the contract between the env that writes them, the policies
that read them and the learners that must ignore the padding; they live here, once.

Shapes (``*`` is the env's batch shape, ``L`` the padded number of links):

- ``TOKENS``: ``[*, L, F]`` float32, one feature row per slot (the root, the base link, at slot
  0); which slot each link takes is the env's layout (:mod:`unipolicy_rl.envs.slot_layout`:
  packed in link order, or fixed by the link's role, with padding in the gaps).
- ``TOKEN_MASK``: ``[*, L]`` bool, True for a real link, False for padding.
- ``TOKEN_PARENT``: ``[*, L]`` int64, the token index of the link's parent in the body tree;
  -1 for the root and for padding (what a graph-masked attention reads).
- ``ACTION_MASK``: ``[*, L]`` bool, True where the link's joint to its parent is actuated.
  The action is ``[*, L]``: slot ``i`` drives its link's parent joint; slots where the mask
  is False (the root, fixed joints, padding) are ignored by the env and must count for nothing
  in a learner's log-probabilities, entropy and KL.
- ``MORPHOLOGY``: ``[*, 1]`` int64, which robot of the env's morphology set each robot is (an
  index into it), for evaluation to group by; set it in a reset to force a robot.
- ``CLOCK``: ``[*, 2]`` float32, only from an env given a clock frequency: ``(sin, cos)`` of the
  gait phase ``2 pi f t``, ``t`` the seconds since the robot's episode began. One rhythm every
  joint can read, whatever the body (a travelling wave is each joint's phase offset on it).

A token's features, in :data:`TOKEN_FEATURES` order (``F`` = :data:`TOKEN_SIZE`), world frame
unless said; the first six are the thesis observation's per-body numbers, so the root token's
first six are the base's ``x, y, z, x_dot, y_dot, z_dot`` that ``walking_reward`` and
``forward_displacement`` read (``walking_reward(tokens[..., 0, :])`` is the reward):

- ``x, y, z``: the root: the base's position from where it started (x, y) and its height (z);
  a link: its centre of mass from the base's.
- ``vx, vy, vz``: linear velocity of the centre of mass.
- ``r00 ... r21``: orientation as the first two columns of a rotation matrix (continuous, unlike
  a quaternion): the root's in the world frame (which holds the base's tilt against gravity),
  a link's relative to the base (``R_base^T R_link``).
- ``wx, wy, wz``: angular velocity.
- ``joint_angle``, ``joint_rate``: of the link's parent joint (rad, rad/s); 0 for the root, a
  fixed joint and a locked hinge.
- ``axis_x, axis_y, axis_z``: the parent hinge's axis in the link's frame; 0 where no hinge moves.
- ``actuated``: 1 where the parent joint is driven (what ``ACTION_MASK`` says).
- ``kind_<name>``: one-hot of the link's kind, one per ``LINK_KINDS`` entry, in its order.
- ``length, radius, mass``: the link's size (m, m, kg); by default at the design distribution's
  mean, not the episode's design, so a policy is not told the uncertain design (as SE).

Padding tokens are all zeros.
"""

from __future__ import annotations

import torch
from tensordict import TensorDictBase

from unipolicy_rl.envs.reward import BASE_X, BASE_X_DOT, BASE_Y, BASE_Z
from unipolicy_rl.robots.grammar.parts import LINK_KINDS

TOKENS = "tokens"
TOKEN_MASK = "token_mask"
TOKEN_PARENT = "token_parent"
ACTION_MASK = "action_mask"
MORPHOLOGY = "morphology"
CLOCK = "clock"

TOKEN_FEATURES: tuple[str, ...] = (
    "x", "y", "z",
    "vx", "vy", "vz",
    "r00", "r10", "r20", "r01", "r11", "r21",
    "wx", "wy", "wz",
    "joint_angle", "joint_rate",
    "axis_x", "axis_y", "axis_z",
    "actuated",
    *(f"kind_{name}" for name in LINK_KINDS),
    "length", "radius", "mass",
)
TOKEN_SIZE = len(TOKEN_FEATURES)
FEATURE_INDEX: dict[str, int] = {name: index for index, name in enumerate(TOKEN_FEATURES)}

# The root token is read by the reward as an observation of the thesis layout.
assert [FEATURE_INDEX[name] for name in ("x", "y", "z", "vx")] == [BASE_X, BASE_Y, BASE_Z, BASE_X_DOT]
# Every real link has exactly one kind; padding has none (it is all zeros).
KIND_FEATURES = [FEATURE_INDEX[f"kind_{name}"] for name in LINK_KINDS]


def real_tokens(tokens: torch.Tensor) -> torch.Tensor:
    """``[*, L]`` bool: the ``TOKEN_MASK`` the tokens themselves imply (a real link has a kind,
    padding is all zeros), for code that holds the tokens alone (a world model's state)."""
    return tokens[..., KIND_FEATURES].sum(-1) > 0.5


def driven_tokens(tokens: torch.Tensor) -> torch.Tensor:
    """``[*, L]`` bool: the ``ACTION_MASK`` the tokens themselves imply (their ``actuated`` feature)."""
    return tokens[..., FEATURE_INDEX["actuated"]] > 0.5


def walking_observation(tensordict: TensorDictBase) -> torch.Tensor:
    """What ``walking_reward`` and ``forward_displacement`` read from a step of either env: the
    root token (the thesis layout's first six numbers) of a token env, else the flat ``observation``."""
    if TOKENS in tensordict.keys():
        return tensordict.get(TOKENS)[..., 0, :]
    return tensordict.get("observation")
