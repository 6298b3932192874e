"""``SleepingParallelEnv``: TorchRL's ``ParallelEnv`` whose parent sleeps while workers step.

TorchRL 0.14's shared-memory ``ParallelEnv`` has the parent spin-poll a byte per worker
until the step is done. That saves a syscall when there are spare cores, but on a 2-core
machine running 2 workers the spinning parent takes a core from them: measured by
``benchmarks/env_throughput.py``, the parent used about 0.9 of a core and two workers ran
at about 0.9x one process. This class only changes that wait: the parent checks the same
flags and sleeps between checks, so both cores step robots. Everything else (buffers,
partial steps, resets) is TorchRL's.
"""

from __future__ import annotations

import time

from torchrl.envs import ParallelEnv

# Polling starts near the expected end of a step; a 0.1 ms poll then adds ~0.05 ms to it.
DEFAULT_POLL_INTERVAL = 1e-4
# Longer steps poll less often: every 1% of the typical wait, so the delay a poll adds stays
# about 0.5% of a step while the parent wakes (and takes CPU from the workers) less.
POLL_FRACTION_OF_WAIT = 0.01
# Seconds between checks that the workers are alive and within the timeout.
HEALTH_CHECK_INTERVAL = 1.0
# Share of the last wait slept in one go before polling starts.
EXPECTED_WAIT_FRACTION = 0.8


class SleepingParallelEnv(ParallelEnv):
    """A ``ParallelEnv`` for machines with no core to spare beyond its workers.

    Takes ``poll_interval`` (the shortest time in seconds between checks of the workers'
    done flags) and every argument of :class:`torchrl.envs.ParallelEnv`.
    """

    def __init__(self, *args, poll_interval: float = DEFAULT_POLL_INTERVAL, **kwargs):
        if not poll_interval > 0:
            raise ValueError(f"poll_interval must be positive seconds, got {poll_interval!r}")
        self.poll_interval = float(poll_interval)
        self._typical_wait = 0.0
        super().__init__(*args, **kwargs)

    def _wait_for_workers(self, workers_range):
        flags = getattr(self, "_shm_done_flags", None)
        if not self._use_buffers or flags is None:
            return super()._wait_for_workers(workers_range)
        workers = [(i, self._worker_indices[i]) for i in workers_range]
        started = time.monotonic()
        next_health_check = started + HEALTH_CHECK_INTERVAL
        # Steps take about as long as the last one: sleep through most of that in one go,
        # then poll, so the parent wakes a few times per step instead of hundreds.
        if self._typical_wait > 0:
            time.sleep(EXPECTED_WAIT_FRACTION * self._typical_wait)
        poll_interval = max(self.poll_interval, POLL_FRACTION_OF_WAIT * self._typical_wait)
        while not all(flags[index] for _, index in workers):
            time.sleep(poll_interval)
            now = time.monotonic()
            if now < next_health_check:
                continue
            next_health_check = now + HEALTH_CHECK_INTERVAL
            if now - started > self.BATCHED_PIPE_TIMEOUT:
                raise RuntimeError(
                    f"workers did not finish within {self.BATCHED_PIPE_TIMEOUT} s "
                    "(raise it with the BATCHED_PIPE_TIMEOUT environment variable)"
                )
            for worker, index in workers:
                if not flags[index] and not self._workers[worker].is_alive():
                    try:  # TorchRL's shutdown can itself fail while the other workers exit
                        self._shutdown_workers()
                    finally:
                        raise RuntimeError(f"ParallelEnv worker {worker} died")
        for _, index in workers:
            flags[index] = 0
        # Falls at once to a shorter wait, rises slowly after a long one (a reset that
        # rebuilds robots), so one slow command does not make the next steps oversleep.
        wait = time.monotonic() - started
        self._typical_wait = min(wait, 0.9 * self._typical_wait + 0.1 * wait)
