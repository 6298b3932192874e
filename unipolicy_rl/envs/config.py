"""The env a config describes: keyword arguments of :class:`~unipolicy_rl.envs.BatchedWalkerEnv`.

Training, evaluation and a loaded checkpoint all build their robots from here, so a policy is
always run on the env it was trained on.
"""

from __future__ import annotations

from hydra.utils import instantiate
from omegaconf import DictConfig


def env_kwargs(cfg: DictConfig) -> dict:
    """Keyword arguments of :class:`BatchedWalkerEnv` (all but ``num_robots``) from the config."""
    robot = cfg.robot
    return {
        "design": instantiate(cfg.design),
        "robot": instantiate(robot.settings, _convert_="all"),
        "physics": instantiate(robot.physics),
        "observation": robot.observation,
        "append_design": robot.append_design,
        "reward_weights": instantiate(robot.reward),
        "episode_length": robot.episode_length,
    }
