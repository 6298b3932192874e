"""Real episodes where the policy acts with its mean action, beside the ones where it samples.

A policy is evaluated, and used, by its mean action; it is trained on the states its sampled
actions reach. The two can part: the default model-based walker's policy at 100,000 real env steps
stands still on one design, its mean action's closed loop settled on a fixed point, while its own
sampled actions walk that design (study/holding/README.md). Collecting a few robots of each real
epoch with the mean action puts the states the mean action goes to into the data: the world model
fits them and imagined branches start from them, so the imagined updates train the policy where
its mean action stands.

The mean-action robots' steps are not samples of the policy their ``action_log_prob`` belongs to,
so a learner that takes an on-policy step on the real batch must not see them; the config refuses
the combinations that would (``validation``). The epoch's logged returns (``train/episode_reward``)
count every robot, the mean-action ones included.
"""

from __future__ import annotations

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase
from torchrl.envs.utils import ExplorationType, exploration_type, set_exploration_type

# Marks each step taken with the mean action (True) or a sampled one (False).
MEAN_ACTION = "mean_action"


class MeanActionRobots(TensorDictModuleBase):
    """``policy`` acting with its mean action on the first ``robots`` rows of each batch (one row per
    robot) and sampling on the rest, while exploration is on; with exploration off (an evaluation),
    every row takes the mean action, as ``policy`` alone would.

    Each row's step carries :data:`MEAN_ACTION`, and the mean-action rows keep the distribution's
    parameters (``loc``, ``scale``) of their own state, so the batch says what each robot did.
    """

    def __init__(self, policy: TensorDictModuleBase, robots: int) -> None:
        super().__init__()
        if not (isinstance(robots, int) and not isinstance(robots, bool) and robots >= 1):
            raise ValueError(f"robots must be a positive integer (the rows acting with the mean action), got "
                             f"{robots!r}")
        self.policy, self.robots = policy, robots
        self.in_keys = list(policy.in_keys)
        self.out_keys = [*policy.out_keys, MEAN_ACTION]

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        rows = tensordict.batch_size[0] if tensordict.batch_dims else 0
        if rows <= self.robots:
            raise ValueError(f"{self.robots} robots act with the mean action, so a batch needs more rows than that "
                             f"(some must sample), got a batch of {tuple(tensordict.batch_size)}")
        mean_rows = torch.zeros(tensordict.batch_size, dtype=torch.bool, device=tensordict.device)
        if exploration_type() in (ExplorationType.DETERMINISTIC, ExplorationType.MODE, ExplorationType.MEAN):
            self.policy(tensordict)
            tensordict.set(MEAN_ACTION, mean_rows.fill_(True).unsqueeze(-1))
            return tensordict
        head = tensordict[: self.robots].clone()
        with set_exploration_type(ExplorationType.DETERMINISTIC):
            self.policy(head)
        self.policy(tensordict)
        tensordict[: self.robots] = head
        mean_rows[: self.robots] = True
        tensordict.set(MEAN_ACTION, mean_rows.unsqueeze(-1))
        return tensordict
