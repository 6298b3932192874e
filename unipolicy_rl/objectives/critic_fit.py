"""Fitting the TRPO critic: Adam on the MSE to fixed value targets, over shuffled minibatches.

The policy moves by the natural gradient alone (:mod:`unipolicy_rl.objectives.natural_gradient`);
the critic is an ordinary regression, and this module keeps its many tiny steps cheap. Like the
policy step, a fit that meets a non-finite number is skipped and leaves the critic and its Adam
state as they were: one NaN target would otherwise poison both for the rest of the run.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable
from dataclasses import dataclass

import torch
from tensordict import TensorDictBase

from unipolicy_rl.cpu_speed.fused_adam import adam
from unipolicy_rl.cpu_speed.plain_mlp import PlainMLPRegression
from unipolicy_rl.objectives.trpo import TRPOLoss

__all__ = ["CriticFitResult", "explained_variance", "fit_critic", "make_critic_optimizer"]

@dataclass(frozen=True)
class CriticFitResult:
    """What one critic fit did.

    Attributes:
        fitted: whether the critic parameters (and the optimizer state) changed.
        skip_reason: ``None`` when fitted, otherwise why the fit was skipped.
        loss: mean minibatch loss (``critic_coeff * MSE``) over the fit (0 when skipped).
    """

    fitted: bool
    skip_reason: str | None
    loss: float = 0.0

    def as_metrics(self, prefix: str = "train/") -> dict[str, float]:
        """``loss_critic`` and ``critic_skipped`` (1.0 when skipped; the reason is dropped)."""
        return {prefix + "loss_critic": self.loss, prefix + "critic_skipped": float(not self.fitted)}


def make_critic_optimizer(loss_module: TRPOLoss, lr: float = 1e-3) -> torch.optim.Adam:
    """Adam over the critic parameters only (the policy moves by the natural gradient alone),
    on the fused kernel where there is one: with small networks and about a thousand minibatch
    steps per update, per-tensor optimizer overhead is a large share of the time."""
    return adam(loss_module.critic_parameters(), lr=lr)


def fit_critic(
    loss_module: TRPOLoss,
    batch: TensorDictBase,
    optimizer: torch.optim.Optimizer,
    epochs: int = 10,
    minibatch_size: int = 128,
    generator: torch.Generator | None = None,
) -> CriticFitResult:
    """Regress the critic on ``batch``'s value target by Adam over shuffled minibatches.

    The value target must already be in ``batch`` (written by the value estimator before
    this fit, so every minibatch regresses on the same fixed targets). Each epoch reshuffles
    the whole batch once and walks it in contiguous slices. The result carries the mean
    minibatch loss (``critic_coeff * MSE``) over the fit.

    Skipped, with the critic parameters and the optimizer state left bit for bit as they
    were, when a value target or critic input is non-finite (checked before any step), or
    when the fit ends with a non-finite loss, parameter or optimizer state (a non-finite
    gradient on the way always leaves one: Adam turns it into a NaN parameter or moment).
    The end-of-fit check costs one pass over the parameters instead of a check per step.

    This loop runs about a thousand tiny steps per update, so per-step overhead, not
    arithmetic, sets its speed: a critic that is a plain MLP gets its MSE gradient by a
    hand-written backward pass (:class:`unipolicy_rl.cpu_speed.plain_mlp.PlainMLPRegression`,
    checked against autograd in ``tests/test_trpo.py``); any other critic goes through
    :meth:`TRPOLoss.critic_loss` and autograd.
    """
    flat = batch.reshape(-1)
    count = flat.numel()
    critic = loss_module.critic_network
    target = flat.get(loss_module.tensor_keys.value_target).detach()
    if not _all_finite([target]):
        return CriticFitResult(False, "non-finite value target")
    if not _all_finite(flat.select(*critic.in_keys).values(True, True)):
        return CriticFitResult(False, "non-finite critic input")
    coeff = float(loss_module.critic_coeff)
    device = target.device
    total = torch.zeros((), device=device)
    steps = 0
    with loss_module.critic_network_params.to_module(critic), torch.no_grad():
        mlp = PlainMLPRegression.from_critic(loss_module)
        if mlp is not None:
            params = mlp.params
            inputs = flat.get(critic.in_keys[0])
        else:
            params = loss_module.critic_parameters()
            inputs = flat.select(*critic.in_keys)
        restore = _snapshot(params, optimizer)
        apply_gradients = _gradient_step_fn(optimizer, params)
        for _ in range(epochs):
            order = torch.randperm(count, generator=generator, device=generator.device if generator else device).to(
                device
            )
            shuffled_inputs, shuffled_target = inputs[order], target[order]
            for start in range(0, count, minibatch_size):
                end = start + minibatch_size
                if mlp is not None:
                    loss, grads = mlp.loss_and_grads(shuffled_inputs[start:end], shuffled_target[start:end], coeff)
                else:
                    minibatch = shuffled_inputs[start:end]
                    minibatch.set(loss_module.tensor_keys.value_target, shuffled_target[start:end])
                    with torch.enable_grad():
                        loss = loss_module.critic_loss(minibatch)
                        grads = list(torch.autograd.grad(loss, params))
                apply_gradients(grads)
                total += loss.detach()
                steps += 1
        if not _all_finite([total, *params, *_state_tensors(optimizer)]):
            restore()
            return CriticFitResult(False, "non-finite critic loss or gradient")
    return CriticFitResult(True, None, float(total / max(steps, 1)))


def explained_variance(prediction: torch.Tensor, target: torch.Tensor) -> float:
    """``1 - Var(target - prediction) / Var(target)``: the share of the target's variance a critic's
    prediction explains (1: exact; 0: no better than the target's mean). The TRPO update logs it
    for the critic before its fit (``train/explained_variance``).

    0.0 where it is undefined (fewer than two samples, a constant target, or a non-finite
    value, which the critic fit reports by skipping), so the metrics stay finite for loggers
    and NaN checks.
    """
    target = target.reshape(-1)
    variance = target.var(correction=0)
    if target.numel() < 2 or variance == 0:
        return 0.0
    residual = target - prediction.reshape(-1)
    explained = float(1.0 - residual.var(correction=0) / variance)
    return explained if math.isfinite(explained) else 0.0


def _all_finite(tensors: Iterable[torch.Tensor]) -> bool:
    """Whether every floating-point element of ``tensors`` is finite (others are skipped)."""
    return all(bool(torch.isfinite(t).all()) for t in tensors if t.is_floating_point())


def _state_tensors(optimizer: torch.optim.Optimizer) -> list[torch.Tensor]:
    """Every tensor in the optimizer's per-parameter state (Adam: moments and step counts)."""
    return [value for state in optimizer.state.values() for value in state.values() if torch.is_tensor(value)]


def _snapshot(params: list[torch.Tensor], optimizer: torch.optim.Optimizer) -> Callable[[], None]:
    """A ``restore()`` that puts ``params`` and ``optimizer``'s state back as they are now.

    Parameters are copied back in place (the modules keep their tensors); the optimizer state
    is restored by entry, and state the fit created (a fresh optimizer's first step) is dropped.
    """
    saved_params = [param.detach().clone() for param in params]
    saved_state = {
        param: {name: value.clone() if torch.is_tensor(value) else value for name, value in state.items()}
        for param, state in optimizer.state.items()
    }

    def restore() -> None:
        with torch.no_grad():
            for param, saved in zip(params, saved_params, strict=True):
                param.copy_(saved)
        for param in list(optimizer.state):
            if param not in saved_state:
                del optimizer.state[param]
        optimizer.state.update(saved_state)

    return restore


def _gradient_step_fn(
    optimizer: torch.optim.Optimizer, params: list[torch.Tensor]
) -> Callable[[list[torch.Tensor]], None]:
    """``grads -> None``: one ``optimizer.step()`` with ``grads`` for ``params`` (the critic's Adam
    is torch's fused kernel where there is one: :func:`unipolicy_rl.cpu_speed.fused_adam.adam`)."""

    def optimizer_step(grads: list[torch.Tensor]) -> None:
        for param, grad in zip(params, grads, strict=True):
            param.grad = grad
        optimizer.step()
        for param in params:
            param.grad = None

    return optimizer_step
