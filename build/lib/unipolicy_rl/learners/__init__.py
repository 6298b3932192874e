"""Policy learners behind one interface (:class:`Learner`): TRPO (on-policy) and the off-policy
SAC, CrossQ and REDQ (TorchRL's losses with our replay buffer and update-to-data ratio; on a
world model, MBPO)."""

from unipolicy_rl.learners.base import Learner, StalledLearning
from unipolicy_rl.learners.off_policy import OffPolicyLearner, OffPolicySettings
from unipolicy_rl.learners.trpo import TRPOLearner

__all__ = ["Learner", "OffPolicyLearner", "OffPolicySettings", "StalledLearning", "TRPOLearner"]
