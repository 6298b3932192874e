"""Where training data come from: real epochs of whole episodes, the replay buffer of real
transitions a world model fits on, and imagined batches from a fitted world model."""

from unipolicy_rl.collectors.imagination import (
    HorizonSchedule,
    Imagination,
    ImaginationSettings,
    ImaginedEpoch,
    RealCheck,
    StoppingRule,
    imagined_metrics,
)
from unipolicy_rl.collectors.mean_action import MEAN_ACTION, MeanActionRobots
from unipolicy_rl.collectors.real import (
    DATA_SOURCE,
    IMAGINED,
    REAL,
    RealEpochCollector,
    ShutdownCompleteMultiSyncCollector,
    is_imagined,
    truncate_last_step,
)
from unipolicy_rl.collectors.replay import COLLECTED_IN, TransitionBuffer, transitions

__all__ = [
    "COLLECTED_IN",
    "DATA_SOURCE",
    "IMAGINED",
    "MEAN_ACTION",
    "REAL",
    "HorizonSchedule",
    "Imagination",
    "ImaginationSettings",
    "ImaginedEpoch",
    "MeanActionRobots",
    "RealCheck",
    "RealEpochCollector",
    "ShutdownCompleteMultiSyncCollector",
    "StoppingRule",
    "TransitionBuffer",
    "imagined_metrics",
    "is_imagined",
    "transitions",
    "truncate_last_step",
]
