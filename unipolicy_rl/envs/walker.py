"""``WalkerEnv``: the thesis robot as a gymnasium environment, registered as ``unipolicy_rl/Walker-v0``."""

from __future__ import annotations

from collections.abc import Mapping

import gymnasium
import numpy as np
import pybullet

from unipolicy_rl.envs.design import Design, DesignDistribution
from unipolicy_rl.envs.limits import EXPLOSION_LIMIT
from unipolicy_rl.envs.reward import RewardWeights, forward_displacement, mean_forward_speed, walking_reward
from unipolicy_rl.envs.simulation import PhysicsSettings, RobotSettings, WalkerSimulation


def design_from_options(options: Mapping | None) -> Design | None:
    """Reads an explicit design from ``reset(options={"design": ...})``: a Design, (l, rho) or a mapping."""
    if not options or options.get("design") is None:
        return None
    design = options["design"]
    if isinstance(design, Design):
        return design
    if isinstance(design, Mapping):
        return Design(float(design["length"]), float(design["density"]))
    try:
        length, density = design
    except (TypeError, ValueError):
        raise ValueError(f"design must be a Design, (length, density) or a mapping, got {design!r}") from None
    return Design(float(length), float(density))


class WalkerEnv(gymnasium.Env):
    """One robot walking on a plane; its build is drawn from ``design`` at every reset.

    Action: targets for the actuated joints in [-1, 1] (clipped), scaled to +-1.5 rad of
    the initial pose. Observation: the base and two feet's positions and velocities (18
    numbers, "thesis") or every link's plus the actuated joints' ("full"), with (l, rho)
    appended when ``append_design``. Reward: :func:`walking_reward` of the observation.
    An episode is truncated after ``episode_length`` actions, or early if the physics
    blows up (``info["physics_fault"]``).
    """

    metadata = {"render_modes": ["rgb_array"], "render_fps": 15}

    def __init__(
        self,
        design: DesignDistribution | None = None,
        robot: RobotSettings | None = None,
        physics: PhysicsSettings | None = None,
        observation: str = "thesis",
        append_design: bool = False,
        reward_weights: RewardWeights | None = None,
        episode_length: int = 100,
        render_mode: str | None = None,
    ):
        if not (isinstance(episode_length, (int, np.integer)) and episode_length >= 1):
            raise ValueError(f"episode_length must be a positive integer, got {episode_length!r}")
        if render_mode is not None and render_mode not in self.metadata["render_modes"]:
            raise ValueError(f"render_mode must be one of {self.metadata['render_modes']} or None, got {render_mode!r}")
        self.design_distribution = design or DesignDistribution()
        self.reward_weights = reward_weights or RewardWeights()
        self.episode_length = int(episode_length)
        self.append_design = append_design
        self.render_mode = render_mode
        self.simulation = WalkerSimulation(robot or RobotSettings(), physics or PhysicsSettings(), observation,
                                           visuals=render_mode is not None)
        size = self.simulation.observation_size + (2 if append_design else 0)
        # Faulted steps never report past the explosion limit, so the bounds are honest.
        self.observation_space = gymnasium.spaces.Box(-EXPLOSION_LIMIT, EXPLOSION_LIMIT, (size,), np.float32)
        self.action_space = gymnasium.spaces.Box(-1.0, 1.0, (self.simulation.num_actions,), np.float32)
        self._steps = 0

    def _observe(self, raw: np.ndarray) -> np.ndarray:
        if self.append_design:
            design = self.simulation.design
            raw = np.concatenate([raw, (design.length, design.density)])
        return raw.astype(np.float32)

    def _info(self, raw: np.ndarray, fault: bool = False) -> dict:
        displacement = float(forward_displacement(raw))
        return {
            "design": self.simulation.design,
            "forward_displacement": displacement,
            "mean_forward_speed": (float(mean_forward_speed(displacement, self._steps,
                                                            self.simulation.physics.control_period))
                                   if self._steps else 0.0),
            "physics_fault": fault,
        }

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        design = design_from_options(options) or self.design_distribution.sample(self.np_random)
        self._steps = 0
        raw = self.simulation.reset(design)
        return self._observe(raw), self._info(raw)

    def step(self, action):
        action = np.asarray(action, dtype=np.float64)
        if action.shape != self.action_space.shape:
            raise ValueError(f"action must have shape {self.action_space.shape}, got {action.shape}")
        if self.simulation.design is None:
            raise RuntimeError("call reset() before step()")
        raw, fault = self.simulation.step(action)
        self._steps += 1
        observation = self._observe(raw)
        reward = float(walking_reward(raw, self.reward_weights))
        truncated = fault or self._steps >= self.episode_length
        return observation, reward, False, truncated, self._info(raw, fault)

    def render(self):
        if self.render_mode != "rgb_array":
            return None
        x, y, _ = self.simulation.base_position()
        client = self.simulation.client
        view = pybullet.computeViewMatrixFromYawPitchRoll((x, y, 0.1), 1.6, 30.0, -30.0, 0.0, 2, physicsClientId=client)
        projection = pybullet.computeProjectionMatrixFOV(60.0, 4 / 3, 0.05, 20.0, physicsClientId=client)
        _, _, rgba, _, _ = pybullet.getCameraImage(
            320, 240, view, projection, renderer=pybullet.ER_TINY_RENDERER, physicsClientId=client
        )
        return np.asarray(rgba, dtype=np.uint8).reshape(240, 320, 4)[..., :3]

    def close(self):
        self.simulation.close()
