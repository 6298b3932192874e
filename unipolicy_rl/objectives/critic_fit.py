"""Fitting the TRPO critic: Adam on the MSE to fixed value targets, over shuffled minibatches.

The policy moves by the natural gradient alone (:mod:`unipolicy_rl.objectives.natural_gradient`);
the critic is an ordinary regression, and this module keeps its many tiny steps cheap. Like the
policy step, a fit that meets a non-finite number is skipped and leaves the critic and its Adam
state as they were: one NaN target would otherwise poison both for the rest of the run.
"""

from __future__ import annotations

import importlib
import inspect
import math
from collections.abc import Callable, Iterable
from dataclasses import dataclass

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModule
from torch import nn

from unipolicy_rl.objectives.trpo import TRPOLoss
from unipolicy_rl.optimizers import adam

__all__ = ["CriticFitResult", "explained_variance", "fit_critic", "make_critic_optimizer"]

# Private: ``torch.optim.adam.adam``, Adam's functional kernel (not re-exported by torch.optim).
# Its positional parameters have grown and moved between torch releases, so the fast path calls
# it with keywords only, after checking that its signature binds them (:func:`_adam_kernel_for`);
# otherwise the fit steps the optimizer by its public ``step()``.
_ADAM_KERNEL: Callable[..., None] | None = getattr(importlib.import_module("torch.optim.adam"), "adam", None)


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
    arithmetic, sets its speed. Two fast paths, each checked against the plain path in
    ``tests/test_trpo.py``, keep it low:

    * a critic that is a plain MLP (``nn.Sequential`` of ``nn.Linear`` and tanh/ReLU, as
      :func:`unipolicy_rl.networks.make_critic` builds) gets its MSE gradient by a
      hand-written backward pass, on tensors, with no TensorDict or autograd bookkeeping;
      any other critic goes through :meth:`TRPOLoss.critic_loss` and autograd;
    * a plain ``torch.optim.Adam`` is applied through torch's private functional kernel on
      the optimizer's own state, skipping ``Optimizer.step``'s per-call bookkeeping; any
      other optimizer, or a torch whose kernel signature differs, is stepped normally.
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
        mlp = _PlainMLPRegression.from_critic(loss_module)
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


class _PlainMLPRegression:
    """MSE loss and its gradient for a ``Linear -> act -> ... -> Linear`` critic, by hand.

    Autograd records and replays about twenty small nodes per minibatch; for a critic of this
    one known shape the backward pass is a few matrix products, written out below.
    """

    _ACTIVATIONS = (nn.Tanh, nn.ReLU)

    def __init__(self, linears: list[nn.Linear], activations: list[nn.Module]) -> None:
        self.linears = linears
        self.tanh = [isinstance(activation, nn.Tanh) for activation in activations]  # else ReLU
        self.params = [t for layer in linears for t in (layer.weight, layer.bias)]

    @classmethod
    def from_critic(cls, loss_module: TRPOLoss) -> _PlainMLPRegression | None:
        """The fast path for ``loss_module``'s critic, or ``None`` if it is not a plain MLP."""
        critic = loss_module.critic_network
        if not (
            isinstance(critic, TensorDictModule)
            and len(critic.in_keys) == 1
            and list(critic.out_keys) == [loss_module.tensor_keys.value]
            and isinstance(critic.module, nn.Sequential)
        ):
            return None
        layers = list(critic.module)
        linears, activations = layers[0::2], layers[1::2]
        if (
            len(layers) % 2 == 0
            or not all(type(layer) is nn.Linear and layer.bias is not None for layer in linears)
            or not all(type(act) in cls._ACTIVATIONS for act in activations)
        ):
            return None
        mlp = cls(linears, activations)
        critic_params = loss_module.critic_parameters()
        if {id(t) for t in mlp.params} != {id(t) for t in critic_params} or len(critic_params) != len(mlp.params):
            return None
        return mlp

    def loss_and_grads(
        self, inputs: torch.Tensor, target: torch.Tensor, coeff: float
    ) -> tuple[torch.Tensor, list[torch.Tensor]]:
        """``coeff * mean((mlp(inputs) - target)^2)`` and its gradient, in ``self.params`` order.

        Call under ``torch.no_grad()``: nothing here is recorded.
        """
        layer_inputs = [inputs]
        hidden = inputs
        for linear, is_tanh in zip(self.linears[:-1], self.tanh, strict=True):
            hidden = torch.addmm(linear.bias, hidden, linear.weight.t())
            hidden = hidden.tanh_() if is_tanh else hidden.relu_()
            layer_inputs.append(hidden)
        output_layer = self.linears[-1]
        error = torch.addmm(output_layer.bias, hidden, output_layer.weight.t())
        error = error.sub_(target.view_as(error))
        scale = coeff / error.numel()
        flat_error = error.view(-1)
        loss = torch.dot(flat_error, flat_error).mul_(scale)
        delta = error.mul_(2.0 * scale)  # d loss / d output
        grads: list[torch.Tensor] = [delta] * len(self.params)
        for index in range(len(self.linears) - 1, -1, -1):
            layer_input = layer_inputs[index]
            grads[2 * index] = delta.t() @ layer_input
            grads[2 * index + 1] = delta.sum(0)
            if index > 0:  # back through this linear map, then the activation that fed it
                delta = delta @ self.linears[index].weight
                if self.tanh[index - 1]:  # tanh' = 1 - tanh^2
                    delta = torch.addcmul(delta, delta * layer_input, layer_input, value=-1.0)
                else:
                    delta = delta.mul_(layer_input > 0)
        return loss, grads


def _adam_kernel_for(arguments: dict[str, object]) -> Callable[..., None] | None:
    """torch's private Adam kernel if its signature binds ``arguments`` by keyword, else ``None``.

    Binding fails on a keyword the kernel lacks (renamed), on a parameter it requires that
    ``arguments`` lacks (newly added), and on positional-only parameters: in each case some
    torch release changed the kernel, and the fit takes the public ``Optimizer.step`` instead.
    """
    if _ADAM_KERNEL is None:
        return None
    try:
        inspect.signature(_ADAM_KERNEL).bind(**arguments)
    except (TypeError, ValueError):
        return None
    return _ADAM_KERNEL


def _gradient_step_fn(
    optimizer: torch.optim.Optimizer, params: list[torch.Tensor]
) -> Callable[[list[torch.Tensor]], None]:
    """``grads -> None`` applying one optimizer step with ``grads`` for ``params``.

    For a plain ``torch.optim.Adam`` over exactly ``params``, and a torch whose private kernel
    ``torch.optim.adam.adam`` takes the keywords used here (:func:`_adam_kernel_for`), this
    calls that kernel on the optimizer's own state (so checkpoints and learning-rate schedules
    keep working); the first step of a fresh optimizer goes through ``optimizer.step()`` so that
    Adam creates its state itself. Otherwise every step is ``optimizer.step()``, the same update.
    """

    def optimizer_step(grads: list[torch.Tensor]) -> None:
        for param, grad in zip(params, grads, strict=True):
            param.grad = grad
        optimizer.step()
        for param in params:
            param.grad = None

    group = optimizer.param_groups[0] if len(optimizer.param_groups) == 1 else None
    if (
        type(optimizer) is not torch.optim.Adam
        or group is None
        or len(group["params"]) != len(params)
        or {id(t) for t in group["params"]} != {id(t) for t in params}
        or any(group[flag] for flag in ("amsgrad", "capturable", "differentiable", "maximize"))
        or group.get("decoupled_weight_decay", False)
        or torch.is_tensor(group["lr"])
    ):
        return optimizer_step

    kernel_arguments: dict[str, object] | None = None  # all but ``grads``, once Adam's state exists
    adam: Callable[..., None] | None = None

    def functional_adam_step(grads: list[torch.Tensor]) -> None:
        nonlocal kernel_arguments, adam
        if kernel_arguments is None:
            if any(param not in optimizer.state for param in params):
                optimizer_step(grads)
                return
            states = [optimizer.state[param] for param in params]
            kernel_arguments = {
                "params": params,
                "exp_avgs": [state["exp_avg"] for state in states],
                "exp_avg_sqs": [state["exp_avg_sq"] for state in states],
                "max_exp_avg_sqs": [],
                "state_steps": [state["step"] for state in states],
                "foreach": group["foreach"],
                "fused": group["fused"],
                "amsgrad": False,
                "beta1": group["betas"][0],
                "beta2": group["betas"][1],
                "lr": group["lr"],
                "weight_decay": group["weight_decay"],
                "eps": group["eps"],
                "maximize": False,
            }
            adam = _adam_kernel_for({"grads": grads, **kernel_arguments})
        if adam is None:
            optimizer_step(grads)
        else:
            adam(grads=grads, **kernel_arguments)

    return functional_adam_step
