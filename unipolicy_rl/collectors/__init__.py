"""Collectors that yield labelled training batches: real epochs, or real epochs alternating
with imagined batches from a world model."""

from unipolicy_rl.collectors.model_based import (
    HorizonSchedule,
    ImaginationSettings,
    ModelBasedCollector,
    StoppingRule,
    transitions,
)
from unipolicy_rl.collectors.real import (
    DATA_SOURCE,
    IMAGINED,
    REAL,
    RealEpochCollector,
    ShutdownCompleteMultiSyncCollector,
    epoch_seed,
    is_imagined,
    truncate_last_step,
)

__all__ = [
    "DATA_SOURCE",
    "IMAGINED",
    "REAL",
    "HorizonSchedule",
    "ImaginationSettings",
    "ModelBasedCollector",
    "RealEpochCollector",
    "ShutdownCompleteMultiSyncCollector",
    "StoppingRule",
    "epoch_seed",
    "is_imagined",
    "transitions",
    "truncate_last_step",
]
