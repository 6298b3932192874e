"""Fitting world models on real transitions: one call, one report, one train/validation split.

:class:`ModelTrainer` fits a :class:`~unipolicy_rl.world_models.dynamics.NeuralDynamics`, kept
apart from the model as mbrl-lib's ``ModelTrainer`` is: the model only predicts and scores; the
trainer splits the data, standardises it, runs the epochs, keeps each member's best weights on
validation data (early stopping with patience) and tells the model its validation errors so it
can pick elites. :class:`ClosedFormTrainer` fits a model that owns its closed-form fit (the
polynomial-chaos models): it splits the data the same way and calls the model's ``fit``.
Both return a :class:`FitReport`.
"""

from __future__ import annotations

import contextlib
import math
import time
from collections.abc import Iterator, Mapping
from dataclasses import dataclass, field
from typing import Protocol

import torch
from tensordict import TensorDictBase

from unipolicy_rl.cpu_speed.fused_adam import adam
from unipolicy_rl.world_models.dynamics import Dynamics, NeuralDynamics, learned_outputs

# Keys of a transition batch (one real step each), as the replay buffer stores them.
TRANSITION_KEYS = ("state", "action", "design", "next_state")
# Marks a transition that began an episode (the buffer keeps each epoch's episodes whole and in order).
EPISODE_START = "episode_start"
# ModelTrainer.precision: the autocast dtype of a fit's training steps (None: none, float32 throughout);
# "auto" is bfloat16 where the fit runs on a CPU with bfloat16 instructions, float32 elsewhere (fit_dtype).
PRECISIONS = {"float32": None, "bfloat16": torch.bfloat16, "auto": None}


def native_bfloat16(device: torch.device | str) -> bool:
    """Whether ``device`` is a CPU that computes in bfloat16 itself (AVX512-BF16 or AMX): there a
    bfloat16 fit step takes about 0.7x a float32 one; where autocast emulates them, about 3x."""
    if torch.device(device).type != "cpu":
        return False
    checks = (getattr(torch.cpu, "_is_avx512_bf16_supported", None), getattr(torch.cpu, "_is_amx_tile_supported", None))
    return any(check is not None and check() for check in checks)


def fit_dtype(precision: str, device: torch.device | str) -> torch.dtype | None:
    """The autocast dtype ``precision`` gives a fit on ``device`` (None: float32 throughout)."""
    if precision == "auto":
        return torch.bfloat16 if native_bfloat16(device) else None
    return PRECISIONS[precision]


@dataclass
class FitReport:
    """What one fit did: epochs run, last training loss, each member's best validation error
    (standardised MSE), the elites, the members that had no data (a thesis cell not visited),
    the wall time, and figures only some models have (``extras``, logged under their own names,
    e.g. a closed-form fit's ``solve_fallbacks``)."""

    epochs: int
    train_loss: float
    validation_error: torch.Tensor
    elites: list[int]
    members_without_data: int
    seconds: float
    extras: Mapping[str, float] = field(default_factory=dict)

    def as_metrics(self, prefix: str = "model/") -> dict[str, float]:
        trained = self.validation_error[torch.isfinite(self.validation_error)]
        elite_error = self.validation_error[self.elites]
        return {
            f"{prefix}fit_epochs": float(self.epochs),
            f"{prefix}train_loss": self.train_loss,
            f"{prefix}validation_mse": float(elite_error[torch.isfinite(elite_error)].mean()) if trained.numel() else
            math.nan,
            f"{prefix}members_without_data": float(self.members_without_data),
            f"{prefix}fit_seconds": self.seconds,
            **{f"{prefix}{name}": float(value) for name, value in self.extras.items()},
        }


class Trainer(Protocol):
    """Fits a model in place on transitions (keys :data:`TRANSITION_KEYS`, batch ``[N]``)."""

    def fit(self, model: Dynamics, transitions: TensorDictBase, generator: torch.Generator | None = None) -> FitReport:
        ...


def split_transitions(n: int, validation_fraction: float,
                      generator: torch.Generator | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """``(train, validation)`` row indices of ``n`` transitions: a random ``validation_fraction``
    (at least one row) held out. Every trainer splits here, so their held-out errors compare."""
    if n < 2:
        raise ValueError(f"need at least 2 transitions to fit and validate a model, got {n}")
    order = torch.randperm(n, generator=generator)
    n_validation = max(1, round(validation_fraction * n))
    return order[n_validation:], order[:n_validation]


def check_validation_fraction(fraction: float) -> None:
    if not 0 < fraction < 1:
        raise ValueError(f"validation_fraction must lie in (0, 1), got {fraction!r}")


@dataclass(frozen=True)
class ModelTrainer:
    """Adam on minibatches, all members at once, early stopping on each member's validation error.

    Args:
        learning_rate: Adam step size. A fresh Adam starts every fit (the weights carry over
            from the previous fit), so a checkpoint needs no optimiser state.
        batch_size: samples per member per step.
        max_epochs: upper bound on passes over the training data per fit.
        max_steps: upper bound on gradient steps per fit (None: whole epochs only). The weights
            carry over between fits, so a fit has only the latest epoch's transitions to take in:
            a budget in steps keeps its time flat as the buffer grows, where a budget in passes
            over the buffer grows with it (docs/results.md, "The league").
        check_every: gradient steps between validation checks (None: one check per epoch).
            Early stopping then counts checks, not epochs: a warm model that has little new to
            learn stops after ``patience`` checks, however large the buffer, while a fit with
            much to learn goes on.
        validation_rows: validation samples per member a check reads, at most (None: all of
            them). The held-out share grows with the buffer (12,000 rows per member at 60,000
            transitions), and a check over all of it costs about 20 gradient steps: with checks
            every ``check_every`` steps that is what keeps a fit's time growing with the buffer.
            A fixed random subset of this size, drawn once per fit, keeps each check's cost flat.
        patience: stop after this many checks in which no member improved its validation
            error by more than ``min_improvement`` (relative).
        validation_fraction: share of the transitions held out (thesis: 80/20).
        weight_decay: Adam's L2 penalty.
        num_threads: torch threads during a fit (then restored), or None to leave them. A
            training run keeps one thread per process (its collector workers would contend
            otherwise), but the workers sit idle while the model fits, so the fit may use
            every core.
        precision: ``"float32"``, or ``"bfloat16"`` for the training steps' forward and backward
            passes under autocast (the weights, Adam's state, the loss's last steps and every
            validation check stay float32), or ``"auto"``: bfloat16 where the fit runs on a CPU
            with bfloat16 instructions (:func:`native_bfloat16`), float32 elsewhere. The fit is
            about half of a model-based epoch's work; on CPUs with those instructions a bfloat16
            training step took 0.68-0.73x a float32 one at the same validation error
            (``benchmarks/fit_precision.py``, docs/results.md); without them, about 3x.
            The report's ``fit_bfloat16`` extra says which ran.
    """

    learning_rate: float = 1e-3
    batch_size: int = 256
    max_epochs: int = 30
    max_steps: int | None = None
    check_every: int | None = None
    validation_rows: int | None = None
    patience: int = 3
    min_improvement: float = 0.01
    validation_fraction: float = 0.2
    weight_decay: float = 0.0
    num_threads: int | None = None
    precision: str = "float32"

    def __post_init__(self) -> None:
        if self.precision not in PRECISIONS:
            raise ValueError(f"precision must be one of {sorted(PRECISIONS)}, got {self.precision!r}")
        for name in ("learning_rate", "min_improvement"):
            if not getattr(self, name) > 0:
                raise ValueError(f"{name} must be positive, got {getattr(self, name)!r}")
        for name in ("batch_size", "max_epochs", "patience"):
            value = getattr(self, name)
            if not (isinstance(value, int) and value >= 1):
                raise ValueError(f"{name} must be a positive integer, got {value!r}")
        for name in ("max_steps", "check_every", "validation_rows"):
            value = getattr(self, name)
            if value is not None and not (isinstance(value, int) and not isinstance(value, bool) and value >= 1):
                raise ValueError(f"{name} must be a positive integer or None, got {value!r}")
        check_validation_fraction(self.validation_fraction)
        if not self.weight_decay >= 0:
            raise ValueError(f"weight_decay must be >= 0, got {self.weight_decay!r}")
        check_num_threads(self.num_threads)

    def fit(self, model: NeuralDynamics, transitions: TensorDictBase,
            generator: torch.Generator | None = None) -> FitReport:
        """Fits ``model`` in place on ``transitions`` (keys :data:`TRANSITION_KEYS`, batch ``[N]``)."""
        with torch_threads(self.num_threads):
            return self._fit(model, transitions, generator)

    def _fit(self, model: NeuralDynamics, transitions: TensorDictBase,
             generator: torch.Generator | None) -> FitReport:
        started = time.perf_counter()
        transitions = transitions.reshape(-1)
        # Index sets are built on the CPU, then moved.
        train, validation = split_transitions(transitions.batch_size[0], self.validation_fraction, generator)
        device = model.device
        state, action, design, next_state = (transitions.get(key).float().to(device) for key in TRANSITION_KEYS)
        inputs = model.inputs(state, action, design)
        targets = learned_targets(model, model.targets(state, next_state), transitions)
        model.fit_normalizers(inputs[train], targets[train])
        with torch.no_grad():
            x, y = model.input_norm(inputs), model.target_norm(targets)
        owners = model.data_members(design)
        owners = None if owners is None else owners.cpu()
        train_sets = _member_sets(owners, train, model.members)
        has_data = torch.tensor([len(s) > 0 for s in train_sets], device=device)
        validation_sets = _member_sets(owners, validation, model.members)
        if self.validation_rows is not None:
            validation_sets = [_subset(rows, self.validation_rows, generator) for rows in validation_sets]
        validation_index, validation_mask = (t.to(device) for t in _padded(validation_sets))

        optimizer = adam(model.parameters(), lr=self.learning_rate, weight_decay=self.weight_decay)
        dtype = fit_dtype(self.precision, device)
        autocast = (contextlib.nullcontext if dtype is None
                    else lambda: torch.autocast(device_type=device.type, dtype=dtype))
        member_parameters = model.member_parameters()
        best_weights = [p.detach().clone() for p in member_parameters]
        best_error = torch.full((model.members,), math.inf, device=device)
        checks_without_improvement = 0
        epochs_run = steps = 0
        train_loss = math.nan
        losses: list[torch.Tensor] = []
        budget = math.inf if self.max_steps is None else self.max_steps
        minibatches = _minibatches(train_sets, self.batch_size, self.max_epochs, generator)
        for epochs_run, chunk, epoch_end in minibatches:  # noqa: B007 (the count is reported)
            chunk = chunk.to(device)
            with autocast():
                per_sample = model.training_loss(x[chunk], y[chunk])  # [members, batch]
            loss = (per_sample.mean(1) * has_data).sum() + model.regularization()
            optimizer.zero_grad(set_to_none=True)
            loss.backward()
            optimizer.step()
            losses.append(loss.detach())
            steps += 1
            out_of_steps = steps >= budget or (epoch_end and epochs_run == self.max_epochs)
            if not (out_of_steps or (epoch_end if self.check_every is None else steps % self.check_every == 0)):
                continue
            # ---- a check: each member's validation error; the best weights so far are kept
            train_loss = float(torch.stack(losses).mean()) / max(int(has_data.sum()), 1)
            losses = []
            error = _masked_mean(model.validation_error(x[validation_index], y[validation_index]), validation_mask)
            improved = error < best_error - self.min_improvement * best_error.abs()
            improved |= torch.isinf(best_error) & torch.isfinite(error)
            if improved.any():
                best_error = torch.where(improved, error, best_error)
                with torch.no_grad():
                    for kept, parameter in zip(best_weights, member_parameters, strict=True):
                        kept[improved] = parameter[improved]
                checks_without_improvement = 0
            else:
                checks_without_improvement += 1
            if out_of_steps or checks_without_improvement >= self.patience:
                break
        with torch.no_grad():
            for kept, parameter in zip(best_weights, member_parameters, strict=True):
                parameter.copy_(kept)
        model.set_elites(best_error)
        return FitReport(epochs_run, train_loss, best_error.cpu(), model.elite_members, int((~has_data).sum()),
                         time.perf_counter() - started,
                         extras={"fit_steps": float(steps), "fit_bfloat16": float(dtype is torch.bfloat16)})


def learned_targets(model: NeuralDynamics, targets: torch.Tensor, transitions: TensorDictBase) -> torch.Tensor:
    """``targets`` with a column per output the model learns beside the state (its
    ``learned_outputs``: the transitions' ``reward``, ``terminated``), in that order."""
    names = learned_outputs(model)
    if not names:
        return targets
    missing = [name for name in names if name not in transitions.keys()]
    if missing:
        raise ValueError(f"{type(model).__name__} learns {list(names)} but the transitions hold no {missing}: "
                         f"keep them in the replay buffer (TransitionBuffer.for_model)")
    columns = [transitions.get(name).reshape(-1, 1).to(targets) for name in names]
    return torch.cat([targets, *columns], dim=-1)


def _minibatches(train_sets: list[torch.Tensor], batch_size: int, epochs: int,
                 generator: torch.Generator | None) -> Iterator[tuple[int, torch.Tensor, bool]]:
    """``(epoch, index [members, batch], last of its epoch)`` for up to ``epochs`` passes, each
    in its own order (drawn when the pass starts)."""
    for epoch in range(1, epochs + 1):
        chunks = _epoch_order(train_sets, generator).split(batch_size, dim=1)
        for number, chunk in enumerate(chunks, start=1):
            yield epoch, chunk, number == len(chunks)


class ClosedFormModel(Protocol):
    """A :class:`~unipolicy_rl.world_models.dynamics.Dynamics` that owns its closed-form fit."""

    def fit(self, transitions: TensorDictBase, train: torch.Tensor, validation: torch.Tensor,
            oversampling: float, generator: torch.Generator | None = None) -> FitReport:
        ...


@dataclass(frozen=True)
class ClosedFormTrainer:
    """Fits a model that owns its closed-form fit (the polynomial-chaos models): the same call and
    report as :class:`ModelTrainer`, the same split, then the model's own ``fit``.

    Args:
        validation_fraction: share of the transitions held out.
        oversampling: training samples per fitted term, at least (least-squares PCE wants 2-3 for
            random inputs; a policy's correlated data want more).
        num_threads: torch threads during a fit (then restored), or None to leave them.
    """

    validation_fraction: float = 0.2
    oversampling: float = 2.0
    num_threads: int | None = None

    def __post_init__(self) -> None:
        check_validation_fraction(self.validation_fraction)
        if not self.oversampling >= 1:
            raise ValueError(f"oversampling must be >= 1 (samples per term), got {self.oversampling!r}")
        check_num_threads(self.num_threads)

    def fit(self, model: ClosedFormModel, transitions: TensorDictBase,
            generator: torch.Generator | None = None) -> FitReport:
        """Fits ``model`` in place on ``transitions`` (keys :data:`TRANSITION_KEYS`, batch ``[N]``)."""
        transitions = transitions.reshape(-1)
        train, validation = split_transitions(transitions.batch_size[0], self.validation_fraction, generator)
        with torch_threads(self.num_threads):
            return model.fit(transitions, train, validation, self.oversampling, generator)


@contextlib.contextmanager
def torch_threads(count: int | None):
    """Runs the block with ``count`` torch threads (None: as they are), then restores them."""
    threads = torch.get_num_threads()
    torch.set_num_threads(count or threads)
    try:
        yield
    finally:
        torch.set_num_threads(threads)


def check_num_threads(count: int | None) -> None:
    if count is not None and not (isinstance(count, int) and not isinstance(count, bool) and count >= 1):
        raise ValueError(f"num_threads must be a positive integer or None, got {count!r}")


def _member_sets(owners: torch.Tensor | None, rows: torch.Tensor, members: int) -> list[torch.Tensor]:
    """The sample indices each member trains (or validates) on, out of ``rows``."""
    if owners is None:
        return [rows] * members
    row_owners = owners[rows]
    return [rows[row_owners == member] for member in range(members)]


def _subset(rows: torch.Tensor, size: int, generator: torch.Generator | None) -> torch.Tensor:
    """``size`` of ``rows`` drawn without replacement (all of them, in order, if there are no more)."""
    if len(rows) <= size:
        return rows
    return rows[torch.randperm(len(rows), generator=generator)[:size]]


def _epoch_order(sets: list[torch.Tensor], generator: torch.Generator | None) -> torch.Tensor:
    """``[members, L]``: each member's samples shuffled, cycled to the longest set's length."""
    length = max(len(s) for s in sets)
    rows = []
    for samples in sets:
        if len(samples) == 0:
            rows.append(torch.zeros(length, dtype=torch.long))
            continue
        shuffled = samples[torch.randperm(len(samples), generator=generator)]
        rows.append(shuffled.repeat(math.ceil(length / len(samples)))[:length])
    return torch.stack(rows)


def _padded(sets: list[torch.Tensor]) -> tuple[torch.Tensor, torch.Tensor]:
    length = max(1, max(len(s) for s in sets))
    index = torch.zeros(len(sets), length, dtype=torch.long)
    mask = torch.zeros(len(sets), length, dtype=torch.bool)
    for member, samples in enumerate(sets):
        index[member, : len(samples)] = samples
        mask[member, : len(samples)] = True
    return index, mask


def _masked_mean(values: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """Mean over each member's own samples; inf for a member with none."""
    counts = mask.sum(1)
    total = torch.where(mask, values, torch.zeros_like(values)).sum(1)
    return torch.where(counts > 0, total / counts.clamp_min(1), torch.full_like(total, math.inf))
