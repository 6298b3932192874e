"""The thesis' walking reward (eq. 2.12) as a pure function of the observation.

Surrogate world models predict observations, not rewards; because the reward reads only
the observation, a surrogate gets exactly the reward the real environment would give.
"""

from __future__ import annotations

from dataclasses import dataclass

# Every observation layout starts with the base link: x, y, z, then x_dot, y_dot, z_dot.
BASE_X, BASE_Y, BASE_Z, BASE_X_DOT = 0, 1, 2, 3


@dataclass(frozen=True)
class RewardWeights:
    """r = w_x * x + w_y * |y| + w_x_dot * x_dot of the base link; w_x > 0, w_y <= 0, w_x_dot >= 0."""

    w_x: float = 1.0
    w_y: float = -1.0
    w_x_dot: float = 1.0

    def __post_init__(self) -> None:
        if not self.w_x > 0:
            raise ValueError(f"w_x must be positive (it rewards forward progress), got {self.w_x!r}")
        if not self.w_y <= 0:
            raise ValueError(f"w_y must be <= 0 (it penalises sideways drift), got {self.w_y!r}")
        if not self.w_x_dot >= 0:
            raise ValueError(f"w_x_dot must be >= 0 (it rewards forward speed), got {self.w_x_dot!r}")


def forward_displacement(observation):
    """How far the robot has walked (m): its base's x, the coordinate the reward pays for.
    Every episode starts at x = 0, so the x of an episode's last observation is its displacement."""
    return observation[..., BASE_X]


def mean_forward_speed(displacement, steps, control_period: float):
    """Mean forward speed (m/s) of an episode of ``steps`` control steps."""
    return displacement / (steps * control_period)


def walking_reward(observation, weights: RewardWeights = RewardWeights()):
    """Reward of each observation in a batch (numpy array or torch tensor, last dim = features)."""
    x = observation[..., BASE_X]
    y = observation[..., BASE_Y]
    x_dot = observation[..., BASE_X_DOT]
    return weights.w_x * x + weights.w_y * abs(y) + weights.w_x_dot * x_dot
