"""One TRPO policy step by natural gradient.

Written to be read top to bottom (in the spirit of stable-baselines3-contrib's TRPO), with each
guard next to the failure it prevents:

1. ``g``: flat gradient of the surrogate advantage ``mean(ratio * A)`` at the current policy
   (:meth:`TRPOLoss.objective`: plus ``entropy_coeff`` times the mean entropy, where set; "the
   surrogate" below is that objective).
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

from unipolicy_rl.objectives.trpo import TRPOLoss

__all__ = [
    "TRPOStepResult",
    "TrustRegion",
    "conjugate_gradient",
    "fisher_vector_product_fn",
    "fisher_subsample",
    "flat_grad",
    "kl_hessian_vector_product_fn",
    "natural_gradient_step",
    "policy_fisher_vector_product_fn",
]


@dataclass(frozen=True)
class TrustRegion:
    """How one TRPO policy step is sized and checked. Defaults: the TRPO papers and
    stable-baselines3-contrib.

    Attributes:
        max_kl: trust-region radius ``delta`` on the mean ``KL(old || new)``.
        damping: added to the Fisher diagonal (conditioning of CG; 0.1 as in the TRPO
            reference implementations).
        cg_iters: conjugate-gradient iterations (Fisher-vector products).
        cg_residual_tol: CG stops early when the squared residual falls below this.
        backtrack_factor: step shrink factor between line-search tries.
        max_backtracks: line-search tries before giving up.
        fisher_fraction: the share of the batch the Fisher-vector products (CG and the step's
            curvature) are computed on, evenly spaced samples (:func:`fisher_subsample`); 1.0,
            the default, is the whole batch. OpenAI baselines' TRPO uses every fifth sample
            (0.2): the Fisher matrix is an average that a subsample estimates well, while the
            products are most of a large network's step. The gradient, and the line search's
            KL and surrogate, always use the whole batch, so the accepted step keeps the bound.
    """

    max_kl: float = 0.01
    damping: float = 0.1
    cg_iters: int = 10
    cg_residual_tol: float = 1e-10
    backtrack_factor: float = 0.8
    max_backtracks: int = 10
    fisher_fraction: float = 1.0

    def __post_init__(self) -> None:
        if not (math.isfinite(self.max_kl) and self.max_kl > 0):
            raise ValueError(f"max_kl must be a positive number, got {self.max_kl!r}")
        for name in ("damping", "cg_residual_tol"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value >= 0):
                raise ValueError(f"{name} must be a non-negative number, got {value!r}")
        if not 0 < self.backtrack_factor < 1:
            raise ValueError(f"backtrack_factor must lie in (0, 1), got {self.backtrack_factor!r}")
        for name in ("cg_iters", "max_backtracks"):
            value = getattr(self, name)
            if not (isinstance(value, int) and value >= 1):
                raise ValueError(f"{name} must be a positive integer, got {value!r}")
        fraction = self.fisher_fraction
        if isinstance(fraction, bool) or not (isinstance(fraction, (int, float)) and math.isfinite(fraction)
                                              and 0 < fraction <= 1):
            raise ValueError(f"fisher_fraction must lie in (0, 1] (the share of the batch the Fisher products "
                             f"use), got {fraction!r}")


@dataclass(frozen=True)
class TRPOStepResult:
    """What one natural-gradient step did.

    Attributes:
        accepted: whether the parameters changed.
        skip_reason: ``None`` when accepted, otherwise why the step was not taken.
        kl: mean ``KL(old || new)`` after the step (0 when not accepted).
        surrogate_improvement: actual increase of the surrogate advantage, with its entropy bonus
            where the loss has one (0 when not accepted).
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
def _grads(
    outputs: torch.Tensor | Sequence[torch.Tensor],
    inputs: Sequence[torch.Tensor],
    grad_outputs: Sequence[torch.Tensor] | None = None,
    **kwargs: bool | None,
) -> tuple[torch.Tensor, ...]:
    """``torch.autograd.grad`` with zeros for inputs the outputs do not depend on.

    Every result is then a tensor shaped like its input, so the results can be flattened into
    one vector with a fixed layout, or fed back as ``grad_outputs``, without special cases.
    """
    return torch.autograd.grad(
        outputs, inputs, grad_outputs=grad_outputs, allow_unused=True, materialize_grads=True, **kwargs
    )


def _flatten(tensors: Sequence[torch.Tensor]) -> torch.Tensor:
    """Concatenate ``tensors`` into one vector, in the parameter layout CG works in."""
    return torch.cat([tensor.reshape(-1) for tensor in tensors])


def _damped(product: Callable[[torch.Tensor], torch.Tensor], damping: float) -> Callable[[torch.Tensor], torch.Tensor]:
    """``v -> product(v) + damping * v``: the damping that keeps CG's matrix positive definite."""

    def damped_product(vector: torch.Tensor) -> torch.Tensor:
        return product(vector) + damping * vector

    return damped_product


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
    return _flatten(_grads(output, params, retain_graph=retain_graph, create_graph=create_graph))


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
    transposed = _grads(outputs, params, probes, create_graph=True)
    moving = [index for index, grad in enumerate(transposed) if grad.requires_grad]  # params that move outputs
    sizes = [param.numel() for param in params]

    def fisher_vector_product(vector: torch.Tensor) -> torch.Tensor:
        pieces = [chunk.view_as(param) for chunk, param in zip(vector.detach().split(sizes), params, strict=True)]
        jacobian_vector = _grads(
            [transposed[index] for index in moving], probes, [pieces[index] for index in moving], retain_graph=True
        )
        curvature_vector = _grads(kl_gradient, points, jacobian_vector, retain_graph=True)
        return _flatten(_grads(outputs, params, curvature_vector, retain_graph=True))

    return _damped(fisher_vector_product, damping)


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

    The Fisher product differentiates the floating-point distribution parameters (``loc``,
    ``scale``); any other one, such as the bool action mask of
    :class:`~unipolicy_rl.masked_normal.MaskedIndependentNormal`, is data and is passed through.
    """
    keys = [key for key in loss_module.actor_network.dist_params_keys if dist_params.get(key).is_floating_point()]
    fixed = dist_params.select(*loss_module.actor_network.dist_params_keys).exclude(*keys)  # empty for a flat policy

    def mean_kl_of(values: list[torch.Tensor]) -> torch.Tensor:
        candidate = fixed.clone(False)
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
    :func:`fisher_vector_product_fn`, at a higher cost (it also differentiates terms that are
    multiplied by the zero KL gradient). Kept as the reference the tests compare to.
    """
    kl_grad = flat_grad(kl, params, create_graph=True)

    def hessian_vector_product(vector: torch.Tensor) -> torch.Tensor:
        return flat_grad(kl_grad @ vector.detach(), params, retain_graph=True)

    return _damped(hessian_vector_product, damping)


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


def fisher_subsample(batch_size: int, fraction: float) -> torch.Tensor | None:
    """Indices of ``ceil(fraction * batch_size)`` evenly spaced samples of a flat batch (every
    fifth for 0.2, as OpenAI baselines' ``arr[::5]``), or None for the whole batch. Fixed, not
    drawn: a step is a function of its batch, so a resumed run repeats it exactly."""
    count = math.ceil(fraction * batch_size)
    if count >= batch_size:
        return None
    return torch.arange(count) * batch_size // count


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
    trust_region: TrustRegion | None = None,
) -> TRPOStepResult:
    """One TRPO policy step on ``batch``; updates ``loss_module.actor_network_params`` in place.

    Args:
        loss_module: the :class:`TRPOLoss` holding the actor parameters and the keys.
        batch: collected data with actions, stored log-probs and ``loc``/``scale``; its
            advantage is computed by the loss's value estimator if missing.
        advantage: the (already normalised) advantage, shaped like ``batch``; pass it to
            avoid recomputing it.
        trust_region: the step's radius, CG and line-search settings (default :class:`TrustRegion`).

    Returns:
        a :class:`TRPOStepResult`.
    """
    trust_region = trust_region or TrustRegion()
    max_kl, max_backtracks, backtrack_factor = (trust_region.max_kl, trust_region.max_backtracks,
                                                trust_region.backtrack_factor)
    params = loss_module.actor_parameters()
    if advantage is None:
        advantage = loss_module.advantage(batch)

    with torch.enable_grad():
        dist_params = loss_module.policy_distribution_params(batch)
        policy = loss_module.distribution_from_params(dist_params)
        # The current policy, frozen: the centre of the trust region and the KL's reference.
        reference = loss_module.distribution_from_params(dist_params.detach())
        surrogate = loss_module.objective(policy, batch, advantage)
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

        subsample = fisher_subsample(batch.numel(), trust_region.fisher_fraction)
        if subsample is None:
            fisher_vector_product = policy_fisher_vector_product_fn(loss_module, dist_params, reference,
                                                                    trust_region.damping)
        else:  # the products back-propagate through the subsample's own (smaller) forward pass
            sub_params = loss_module.policy_distribution_params(batch.reshape(-1)[subsample])
            sub_reference = loss_module.distribution_from_params(sub_params.detach())
            fisher_vector_product = policy_fisher_vector_product_fn(loss_module, sub_params, sub_reference,
                                                                    trust_region.damping)
        direction, cg_iterations = conjugate_gradient(fisher_vector_product, gradient, trust_region.cg_iters,
                                                      trust_region.cg_residual_tol)
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
            improvement = float(loss_module.objective(candidate, batch, advantage) - surrogate_before)
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
