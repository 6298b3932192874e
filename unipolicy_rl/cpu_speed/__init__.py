"""Speed tricks for a small CPU machine, kept apart from the algorithms they speed up.

Each one replaces a plain path by a faster one that computes the same thing, and has a test
that it does:

* :func:`~unipolicy_rl.cpu_speed.fused_adam.adam`: ``torch.optim.Adam(fused=True)`` wherever the
  parameters' device has the fused kernel (``tests/test_optimizers.py``: the same steps as the
  default kernel, to float rounding).
* :class:`~unipolicy_rl.cpu_speed.plain_mlp.PlainMLPRegression`: a plain-MLP critic's MSE gradient
  by a hand-written backward pass (``tests/test_trpo.py``: the same fit as autograd's).
* :class:`~unipolicy_rl.cpu_speed.critic_process.CriticFitProcess`: TRPO's lagged critic fit on a
  forked process beside the next update (``tests/test_critic_fit.py``: the same learning as
  ``algo.critic_fit=lagged`` in one process).
* :class:`~unipolicy_rl.cpu_speed.parallel_env.SleepingParallelEnv`: TorchRL's ``ParallelEnv`` whose
  parent sleeps instead of spin-polling its workers (``tests/test_envs.py``: the same steps as
  TorchRL's ``ParallelEnv``).

Nothing here imports the rest of the package: the algorithms import these, never the reverse.
"""

from unipolicy_rl.cpu_speed.critic_process import CriticFitProcess
from unipolicy_rl.cpu_speed.fused_adam import adam
from unipolicy_rl.cpu_speed.parallel_env import SleepingParallelEnv
from unipolicy_rl.cpu_speed.plain_mlp import PlainMLPRegression

__all__ = ["CriticFitProcess", "PlainMLPRegression", "SleepingParallelEnv", "adam"]
