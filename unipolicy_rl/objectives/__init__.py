"""TRPO for TorchRL: the loss module and the natural-gradient update built on it."""

from unipolicy_rl.objectives.natural_gradient import (
    TRPOStepResult,
    TRPOUpdater,
    conjugate_gradient,
    fisher_vector_product_fn,
    fit_critic,
    flat_grad,
    kl_hessian_vector_product_fn,
    make_critic_optimizer,
    natural_gradient_step,
    policy_fisher_vector_product_fn,
)
from unipolicy_rl.objectives.trpo import TRPOLoss

__all__ = [
    "TRPOLoss",
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
