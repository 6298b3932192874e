"""TRPO for TorchRL: the loss module and the natural-gradient update built on it (and PPO's
clipped policy step as the alternative step of the same update).

Each submodule's ``__all__`` names its public API; this package re-exports all of them.
"""

from unipolicy_rl.objectives import clipped_step, critic_fit, natural_gradient, trpo, updater
from unipolicy_rl.objectives.clipped_step import *  # noqa: F403
from unipolicy_rl.objectives.critic_fit import *  # noqa: F403
from unipolicy_rl.objectives.natural_gradient import *  # noqa: F403
from unipolicy_rl.objectives.trpo import *  # noqa: F403
from unipolicy_rl.objectives.updater import *  # noqa: F403

__all__: list[str] = []
__all__ += trpo.__all__
__all__ += natural_gradient.__all__
__all__ += critic_fit.__all__
__all__ += updater.__all__
__all__ += clipped_step.__all__
