"""Policy learners behind one interface (:class:`Learner`): TRPO (on-policy), the off-policy
SAC, CrossQ and REDQ (TorchRL's losses with our replay buffer and update-to-data ratio; on a
world model, MBPO), and distillation of grammar robots' specialists into one token policy (DAgger)."""

from unipolicy_rl.learners.base import Learner, StalledLearning
from unipolicy_rl.learners.distillation import DistillationLearner, DistillationSettings, SpecialistTeachers
from unipolicy_rl.learners.off_policy import OffPolicyLearner, OffPolicySettings
from unipolicy_rl.learners.trpo import TRPOLearner

__all__ = ["DistillationLearner", "DistillationSettings", "Learner", "OffPolicyLearner", "OffPolicySettings",
           "SpecialistTeachers", "StalledLearning", "TRPOLearner"]
