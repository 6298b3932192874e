"""A training run's infrastructure, apart from the algorithm: its metrics file, its stop signals,
the lock that keeps two runs out of one folder, and the CPU seconds its processes spend.

Light on purpose: the report and the evaluation read metrics.csv through
:mod:`unipolicy_rl.training.metrics_file`, so nothing here may import collectors, world models
or objectives.
"""

from unipolicy_rl.training.cpu_time import process_tree_cpu_seconds
from unipolicy_rl.training.metrics_file import MetricsCSV
from unipolicy_rl.training.run_lock import RunFolderInUse, RunLock
from unipolicy_rl.training.signals import StopAtEpochEnd

__all__ = ["MetricsCSV", "RunFolderInUse", "RunLock", "StopAtEpochEnd", "process_tree_cpu_seconds"]
