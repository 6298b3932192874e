"""Robots from RoboGrammar's graph grammar: the rules as data, derivations, morphologies and their split.

A derivation (rule names, each applied to the leftmost nonterminal) yields a robot graph,
and :func:`describe` turns it into a :class:`~unipolicy_rl.robots.RobotDescription` at a
design (l, rho). :class:`Morphology` holds a derivation's choices for counting, enumerating
and sampling; :func:`split_morphologies` draws a fixed training / held-out split of the
robots that stand. docs/grammar.md walks through it.
"""

from unipolicy_rl.robots.grammar.build import PartKinds, describe, part_kinds
from unipolicy_rl.robots.grammar.derivation import RobotGraph, applicable_rules, apply_rule, derive
from unipolicy_rl.robots.grammar.morphology import (
    VERTEBRATE,
    LimbLink,
    Morphology,
    SizeLimits,
    count_morphologies,
    enumerate_morphologies,
    sample_morphology,
)
from unipolicy_rl.robots.grammar.parts import LINK_KINDS, JointPart, LinkKind
from unipolicy_rl.robots.grammar.rules import RULES, Rule, rules_for
from unipolicy_rl.robots.grammar.split import MorphologySplit, split_morphologies, stands_at
from unipolicy_rl.robots.grammar.standing import Stance, stance, stands

__all__ = [
    "LINK_KINDS",
    "RULES",
    "VERTEBRATE",
    "JointPart",
    "LimbLink",
    "LinkKind",
    "Morphology",
    "MorphologySplit",
    "PartKinds",
    "RobotGraph",
    "Rule",
    "SizeLimits",
    "Stance",
    "applicable_rules",
    "apply_rule",
    "count_morphologies",
    "derive",
    "describe",
    "enumerate_morphologies",
    "part_kinds",
    "rules_for",
    "sample_morphology",
    "split_morphologies",
    "stance",
    "stands",
    "stands_at",
]
