"""unipolicy_rl: one TRPO locomotion policy for a robot whose build is uncertain, on TorchRL.

Importing the package registers the gymnasium id ``unipolicy_rl/Walker-v0`` (as environment
packages do), so ``gymnasium.make`` works after ``import unipolicy_rl``. The id is registered by
:mod:`unipolicy_rl.envs`, its one home; importing it here costs what that package costs (torch,
TorchRL, PyBullet), which every use of this package pays anyway.
"""

from unipolicy_rl.envs import ENV_ID

__version__ = "0.1.0"

__all__ = ["ENV_ID", "__version__"]
