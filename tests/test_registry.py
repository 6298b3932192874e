"""The registry's names are the factories' and the validation's: one list, every name buildable."""

from unipolicy_rl import factories, registry, validation
from unipolicy_rl.learners.off_policy import LOSSES
from unipolicy_rl.policy import ON_POLICY_ALGOS


def test_every_registered_learner_has_a_factory_and_every_factory_a_name():
    assert set(factories.LEARNERS) == set(registry.LEARNER_NAMES)
    assert set(registry.OFF_POLICY_LEARNERS) == set(LOSSES)
    assert set(registry.ON_POLICY_LEARNERS) == set(ON_POLICY_ALGOS)


def test_validation_refuses_a_name_outside_the_registry():
    assert validation.RULES["algo.name"]("a2c") is not None
    assert all(validation.RULES["algo.name"](name) is None for name in registry.LEARNER_NAMES)
    assert validation.RULES["source.kind"]("imagined") is not None
    assert all(validation.RULES["source.kind"](kind) is None for kind in registry.SOURCE_KINDS)
