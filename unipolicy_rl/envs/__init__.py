"""Walking environments: gymnasium's ``WalkerEnv``, the batched TorchRL ``BatchedWalkerEnv``,
``MorphologyWalkerEnv`` for robots of many grammar morphologies, and ``SleepingParallelEnv`` to
spread batches over cores.

The names below load on first use (PEP 562), so a module of this package that needs no physics
(the reward, the blow-up limit, the token layout) imports without PyBullet: a world model of
another env, or a policy's evaluation elsewhere, never pays for the simulator. The gymnasium id
is registered here, by name only (its entry point is imported when an env is made).
"""

from __future__ import annotations

import importlib

import gymnasium

ENV_ID = "unipolicy_rl/Walker-v0"
if ENV_ID not in gymnasium.registry:
    gymnasium.register(ENV_ID, entry_point="unipolicy_rl.envs.walker:WalkerEnv")

# Each exported name -> the module of this package that defines it (or its full name, elsewhere).
_EXPORTS = {
    "BatchedWalkerEnv": "batched",
    "Design": "design",
    "DesignDistribution": "design",
    "MorphologyWalkerEnv": "morphology",
    "SleepingParallelEnv": "unipolicy_rl.cpu_speed.parallel_env",
    "RewardWeights": "reward",
    "walking_reward": "reward",
    "PhysicsSettings": "simulation",
    "RobotSettings": "simulation",
    "WalkerSimulation": "simulation",
    "WalkerEnv": "walker",
}


def __getattr__(name: str):
    if name not in _EXPORTS:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    module = _EXPORTS[name] if "." in _EXPORTS[name] else f"{__name__}.{_EXPORTS[name]}"
    value = getattr(importlib.import_module(module), name)
    globals()[name] = value  # later lookups skip this function
    return value


def __dir__() -> list[str]:
    return sorted({*globals(), *_EXPORTS})


__all__ = ["ENV_ID", *_EXPORTS]
