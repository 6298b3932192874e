"""The names a run's config may choose among: the learners (``algo.name``) and the source kinds
(``source.kind``).

Defined here, below both the factories that build each choice and the start-up validation
that refuses an unknown one, so neither has to import the other to know the names.
``tests/test_registry.py`` checks that every name has its factory and no factory lacks a name.
"""

from __future__ import annotations

# ``algo.name``: on-policy (TRPO and PPO, one learner), off-policy (TorchRL's losses), distillation.
ON_POLICY_LEARNERS = ("trpo", "ppo")
OFF_POLICY_LEARNERS = ("sac", "crossq", "redq")
LEARNER_NAMES = (*ON_POLICY_LEARNERS, *OFF_POLICY_LEARNERS, "distill")

# ``source.kind``: real data only, or a world model fitted to them.
SOURCE_KINDS = ("real", "model")
