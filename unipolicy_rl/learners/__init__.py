"""Policy learners behind one interface (:class:`Learner`): TRPO today."""

from unipolicy_rl.learners.base import Learner, StalledLearning
from unipolicy_rl.learners.trpo import TRPOLearner

__all__ = ["Learner", "StalledLearning", "TRPOLearner"]
