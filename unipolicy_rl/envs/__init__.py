"""Walking environments: gymnasium's ``WalkerEnv``, the batched TorchRL ``BatchedWalkerEnv``,
``MorphologyWalkerEnv`` for robots of many grammar morphologies, and ``SleepingParallelEnv`` to
spread batches over cores."""

import gymnasium

from unipolicy_rl.cpu_speed.parallel_env import SleepingParallelEnv
from unipolicy_rl.envs.batched import BatchedWalkerEnv
from unipolicy_rl.envs.design import Design, DesignDistribution
from unipolicy_rl.envs.morphology import MorphologyWalkerEnv
from unipolicy_rl.envs.reward import RewardWeights, walking_reward
from unipolicy_rl.envs.simulation import PhysicsSettings, RobotSettings, WalkerSimulation
from unipolicy_rl.envs.walker import WalkerEnv

ENV_ID = "unipolicy_rl/Walker-v0"
if ENV_ID not in gymnasium.registry:
    gymnasium.register(ENV_ID, entry_point="unipolicy_rl.envs.walker:WalkerEnv")

__all__ = [
    "ENV_ID",
    "BatchedWalkerEnv",
    "Design",
    "DesignDistribution",
    "MorphologyWalkerEnv",
    "PhysicsSettings",
    "RewardWeights",
    "RobotSettings",
    "SleepingParallelEnv",
    "WalkerEnv",
    "WalkerSimulation",
    "walking_reward",
]
