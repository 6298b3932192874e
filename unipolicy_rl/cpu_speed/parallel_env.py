"""``SleepingParallelEnv``: TorchRL's ``ParallelEnv`` whose parent sleeps while workers step.

TorchRL 0.14's shared-memory ``ParallelEnv`` has the parent spin-poll a byte per worker
until the step is done. That saves a syscall when there are spare cores, but on a 2-core
machine running 2 workers the spinning parent takes a core from them, and two workers ran
slower than one process (``benchmarks/env_throughput.py``; docs/results.md, "Environment
throughput"). This class changes only that wait. Each worker still sets its
done byte, and now also posts a semaphore; the parent blocks on the semaphores, so the
kernel wakes it the moment the last worker is done and it uses no CPU before. Everything
else (buffers, pipes, partial steps, resets) is TorchRL's.
"""

from __future__ import annotations

import multiprocessing
import time

from torchrl.envs import ParallelEnv

# Seconds a blocked parent waits before it checks that the workers are alive and within
# the timeout; a dead worker is reported this long after it dies, at most.
HEALTH_CHECK_INTERVAL = 1.0


class WakingDoneFlags:
    """TorchRL's per-worker done bytes, with a semaphore per worker posted on every "done".

    Workers write ``flags[i] = 1`` (TorchRL's own worker loop does this); the parent calls
    :meth:`wait`. The bytes stay the truth: a worker also signals done for commands the
    parent waits for another way (close, load_state_dict), which leaves extra posts on a
    semaphore, so a wake-up only means "look at the byte again".
    """

    def __init__(self, flags, context: multiprocessing.context.BaseContext):
        self.flags = flags
        self.semaphores = [context.Semaphore(0) for _ in range(len(flags))]

    def __getitem__(self, index: int) -> int:
        return self.flags[index]

    def __setitem__(self, index: int, value: int) -> None:
        self.flags[index] = value
        if value:
            self.semaphores[index].release()

    def wait(self, index: int, timeout: float) -> bool:
        """Blocks until worker ``index`` is done or ``timeout`` s pass; True when done."""
        deadline = time.monotonic() + timeout
        while not self.flags[index]:
            remaining = deadline - time.monotonic()
            if remaining <= 0 or not self.semaphores[index].acquire(timeout=remaining):
                return bool(self.flags[index])
        return True


class SleepingParallelEnv(ParallelEnv):
    """A ``ParallelEnv`` for machines with no core to spare beyond its workers.

    Takes every argument of :class:`torchrl.envs.ParallelEnv`. Relies on TorchRL 0.14's
    worker protocol (``_shm_done_flags``, ``_wait_for_workers``), hence the project's
    ``torchrl<0.15`` pin.
    """

    @property
    def _shm_done_flags(self) -> WakingDoneFlags | None:
        return self.__dict__.get("_waking_done_flags")

    @_shm_done_flags.setter
    def _shm_done_flags(self, flags) -> None:
        # TorchRL assigns a fresh byte array as it starts the workers and hands this
        # attribute to each of them: wrapping it here gives workers and parent the semaphores.
        if flags is not None and not isinstance(flags, WakingDoneFlags):
            context = multiprocessing.get_context(self._mp_start_method)
            flags = WakingDoneFlags(flags, context)
        self.__dict__["_waking_done_flags"] = flags

    def _wait_for_workers(self, workers_range):
        flags = self._shm_done_flags
        if not self._use_buffers or flags is None:
            return super()._wait_for_workers(workers_range)
        started = time.monotonic()
        for worker in workers_range:
            index = self._worker_indices[worker]
            while not flags.wait(index, HEALTH_CHECK_INTERVAL):
                if time.monotonic() - started > self.BATCHED_PIPE_TIMEOUT:
                    raise RuntimeError(
                        f"workers did not finish within {self.BATCHED_PIPE_TIMEOUT} s "
                        "(raise it with the BATCHED_PIPE_TIMEOUT environment variable)"
                    )
                if not self._workers[worker].is_alive():
                    try:  # TorchRL's shutdown can itself fail while the other workers exit
                        self._shutdown_workers()
                    finally:
                        raise RuntimeError(f"ParallelEnv worker {worker} died")
        for worker in workers_range:
            flags[self._worker_indices[worker]] = 0  # clearing posts nothing
