"""``SleepingParallelEnv`` lives in :mod:`unipolicy_rl.cpu_speed.parallel_env`; this name stays for scripts
that import it from here."""

from unipolicy_rl.cpu_speed.parallel_env import HEALTH_CHECK_INTERVAL, SleepingParallelEnv, WakingDoneFlags

__all__ = ["HEALTH_CHECK_INTERVAL", "SleepingParallelEnv", "WakingDoneFlags"]
