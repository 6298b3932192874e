"""The critic fit beside the next update: on a forked process of its own (``algo.critic_fit=process``).

A model-based epoch runs twenty imagined updates one after the other, and about half of each is
the critic fit (hundreds of small Adam steps), while a run that is alone on a machine leaves its
second core idle. The next update's rollout, advantages and policy step need the policy, not the
freshly fitted critic, so the fit of update ``k`` can run beside update ``k + 1`` if update ``k + 1``
computes its advantages with the critic fitted through update ``k - 1``: the critic lags the policy
by one update (``algo.critic_fit=lagged`` is the same learning in one process; a probe of it reached
SE-TRPO's final level after as few real env steps as the default on two seeds, docs/results.md).
A thread cannot do this here: both sides are many small operations whose Python holds the GIL.

The fit itself is the caller's (``fit``: :func:`unipolicy_rl.objectives.critic_fit.fit_critic`), so
the child runs exactly what ``algo.critic_fit=lagged`` runs in one process (``tests/test_critic_fit.py``
compares the two); this module only moves it onto a fork.

The child is a fork of the parent at its first fit, so it starts from the parent's critic, its Adam
optimizer and the fit's generator, and owns them from then on; the parent keeps the critic's weights
up to date from each finished fit, and pushes them back after it changes them itself (a normaliser
refresh that re-expresses the critic's first layer). Checkpoints read the optimizer and generator
from the child.
"""

from __future__ import annotations

import multiprocessing
import signal
import traceback
import weakref
from collections.abc import Callable

import torch
from tensordict import TensorDictBase
from torchrl.objectives import LossModule

__all__ = ["CriticFitProcess"]

# What a terminal's Ctrl-C, `timeout` or a scheduler send to a whole process group.
STOP_SIGNALS = {signal.SIGINT, signal.SIGTERM}


class CriticFitProcess:
    """``fit`` (the critic fit) on a forked child process, one fit at a time.

    ``start_fit(batch)`` sends a batch (its critic inputs and value targets) and returns at once;
    ``finish()`` waits for that fit, copies the fitted weights into the parent's critic and returns
    ``fit``'s result. ``push_weights()`` sends the parent's critic weights to the child;
    ``optimizer_state()`` / ``load_optimizer_state()`` move the Adam state and the generator's once
    the child has started.

    Args:
        fit: ``fit(loss, batch, optimizer, epochs, minibatch_size, generator) -> result``, the critic
            fit run in the child (its result is picklable).
        loss: the updater's loss (its critic is the one fitted; ``critic_parameters()``).
        optimizer: the critic's Adam optimizer (the child takes it over at the fork).
        epochs, minibatch_size: passed to ``fit``.
        generator: the fit's shuffling generator (the child takes it over at the fork).
    """

    def __init__(self, fit: Callable, loss: LossModule, optimizer: torch.optim.Optimizer, epochs: int,
                 minibatch_size: int, generator: torch.Generator | None) -> None:
        self.fit = fit
        self.loss, self.optimizer, self.generator = loss, optimizer, generator
        self.epochs, self.minibatch_size = epochs, minibatch_size
        self.pending = False
        self._connection = None
        self._process = None

    @property
    def started(self) -> bool:
        return self._process is not None

    def start_fit(self, batch: TensorDictBase) -> None:
        if self.pending:
            raise RuntimeError("a critic fit is still pending: finish() it first")
        keys = self.loss.tensor_keys
        critic_batch = batch.select(*self.loss.critic_network.in_keys, keys.value_target)  # (sending copies it)
        self._start()
        self._connection.send(("fit", critic_batch))
        self.pending = True

    def finish(self):
        if not self.pending:
            raise RuntimeError("no critic fit is pending")
        self.pending = False
        result, weights = self._receive()
        with torch.no_grad():
            for parameter, fitted in zip(self.loss.critic_parameters(), weights, strict=True):
                parameter.copy_(fitted)
        return result

    def push_weights(self) -> None:
        """The parent's critic weights to the child (after the parent changed them)."""
        if self.started:
            self._call("weights", [p.detach().clone() for p in self.loss.critic_parameters()])

    def optimizer_state(self) -> tuple[dict, torch.Tensor | None]:
        """The child's critic optimizer ``state_dict`` and generator state (before the child starts,
        the parent's own are the ones it will inherit)."""
        return self._call("state", None)

    def load_optimizer_state(self, optimizer_state: dict, generator_state: torch.Tensor | None) -> None:
        self._call("load_state", (optimizer_state, generator_state))

    def close(self) -> None:
        if self._process is not None:
            self._closer()
            self._process = self._connection = None
        self.pending = False

    def _start(self) -> None:
        if self._process is not None:
            return
        context = multiprocessing.get_context("fork")
        parent, child = context.Pipe()
        # daemon: the child ends with the parent, however the parent ends
        self._process = context.Process(target=_serve, daemon=True, name="critic-fit",
                                        args=(child, self.fit, self.loss, self.optimizer, self.epochs,
                                              self.minibatch_size, self.generator))
        # The child starts with the stop signals blocked, so none reaches it before _serve ignores them.
        unblocked = signal.pthread_sigmask(signal.SIG_BLOCK, STOP_SIGNALS)
        try:
            self._process.start()
        finally:
            signal.pthread_sigmask(signal.SIG_SETMASK, unblocked)
        child.close()
        self._connection = parent
        # Ended by close(), or at the latest when the interpreter exits: before multiprocessing's own
        # exit handler, which would SIGTERM the child (ignored: _serve) and then wait on it forever.
        self._closer = weakref.finalize(self, _end_child, self._process, parent)

    def _call(self, command: str, payload):
        if self.pending:
            raise RuntimeError(f"{command}: a critic fit is still pending: finish() it first")
        self._connection.send((command, payload))
        return self._receive()

    def _receive(self):
        status, payload = self._connection.recv()
        if status == "error":
            raise RuntimeError(f"the critic fit process failed:\n{payload}")
        return payload

    def __del__(self) -> None:
        self.close()


def _end_child(process: multiprocessing.process.BaseProcess, connection) -> None:
    """Asks the child to stop, waits a little, kills it if it is still there."""
    try:
        connection.send(("close", None))
    except (BrokenPipeError, OSError):
        pass
    process.join(timeout=5)
    if process.is_alive():
        process.kill()
        process.join()
    connection.close()


def _serve(connection, fit: Callable, loss: LossModule, optimizer: torch.optim.Optimizer, epochs: int,
           minibatch_size: int, generator: torch.Generator | None) -> None:
    """The child's loop: fits, weight and state exchanges, until ``close``.

    Ctrl-C and a scheduler's SIGTERM reach the whole process group; the training process decides
    what they mean (stop after the epoch), so the child, a fork that would otherwise share its
    handler or die mid-fit, ignores them. It ends on ``close``, on the parent's end of the pipe
    closing, or by SIGKILL."""
    for number in STOP_SIGNALS:
        signal.signal(number, signal.SIG_IGN)
    signal.pthread_sigmask(signal.SIG_UNBLOCK, STOP_SIGNALS)
    torch.set_num_threads(1)
    while True:
        try:
            command, payload = connection.recv()
        except EOFError:  # the parent is gone
            return
        if command == "close":
            connection.close()
            return
        try:
            if command == "fit":
                result = fit(loss, payload, optimizer, epochs, minibatch_size, generator)
                reply = (result, [p.detach().clone() for p in loss.critic_parameters()])
            elif command == "weights":
                with torch.no_grad():
                    for parameter, value in zip(loss.critic_parameters(), payload, strict=True):
                        parameter.copy_(value)
                reply = None
            elif command == "state":
                reply = (optimizer.state_dict(), None if generator is None else generator.get_state())
            elif command == "load_state":
                optimizer_state, generator_state = payload
                optimizer.load_state_dict(optimizer_state)
                if generator_state is not None:
                    generator.set_state(generator_state)
                reply = None
            else:
                raise ValueError(f"unknown command {command!r}")
            connection.send(("ok", reply))
        except Exception:  # noqa: BLE001 (reported to the parent, which raises it)
            connection.send(("error", traceback.format_exc()))
