"""Real-env data, one epoch of whole episodes per batch, labelled and reseeded per epoch.

Wraps TorchRL's ``Collector`` / ``MultiSyncCollector`` (built by
:func:`unipolicy_rl.factories.make_collector`) with the two things a resumable training run
needs from it: every epoch restarts its designs, action noise and robots from
``epoch_seed(seed, epoch)``, so an epoch is a function of the weights and statistics that
start it and a resumed run continues exactly; and a count of the real env steps used so far.

An off-policy learner may learn while the epoch is collected (``algo.update_every``): the
collector then yields the epoch in chunks of a few steps of every env, hands each chunk to the
learner, whose gradient steps change the policy that collects the next one, and still yields
the whole epoch, assembled, to the training loop.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterator

import torch
from tensordict import TensorDictBase
from torchrl.collectors import Collector, MultiSyncCollector
from torchrl.weight_update import MultiProcessWeightSyncScheme

from unipolicy_rl.seeding import epoch_seed

# Every batch a collector of this package yields says where its data came from.
DATA_SOURCE = "data_source"
REAL, IMAGINED = "real", "imagined"


def label(batch: TensorDictBase, source: str) -> TensorDictBase:
    batch.set_non_tensor(DATA_SOURCE, source)
    return batch


def is_imagined(batch: TensorDictBase) -> bool:
    return DATA_SOURCE in batch.keys() and batch.get_non_tensor(DATA_SOURCE) == IMAGINED


class RealEpochCollector:
    """Yields ``epochs`` real batches (``[robots, steps]``), labelled ``real``.

    Args:
        collector: a TorchRL collector whose every batch is one epoch of whole episodes or, with
            ``chunks_per_epoch``, one chunk of every env's steps (a single-process ``Collector``,
            whose policy is the learner's own).
        seed: the run's seed.
        epochs: the epoch to stop after (absolute: a resumed run starts at :attr:`epoch`).
        frames_per_batch: real env steps in one epoch.
        chunks_per_epoch: chunks the epoch is collected in, each handed to ``between_chunks``
            (None: the collector's batch is the epoch).
        between_chunks: called with each chunk (labelled ``real``) as it arrives: an off-policy
            learner's gradient steps on it, which the next chunk's actions then follow.
        postproc: applied to each assembled epoch (the chunked collector's batches are chunks,
            so it cannot apply the epoch's post-processing itself).
    """

    def __init__(self, collector: Collector | MultiSyncCollector, seed: int, epochs: int,
                 frames_per_batch: int, chunks_per_epoch: int | None = None,
                 between_chunks: Callable[[TensorDictBase], object] | None = None,
                 postproc: Callable[[TensorDictBase], TensorDictBase] | None = None) -> None:
        if chunks_per_epoch is not None and not (isinstance(chunks_per_epoch, int) and chunks_per_epoch >= 1):
            raise ValueError(f"chunks_per_epoch must be an integer >= 1 or None, got {chunks_per_epoch!r}")
        if chunks_per_epoch is not None and not isinstance(collector, Collector):
            raise ValueError(f"an epoch in {chunks_per_epoch} chunks needs the single-process Collector, whose "
                             f"policy the learner updates between chunks, not a {type(collector).__name__}")
        self.collector = collector
        self.seed = seed
        self.epochs = epochs
        self.frames_per_batch = frames_per_batch
        self.chunks_per_epoch = chunks_per_epoch
        self.between_chunks = between_chunks
        self.postproc = postproc
        self.epoch = 0
        self.real_env_steps = 0
        self.between_chunks_seconds = 0.0  # the last epoch's time in ``between_chunks``

    def __iter__(self) -> Iterator[TensorDictBase]:
        batches = iter(self.collector)
        while self.epoch < self.epochs:
            self._restart_randomness(self.epoch)
            batch = next(batches) if self.chunks_per_epoch is None else self._chunked_epoch(batches)
            if self.postproc is not None:
                batch = self.postproc(batch)
            self.epoch += 1
            self.real_env_steps += self.frames_per_batch
            yield label(batch, REAL)

    def _chunked_epoch(self, batches: Iterator[TensorDictBase]) -> TensorDictBase:
        """The epoch's chunks, each handed to ``between_chunks`` as it comes, joined along time."""
        chunks, self.between_chunks_seconds = [], 0.0
        for _ in range(self.chunks_per_epoch):
            chunk = next(batches).clone()  # the collector reuses its output's memory
            chunks.append(chunk)
            if self.between_chunks is not None:
                started = time.perf_counter()
                self.between_chunks(label(chunk.copy(), REAL))  # a shallow copy takes the label
                self.collector.update_policy_weights_()
                self.between_chunks_seconds += time.perf_counter() - started
        return torch.cat(chunks, dim=-1)  # the last batch dimension is time

    def _restart_randomness(self, epoch: int) -> None:
        # The multi-process collector seeds each worker's torch and resets its robots itself.
        seed = epoch_seed(self.seed, epoch)
        self.collector.set_seed(seed)
        if isinstance(self.collector, Collector):
            torch.manual_seed(seed)
            self.collector.reset()

    def metrics(self) -> dict[str, float]:
        return {"real_env_steps": float(self.real_env_steps)}

    def update_policy_weights_(self) -> None:
        self.collector.update_policy_weights_()

    def shutdown(self) -> None:
        self.collector.shutdown()

    def __enter__(self) -> RealEpochCollector:
        return self

    def __exit__(self, *exc_info) -> None:
        # Also on failure: else the interpreter waits for the worker processes forever on exit.
        self.shutdown()

    def state_dict(self) -> dict:
        return {"epoch": self.epoch, "real_env_steps": self.real_env_steps}

    def load_state_dict(self, state: dict) -> None:
        self.epoch = int(state["epoch"])
        self.real_env_steps = int(state["real_env_steps"])


class ShutdownCompleteMultiSyncCollector(MultiSyncCollector):
    """TorchRL's ``MultiSyncCollector`` whose ``shutdown`` also shuts its weight-sync scheme down.

    TorchRL 0.14 leaves that to the scheme's ``__del__``. When a run fails, the exception's
    traceback keeps the collector alive until the interpreter exits, the ``__del__`` then runs
    during finalisation, starts a queue thread, and the process hangs forever after printing
    its error. The scheme is the one TorchRL would make by default, made here so it can be
    closed with the collector.
    """

    def __init__(self, *args, **kwargs) -> None:
        schemes = kwargs.setdefault("weight_sync_schemes", {"policy": MultiProcessWeightSyncScheme()})
        super().__init__(*args, **kwargs)
        self._schemes_to_close = dict(schemes)

    def shutdown(self, *args, **kwargs) -> None:
        try:
            super().shutdown(*args, **kwargs)
        finally:
            for scheme in self._schemes_to_close.values():
                scheme.shutdown()


def truncate_last_step(batch: TensorDictBase) -> TensorDictBase:
    """Ends every trajectory at the batch's last step (truncated, not terminated), as a time
    limit would, so the value estimator bootstraps there. (TorchRL's own ``set_truncated``
    misses reused collector buffers.)"""
    for key in ("truncated", "done"):
        flags = batch.get(("next", key))
        flags[..., -1, :] = True
        batch.set(("next", key), flags)
    return batch
