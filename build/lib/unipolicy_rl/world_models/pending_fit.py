"""A world-model fit that may run on a second thread while the policy trains on the previous fit.

A model-based epoch spends most of its time in two parts that need not wait for each other: the
fit of the model on the replay buffer and the imagined policy updates. With
``imagination.background_fit`` the fit after epoch k runs on a copy of the model in a thread
while the policy trains on the model of the fit before (one epoch older); the fitted weights
replace the model's when the epoch's updates are done. Torch releases the interpreter lock inside
its operations, so on a machine with a core to spare the epoch takes about the longer of the two
instead of their sum (``docs/results.md``, "A fit beside the imagined updates").

The run stays reproducible: the fit draws only from its own generator, the imagined updates only
from their epoch's seed, and the weights change hands at the same point of every epoch, so
neither the thread's timing nor the machine's load changes a number (a resumed run, its
checkpoint written after the swap, repeats the straight one).
"""

from __future__ import annotations

import copy
import threading

import torch
from tensordict import TensorDictBase

from unipolicy_rl.world_models.dynamics import Dynamics
from unipolicy_rl.world_models.trainer import FitReport, Trainer


def check_background_fit(trainer: Trainer) -> None:
    """Refuses, by name, a trainer that sets torch's thread count for its fits: the count is the
    whole process's, so a fit in the background would change the policy updates' threads too."""
    threads = getattr(trainer, "num_threads", None)
    if threads is not None:
        raise ValueError(f"imagination.background_fit shares the process's torch threads between the fit and the "
                         f"policy's updates: set world_model.trainer.num_threads=null (got {threads!r}) or "
                         f"imagination.background_fit=false")


class PendingFit:
    """One fit of ``model`` on ``transitions``: done at once (``background=False``), or started on a
    thread on a copy of the model (``background=True``), the model itself left as it is until
    :meth:`result`.

    Args:
        trainer: fits the model (its ``num_threads`` must be None in the background: torch's
            thread count is shared by the whole process, the policy's updates included).
        model: the world model the imagination uses.
        transitions: the real transitions to fit on (read, never changed, by the fit).
        generator: the fit's random numbers (its split, minibatches and resamples).
        background: fit on a second thread.
    """

    def __init__(self, trainer: Trainer, model: Dynamics, transitions: TensorDictBase,
                 generator: torch.Generator | None, background: bool) -> None:
        if background:
            check_background_fit(trainer)
        self.model = model
        self._report: FitReport | None = None
        self._error: BaseException | None = None
        self._thread: threading.Thread | None = None
        if not background:
            self._report = trainer.fit(model, transitions, generator)
            return
        self._copy = copy.deepcopy(model)

        def fit() -> None:
            try:
                self._report = trainer.fit(self._copy, transitions, generator)
            except BaseException as error:  # raised again in the loop's thread, by result()
                self._error = error

        # A daemon: an interrupted run exits without waiting for a fit nobody will read.
        self._thread = threading.Thread(target=fit, name="world-model-fit", daemon=True)
        self._thread.start()

    def result(self) -> FitReport:
        """The fit's report, once the model holds the fitted weights (waits for a background fit;
        raises what it raised)."""
        if self._thread is not None:
            self._thread.join()
            self._thread = None
            if self._error is not None:
                raise self._error
            self.model.load_state_dict(self._copy.state_dict())
            del self._copy
        assert self._report is not None
        return self._report
