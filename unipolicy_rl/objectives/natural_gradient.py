"""The TRPO update: one natural-gradient policy step, then an Adam fit of the critic.

Written to be read top to bottom (in the spirit of stable-baselines3-contrib's TRPO), with each
guard next to the failure it prevents:

1. ``g``: flat gradient of the surrogate advantage ``mean(ratio * A)`` at the current policy.
2. ``F v``: Fisher-vector product, the Hessian of the mean ``KL(pi_detached || pi)`` times
   ``v``. The reference distribution is a *detached copy of the current policy*, so the KL and
   its gradient are zero at the current parameters and its Hessian there is the Fisher
   information matrix, positive semi-definite. (A KL against a non-detached copy is zero
   everywhere, a zero "Hessian"; one against a stale policy has an indefinite Hessian; both
   are the classic source of a non-positive ``s^T H s``.) ``damping * v`` is added so
   ``F + damping I`` is safely positive definite.
   Because the KL's gradient with respect to the distribution parameters (``loc``, ``scale``)
   is zero at the reference point, the chain rule leaves only ``J^T M J v``: ``J`` the
   Jacobian of the distribution parameters w.r.t. the policy weights, ``M`` the Hessian of
   the mean KL w.r.t. the distribution parameters (by double backward, on ``[N, act_dim]``
   tensors). :func:`fisher_vector_product_fn` computes exactly that, skipping the
   second-derivative-of-the-network terms that full double backward through the network
   (:func:`kl_hessian_vector_product_fn`, kept as the textbook reference) computes only to
   multiply them by zero; the tests check both against an explicit Hessian of the KL.
3. ``s``: approximate solution of ``(F + damping I) s = g`` by conjugate gradient.
4. The full step ``sqrt(2 delta / s^T H s) * s`` is the largest step along ``s`` whose
   *quadratic* KL estimate equals ``delta``.
5. Backtracking line search on the *true* KL and surrogate: accept the first step (shrinking by
   ``backtrack_factor``) with ``KL <= delta`` and a surrogate that improved; if none does,
   restore the parameters bit for bit.

Anything non-finite, or a curvature ``s^T H s <= 0``, skips the step before a parameter is
touched, and the returned :class:`TRPOStepResult` says why.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModule
from torch import nn
from torch.optim.adam import adam

from unipolicy_rl.objectives.trpo import TRPOLoss

__all__ = [
    "TRPOStepResult",
    "TRPOUpdater",
    "conjugate_gradient",
    "fisher_vector_product_fn",
    "fit_critic",
    "flat_grad",
    "kl_hessian_vector_product_fn",
    "make_critic_optimizer",
    "natural_gradient_step",
    "policy_fisher_vector_product_fn",
]


@dataclass(frozen=True)
class TRPOStepResult:
    """What one natural-gradient step did.

    Attributes:
        accepted: whether the parameters changed.
        skip_reason: ``None`` when accepted, otherwise why the step was not taken.
        kl: mean ``KL(old || new)`` after the step (0 when not accepted).
        surrogate_improvement: actual increase of the surrogate advantage (0 when not accepted).
        expected_improvement: first-order prediction ``g . delta_theta`` for the step applied
            (for the full step when none was applied). ``surrogate_improvement /
            expected_improvement`` near 1 means the linear model was trustworthy.
        step_size: the multiplier of the CG direction actually applied (full-step scale times
            the accepted backtracking fraction; 0 when not accepted).
        step_norm: Euclidean norm of the parameter change (0 when not accepted).
        line_search_tries: how many candidate steps were evaluated.
        cg_iterations: Fisher-vector products spent in conjugate gradient.
        curvature: ``s^T (F + damping I) s`` for the CG direction ``s``.
        gradient_norm: norm of the surrogate gradient ``g``.
        entropy: mean policy entropy before the step.
    """

    accepted: bool
    skip_reason: str | None
    kl: float = 0.0
    surrogate_improvement: float = 0.0
    expected_improvement: float = 0.0
    step_size: float = 0.0
    step_norm: float = 0.0
    line_search_tries: int = 0
    cg_iterations: int = 0
    curvature: float = 0.0
    gradient_norm: float = 0.0
    entropy: float = 0.0

    def as_metrics(self, prefix: str = "train/") -> dict[str, float]:
        """Flat float metrics (``accepted`` becomes ``step_accepted``; the reason is dropped)."""
        values = asdict(self)
        values.pop("skip_reason")
        values["step_accepted"] = float(values.pop("accepted"))
        return {prefix + name: float(value) for name, value in values.items()}


# ---------------------------------------------------------------------------------- building blocks
def flat_grad(
    output: torch.Tensor,
    params: Sequence[torch.Tensor],
    *,
    retain_graph: bool | None = None,
    create_graph: bool = False,
) -> torch.Tensor:
    """Gradient of a scalar w.r.t. ``params``, concatenated into one vector.

    Parameters the output does not depend on get zeros, so the vector layout always matches
    ``params``.
    """
    grads = torch.autograd.grad(
        output,
        params,
        retain_graph=retain_graph,
        create_graph=create_graph,
        allow_unused=True,
        materialize_grads=True,
    )
    return torch.cat([grad.reshape(-1) for grad in grads])


def fisher_vector_product_fn(
    outputs: Sequence[torch.Tensor],
    mean_kl_of: Callable[[list[torch.Tensor]], torch.Tensor],
    params: Sequence[torch.Tensor],
    damping: float,
) -> Callable[[torch.Tensor], torch.Tensor]:
    """``v -> (F + damping I) v``, ``F`` the Hessian of the mean KL at the current policy.

    Args:
        outputs: the policy's distribution parameters (e.g. ``loc``, ``scale``) computed from
            ``params`` (with their autograd graph).
        mean_kl_of: maps values of those distribution parameters to the mean
            ``KL(reference || distribution(values))``, the reference being a detached copy of
            the current policy (so ``outputs`` are where the KL and its gradient vanish).
        params: the policy parameters.
        damping: added times ``v``.

    ``F v = J^T (M (J v))`` with ``J = d outputs / d params`` and ``M`` the Hessian of
    ``mean_kl_of`` at ``outputs`` (by double backward on the small output tensors). ``J v``
    uses the double-vjp trick: ``w -> J^T w`` is linear in ``w``, so its derivative w.r.t.
    ``w`` along ``v`` is ``J v``. Each product is three backward passes over graphs built once.
    """
    params = list(params)
    points = [output.detach().requires_grad_() for output in outputs]
    kl_gradient = torch.autograd.grad(mean_kl_of(points), points, create_graph=True)
    probes = [torch.zeros_like(output, requires_grad=True) for output in outputs]
    transposed = torch.autograd.grad(
        outputs, params, grad_outputs=probes, create_graph=True, allow_unused=True, materialize_grads=True
    )
    moving = [index for index, grad in enumerate(transposed) if grad.requires_grad]  # params that move outputs
    sizes = [param.numel() for param in params]

    def fisher_vector_product(vector: torch.Tensor) -> torch.Tensor:
        pieces = [chunk.view_as(param) for chunk, param in zip(vector.detach().split(sizes), params, strict=True)]
        jacobian_vector = torch.autograd.grad(
            [transposed[index] for index in moving],
            probes,
            grad_outputs=[pieces[index] for index in moving],
            retain_graph=True,
            allow_unused=True,
            materialize_grads=True,
        )
        curvature_vector = torch.autograd.grad(
            kl_gradient,
            points,
            grad_outputs=jacobian_vector,
            retain_graph=True,
            allow_unused=True,
            materialize_grads=True,
        )
        fisher_vector = torch.autograd.grad(
            outputs,
            params,
            grad_outputs=curvature_vector,
            retain_graph=True,
            allow_unused=True,
            materialize_grads=True,
        )
        return torch.cat([piece.reshape(-1) for piece in fisher_vector]) + damping * vector

    return fisher_vector_product


def policy_fisher_vector_product_fn(
    loss_module: TRPOLoss,
    dist_params: TensorDictBase,
    reference: torch.distributions.Distribution,
    damping: float,
) -> Callable[[torch.Tensor], torch.Tensor]:
    """:func:`fisher_vector_product_fn` for ``loss_module``'s policy on a batch.

    Args:
        loss_module: holds the actor parameters and builds distributions.
        dist_params: ``loss_module.policy_distribution_params(batch)``, with its graph.
        reference: the same distribution built from ``dist_params.detach()``.
        damping: added times ``v``.
    """
    keys = loss_module.actor_network.dist_params_keys

    def mean_kl_of(values: list[torch.Tensor]) -> torch.Tensor:
        candidate = dist_params.empty()
        for key, value in zip(keys, values, strict=True):
            candidate.set(key, value)
        return loss_module.mean_kl(reference, loss_module.distribution_from_params(candidate))

    outputs = [dist_params.get(key) for key in keys]
    return fisher_vector_product_fn(outputs, mean_kl_of, loss_module.actor_parameters(), damping)


def kl_hessian_vector_product_fn(
    kl: torch.Tensor, params: Sequence[torch.Tensor], damping: float
) -> Callable[[torch.Tensor], torch.Tensor]:
    """``v -> (H + damping I) v`` with ``H`` the Hessian of the scalar ``kl`` w.r.t. ``params``.

    The textbook Pearlmutter product: build ``grad kl`` with ``create_graph=True`` once, then
    back-propagate ``grad kl . v`` through it. With ``kl`` the mean KL against a detached copy
    of the current policy, ``H`` is the Fisher matrix and this equals
    :func:`fisher_vector_product_fn`, at about 1.7x its cost (it also differentiates terms
    that are multiplied by the zero KL gradient). Kept as the reference the tests compare to.
    """
    kl_grad = flat_grad(kl, params, create_graph=True)

    def hessian_vector_product(vector: torch.Tensor) -> torch.Tensor:
        directional = kl_grad @ vector.detach()
        return flat_grad(directional, params, retain_graph=True) + damping * vector

    return hessian_vector_product


def conjugate_gradient(
    matvec: Callable[[torch.Tensor], torch.Tensor],
    b: torch.Tensor,
    max_iters: int = 10,
    residual_tol: float = 1e-10,
) -> tuple[torch.Tensor, int]:
    """Approximately solve ``A x = b`` for symmetric positive-definite ``A`` given as ``matvec``.

    Stops after ``max_iters`` products, when the squared residual falls below
    ``residual_tol``, or when a search direction has non-positive curvature ``p^T A p``
    (``A`` is then not positive definite along ``p``; continuing would divide by it and
    could flip the step's sign). Returns ``(x, number_of_matvec_calls)``.
    """
    x = torch.zeros_like(b)
    residual = b.clone()
    direction = b.clone()
    residual_sq = residual @ residual
    iterations = 0
    for _ in range(max_iters):
        if residual_sq <= residual_tol:
            break
        a_direction = matvec(direction)
        iterations += 1
        curvature = direction @ a_direction
        if not (torch.isfinite(curvature) and curvature > 0):
            break
        alpha = residual_sq / curvature
        x += alpha * direction
        residual -= alpha * a_direction
        new_residual_sq = residual @ residual
        direction = residual + (new_residual_sq / residual_sq) * direction
        residual_sq = new_residual_sq
    return x, iterations


def _apply_step(
    params: Sequence[torch.Tensor],
    originals: Sequence[torch.Tensor],
    step: torch.Tensor | None,
) -> None:
    """Set ``params`` to ``originals + step`` in place (``step=None`` restores exactly)."""
    offset = 0
    for param, original in zip(params, originals, strict=True):
        if step is None:
            param.copy_(original)
        else:
            count = param.numel()
            param.copy_(original + step[offset : offset + count].view_as(param))
            offset += count


# ------------------------------------------------------------------------------------ policy step
def natural_gradient_step(
    loss_module: TRPOLoss,
    batch: TensorDictBase,
    *,
    advantage: torch.Tensor | None = None,
    max_kl: float = 0.01,
    damping: float = 0.1,
    cg_iters: int = 10,
    cg_residual_tol: float = 1e-10,
    backtrack_factor: float = 0.8,
    max_backtracks: int = 10,
) -> TRPOStepResult:
    """One TRPO policy step on ``batch``; updates ``loss_module.actor_network_params`` in place.

    Args:
        loss_module: the :class:`TRPOLoss` holding the actor parameters and the keys.
        batch: collected data with actions, stored log-probs and ``loc``/``scale``; its
            advantage is computed by the loss's value estimator if missing.
        advantage: the (already normalised) advantage, shaped like ``batch``; pass it to
            avoid recomputing it.
        max_kl: trust-region radius ``delta`` on the mean ``KL(old || new)``.
        damping: added to the Fisher diagonal (conditioning of CG; 0.1 as in the TRPO
            reference implementations).
        cg_iters: conjugate-gradient iterations (Fisher-vector products).
        cg_residual_tol: CG stops early when the squared residual falls below this.
        backtrack_factor: step shrink factor between line-search tries.
        max_backtracks: line-search tries before giving up.

    Returns:
        a :class:`TRPOStepResult`.
    """
    params = loss_module.actor_parameters()
    if advantage is None:
        advantage = loss_module.advantage(batch)

    with torch.enable_grad():
        dist_params = loss_module.policy_distribution_params(batch)
        policy = loss_module.distribution_from_params(dist_params)
        # The current policy, frozen: the centre of the trust region and the KL's reference.
        reference = loss_module.distribution_from_params(dist_params.detach())
        surrogate = loss_module.surrogate_advantage(policy, batch, advantage)
        entropy = float(reference.entropy().mean())

        gradient = flat_grad(surrogate, params, retain_graph=True)
        gradient_norm = float(gradient.norm())
        if not math.isfinite(gradient_norm):
            # NaN/inf advantages or log-probs: any step built from this would be garbage.
            return TRPOStepResult(False, "non-finite policy gradient", entropy=entropy)
        if gradient_norm == 0.0:
            # Nothing to improve (e.g. all advantages equal): CG would return s = 0 and the
            # step scale would divide by zero.
            return TRPOStepResult(False, "zero policy gradient", gradient_norm=0.0, entropy=entropy)

        fisher_vector_product = policy_fisher_vector_product_fn(loss_module, dist_params, reference, damping)
        direction, cg_iterations = conjugate_gradient(fisher_vector_product, gradient, cg_iters, cg_residual_tol)
        curvature = float(direction @ fisher_vector_product(direction))
        del fisher_vector_product  # frees the retained graphs before the line search
    surrogate_before = surrogate.detach()
    diagnostics = {
        "cg_iterations": cg_iterations,
        "curvature": curvature,
        "gradient_norm": gradient_norm,
        "entropy": entropy,
    }

    if not (math.isfinite(curvature) and curvature > 0.0):
        # With damping > 0 this is impossible for a correct Fisher product; it signals a
        # mis-built KL graph (or overflow). The quadratic model cannot size a step.
        return TRPOStepResult(False, f"non-positive curvature s^T H s = {curvature:.3g}", **diagnostics)
    full_step_scale = math.sqrt(2.0 * max_kl / curvature)
    full_step = full_step_scale * direction
    expected_full = float(gradient @ full_step)
    if not (torch.isfinite(full_step).all() and math.isfinite(expected_full)):
        return TRPOStepResult(False, "non-finite step", expected_improvement=expected_full, **diagnostics)

    with torch.no_grad():
        originals = [param.detach().clone() for param in params]
        for tries in range(1, max_backtracks + 1):
            fraction = backtrack_factor ** (tries - 1)
            _apply_step(params, originals, fraction * full_step)
            candidate = loss_module.policy_distribution(batch)
            improvement = float(loss_module.surrogate_advantage(candidate, batch, advantage) - surrogate_before)
            new_kl = float(loss_module.mean_kl(reference, candidate))
            # Both conditions, on the true (not quadratic) KL: the quadratic model can
            # under-estimate the KL, and a first-order gain can be a real loss.
            if new_kl <= max_kl and improvement > 0.0:  # False for NaN too
                return TRPOStepResult(
                    True,
                    None,
                    kl=new_kl,
                    surrogate_improvement=improvement,
                    expected_improvement=fraction * expected_full,
                    step_size=fraction * full_step_scale,
                    step_norm=fraction * float(full_step.norm()),
                    line_search_tries=tries,
                    **diagnostics,
                )
        _apply_step(params, originals, None)  # bit-identical restore
    return TRPOStepResult(
        False,
        "line search failed: no step kept KL <= max_kl and improved the surrogate",
        expected_improvement=expected_full,
        line_search_tries=max_backtracks,
        **diagnostics,
    )


# ------------------------------------------------------------------------------------ critic fit
def make_critic_optimizer(loss_module: TRPOLoss, lr: float = 1e-3) -> torch.optim.Adam:
    """Adam over the critic parameters only (the policy moves by the natural gradient alone).

    Uses the fused Adam kernel where available: with small networks and about a thousand
    minibatch steps per update, per-tensor optimizer overhead is a large share of the time.
    """
    params = loss_module.critic_parameters()
    try:
        return torch.optim.Adam(params, lr=lr, fused=True)
    except (RuntimeError, TypeError):
        return torch.optim.Adam(params, lr=lr)


def fit_critic(
    loss_module: TRPOLoss,
    batch: TensorDictBase,
    optimizer: torch.optim.Optimizer,
    epochs: int = 10,
    minibatch_size: int = 128,
    generator: torch.Generator | None = None,
) -> float:
    """Regress the critic on ``batch``'s value target by Adam over shuffled minibatches.

    The value target must already be in ``batch`` (written by the value estimator before
    this fit, so every minibatch regresses on the same fixed targets). Each epoch reshuffles
    the whole batch once and walks it in contiguous slices. Returns the mean minibatch loss
    (``critic_coeff * MSE``) over the fit.

    This loop runs about a thousand tiny steps per update, so per-step overhead, not
    arithmetic, sets its speed. Two fast paths, each checked against the plain path in
    ``tests/test_trpo.py``, keep it low:

    * a critic that is a plain MLP (``nn.Sequential`` of ``nn.Linear`` and tanh/ReLU, as
      :func:`unipolicy_rl.networks.make_critic` builds) gets its MSE gradient by a
      hand-written backward pass, on tensors, with no TensorDict or autograd bookkeeping;
      any other critic goes through :meth:`TRPOLoss.critic_loss` and autograd;
    * a plain ``torch.optim.Adam`` is applied through ``torch.optim.adam.adam`` on the
      optimizer's own state, skipping ``Optimizer.step``'s per-call bookkeeping; any other
      optimizer is stepped normally.
    """
    flat = batch.reshape(-1)
    count = flat.numel()
    critic = loss_module.critic_network
    target = flat.get(loss_module.tensor_keys.value_target).detach()
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
    return float(total / max(steps, 1))


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


def _gradient_step_fn(
    optimizer: torch.optim.Optimizer, params: list[torch.Tensor]
) -> Callable[[list[torch.Tensor]], None]:
    """``grads -> None`` applying one optimizer step with ``grads`` for ``params``.

    For a plain ``torch.optim.Adam`` over exactly ``params`` this calls the public functional
    kernel ``torch.optim.adam.adam`` on the optimizer's own state (so checkpoints and
    learning-rate schedules keep working); the first step of a fresh optimizer goes through
    ``optimizer.step()`` so that Adam creates its state itself.
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

    state_lists: tuple[list[torch.Tensor], ...] | None = None

    def functional_adam_step(grads: list[torch.Tensor]) -> None:
        nonlocal state_lists
        if state_lists is None:
            if any(param not in optimizer.state for param in params):
                optimizer_step(grads)
                return
            states = [optimizer.state[param] for param in params]
            state_lists = tuple([state[name] for state in states] for name in ("exp_avg", "exp_avg_sq", "step"))
        exp_avgs, exp_avg_sqs, state_steps = state_lists
        adam(
            params,
            grads,
            exp_avgs,
            exp_avg_sqs,
            [],
            state_steps,
            foreach=group["foreach"],
            fused=group["fused"],
            amsgrad=False,
            beta1=group["betas"][0],
            beta2=group["betas"][1],
            lr=group["lr"],
            weight_decay=group["weight_decay"],
            eps=group["eps"],
            maximize=False,
        )

    return functional_adam_step


# ------------------------------------------------------------------------------------ full update
class TRPOUpdater:
    """One full TRPO update per call: advantage, natural-gradient policy step, critic fit.

    Keeps the critic's Adam state across updates. ``update(batch)`` takes a collected batch
    shaped ``[*envs, time]`` (time last, as TorchRL's GAE expects) and returns flat float
    metrics named ``train/...``; the last :class:`TRPOStepResult` (with its skip reason) is
    kept in ``last_step``.

    Defaults follow the TRPO papers / stable-baselines3-contrib: ``max_kl=0.01``,
    ``damping=0.1``, 10 CG iterations, backtracking by 0.8 up to 10 tries, critic Adam
    ``lr=1e-3`` for 10 epochs of minibatches of 128.
    """

    def __init__(
        self,
        loss_module: TRPOLoss,
        *,
        max_kl: float = 0.01,
        damping: float = 0.1,
        cg_iters: int = 10,
        cg_residual_tol: float = 1e-10,
        backtrack_factor: float = 0.8,
        max_backtracks: int = 10,
        critic_lr: float = 1e-3,
        critic_epochs: int = 10,
        critic_minibatch_size: int = 128,
        generator: torch.Generator | None = None,
    ) -> None:
        self.loss_module = loss_module
        self.step_kwargs = {
            "max_kl": max_kl,
            "damping": damping,
            "cg_iters": cg_iters,
            "cg_residual_tol": cg_residual_tol,
            "backtrack_factor": backtrack_factor,
            "max_backtracks": max_backtracks,
        }
        self.critic_optimizer = make_critic_optimizer(loss_module, critic_lr)
        self.critic_epochs = critic_epochs
        self.critic_minibatch_size = critic_minibatch_size
        self.generator = generator
        self.last_step: TRPOStepResult | None = None

    def update(self, batch: TensorDictBase) -> dict[str, float]:
        """Update policy and critic on ``batch`` (advantage keys are written into it)."""
        loss = self.loss_module
        loss.compute_advantage(batch)
        flat = batch.reshape(-1)
        advantage = loss.advantage(flat)
        step = natural_gradient_step(loss, flat, advantage=advantage, **self.step_kwargs)
        self.last_step = step
        metrics = step.as_metrics("train/")
        metrics["train/explained_variance"] = _explained_variance(
            flat.get(loss.tensor_keys.value), flat.get(loss.tensor_keys.value_target)
        )
        metrics["train/loss_critic"] = fit_critic(
            loss,
            flat,
            self.critic_optimizer,
            self.critic_epochs,
            self.critic_minibatch_size,
            self.generator,
        )
        return metrics


def _explained_variance(prediction: torch.Tensor, target: torch.Tensor) -> float:
    """``1 - Var(target - prediction) / Var(target)`` of the critic before its fit.

    0.0 where it is undefined (fewer than two samples, or a constant target), so the metrics
    stay finite for loggers and NaN checks.
    """
    target = target.reshape(-1)
    variance = target.var(correction=0)
    if target.numel() < 2 or variance == 0:
        return 0.0
    residual = target - prediction.reshape(-1)
    return float(1.0 - residual.var(correction=0) / variance)
