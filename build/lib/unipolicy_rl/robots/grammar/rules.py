"""RoboGrammar's rule set as data, and the one rule the thesis robot adds.

Transcribed from RoboGrammar's public rule file ``data/designs/grammar_apr30.dot``
(github.com/allanzhao/RoboGrammar, MIT licence): each rule's left side (the pattern it
rewrites) and right side (what replaces it), node and edge for node and edge, with the
terminal parts converted to our frame by :mod:`unipolicy_rl.robots.grammar.parts`.

A rule's left side holds exactly one labelled element, the nonterminal it rewrites, and the
unlabelled neighbours it needs (a tail's parent edge, say). Elements named on both sides are
kept: a node by its name, an edge by its ``id``; the right side may relabel them or make them
terminal. Left elements missing on the right are deleted; right elements missing on the left
are created.
"""

from __future__ import annotations

from dataclasses import dataclass

from unipolicy_rl.robots.grammar.parts import JointPart, link_kind, robogrammar_joint


@dataclass(frozen=True)
class NodeSpec:
    """A node of a rule side: ``label`` is a nonterminal (required on the left, set on the right);
    ``link`` (right side only) makes the node a terminal capsule of that link kind."""

    name: str
    label: str | None = None
    link: str | None = None

    def __post_init__(self) -> None:
        if self.label is not None and self.link is not None:
            raise ValueError(f"node {self.name!r}: a node is a nonterminal or a link, not both")
        if self.link is not None:
            link_kind(self.link)


@dataclass(frozen=True)
class EdgeSpec:
    """An edge of a rule side from ``parent`` to ``child``; ``joint`` (right side only) makes it terminal.

    ``mirror`` mirrors the joint and everything below it across the robot's sagittal plane,
    as RoboGrammar's ``mirror=true``; an edge with the same ``id`` on both sides is kept.
    """

    parent: str
    child: str
    label: str | None = None
    joint: JointPart | None = None
    mirror: bool = False
    id: str | None = None

    def __post_init__(self) -> None:
        if self.label is not None and self.joint is not None:
            raise ValueError(f"edge {self.parent}->{self.child}: an edge is a nonterminal or a joint, not both")


@dataclass(frozen=True)
class Rule:
    name: str
    left_nodes: tuple[NodeSpec, ...]
    left_edges: tuple[EdgeSpec, ...]
    right_nodes: tuple[NodeSpec, ...]
    right_edges: tuple[EdgeSpec, ...] = ()

    def __post_init__(self) -> None:
        labelled = [n for n in self.left_nodes if n.label] + [e for e in self.left_edges if e.label]
        if len(labelled) != 1:
            raise ValueError(f"rule {self.name!r}: its left side must require exactly one label, got {labelled}")
        if any(n.link for n in self.left_nodes) or any(e.joint for e in self.left_edges):
            raise ValueError(f"rule {self.name!r}: a left side matches nonterminals, it holds no parts")
        names = {n.name for n in self.left_nodes}
        for edge in self.left_edges:
            if edge.parent not in names or edge.child not in names:
                raise ValueError(f"rule {self.name!r}: left edge {edge.parent}->{edge.child} names an unknown node")
        anchor = labelled[0]
        if isinstance(anchor, NodeSpec):
            neighbours = {anchor.name} | {e.parent for e in self.left_edges} | {e.child for e in self.left_edges}
            if any(anchor.name not in (e.parent, e.child) for e in self.left_edges) or names - neighbours:
                raise ValueError(f"rule {self.name!r}: a left side is its nonterminal and that node's own edges")
        right_names = {n.name for n in self.right_nodes}
        for edge in self.right_edges:
            if edge.parent not in right_names or edge.child not in right_names:
                raise ValueError(f"rule {self.name!r}: right edge {edge.parent}->{edge.child} names an unknown node")

    @property
    def rewrites(self) -> str:
        """The nonterminal label this rule rewrites."""
        return next(element.label for element in (*self.left_nodes, *self.left_edges) if element.label)


def _rewrite_node(name: str, label: str, into: tuple[NodeSpec, ...], edges: tuple[EdgeSpec, ...] = ()) -> Rule:
    """A rule that rewrites a lone nonterminal node ``label`` (named ``label`` on both sides)."""
    return Rule(name, (NodeSpec(label, label),), (), into, edges)


def _erase_leaf(name: str, label: str) -> Rule:
    """A rule that deletes the nonterminal leaf ``label`` and the edge from its parent."""
    return Rule(name, (NodeSpec(label, label), NodeSpec("parent")), (EdgeSpec("parent", label),),
                (NodeSpec("parent"),))


def _make_joint(name: str, label: str, joint: JointPart) -> Rule:
    """A rule that turns a nonterminal edge ``label`` into ``joint``."""
    ends = (NodeSpec("parent"), NodeSpec("child"))
    return Rule(name, ends, (EdgeSpec("parent", "child", label=label, id="joint"),),
                ends, (EdgeSpec("parent", "child", joint=joint, id="joint"),))


_LIMB_MOUNT = robogrammar_joint("mount", "fixed", offset=0.5, axis_angle=(0, 1, 0, 90))

ROBOGRAMMAR_RULES: tuple[Rule, ...] = (
    _rewrite_node("make_robot", "robot",
                  (NodeSpec("head", "head"), NodeSpec("body", "body"), NodeSpec("tail", "tail")),
                  (EdgeSpec("head", "body", label="body_joint"), EdgeSpec("body", "tail", label="body_joint"))),
    Rule("append_body",
         (NodeSpec("tail", "tail"), NodeSpec("parent")), (EdgeSpec("parent", "tail", id="parent_edge"),),
         (NodeSpec("tail", "tail"), NodeSpec("body", "body"), NodeSpec("parent")),
         (EdgeSpec("parent", "body", id="parent_edge"), EdgeSpec("body", "tail", label="body_joint"))),
    _rewrite_node("make_body_with_legs", "body",
                  (NodeSpec("body", link="body"), NodeSpec("limb_mount", link="limb_mount"),
                   NodeSpec("limb_link", "limb_link"), NodeSpec("limb", "limb")),
                  (EdgeSpec("body", "limb_mount", joint=_LIMB_MOUNT),
                   EdgeSpec("body", "limb_mount", joint=_LIMB_MOUNT, mirror=True),
                   EdgeSpec("limb_mount", "limb_link", label="limb_joint"),
                   EdgeSpec("limb_link", "limb"))),
    _rewrite_node("make_body_without_legs", "body", (NodeSpec("body", link="body"),)),
    Rule("append_limb_link",
         (NodeSpec("limb", "limb"), NodeSpec("parent")), (EdgeSpec("parent", "limb"),),
         (NodeSpec("limb", "limb"), NodeSpec("limb_link", "limb_link"), NodeSpec("parent")),
         (EdgeSpec("parent", "limb_link", label="limb_joint"), EdgeSpec("limb_link", "limb"))),
    _erase_leaf("end_limb", "limb"),
    _erase_leaf("end_tail", "tail"),
    Rule("end_head", (NodeSpec("head", "head"), NodeSpec("child")), (EdgeSpec("head", "child"),),
         (NodeSpec("child"),)),
    _rewrite_node("make_normal_limb_link", "limb_link", (NodeSpec("limb_link", link="normal_limb_link"),)),
    _rewrite_node("make_long_limb_link", "limb_link", (NodeSpec("limb_link", link="long_limb_link"),)),
    _make_joint("make_fixed_body_joint", "body_joint", robogrammar_joint("fixed", "fixed")),
    _make_joint("make_roll_body_joint", "body_joint", robogrammar_joint("roll", "hinge", joint_axis=(1, 0, 0))),
    _make_joint("make_swing_body_joint", "body_joint", robogrammar_joint("swing", "hinge", joint_axis=(0, 1, 0))),
    _make_joint("make_lift_body_joint", "body_joint", robogrammar_joint("lift", "hinge", joint_axis=(0, 0, 1))),
    _make_joint("make_left_roll_limb_joint", "limb_joint",
                robogrammar_joint("left_roll", "hinge", axis_angle=(0, 1, 0, -90), joint_axis=(1, 0, 0))),
    _make_joint("make_right_roll_limb_joint", "limb_joint",
                robogrammar_joint("right_roll", "hinge", axis_angle=(0, 1, 0, 90), joint_axis=(1, 0, 0))),
    _make_joint("make_swing_limb_joint", "limb_joint", robogrammar_joint("swing", "hinge", joint_axis=(0, 1, 0))),
    _make_joint("make_acute_lift_limb_joint", "limb_joint",
                robogrammar_joint("acute_lift", "hinge", axis_angle=(0, 0, 1, 120), joint_axis=(0, 0, 1))),
    _make_joint("make_obtuse_lift_limb_joint", "limb_joint",
                robogrammar_joint("obtuse_lift", "hinge", axis_angle=(0, 0, 1, 60), joint_axis=(0, 0, 1))),
    _make_joint("make_backwards_lift_limb_joint", "limb_joint",
                robogrammar_joint("backwards_lift", "hinge", axis_angle=(0, 0, 1, -60), joint_axis=(0, 0, 1))),
)

# The thesis robot's hip turns about the limb's own axis with no turn (RoboGrammar's roll limb
# joints first turn the limb 90 degrees to lie along the body). With it the thesis robot is a
# derivation: unipolicy_rl.robots.vertebrate builds the same robot by hand.
THESIS_RULES: tuple[Rule, ...] = (
    _make_joint("make_axial_roll_limb_joint", "limb_joint",
                robogrammar_joint("axial_roll", "hinge", joint_axis=(1, 0, 0))),
)

RULES: dict[str, Rule] = {rule.name: rule for rule in (*ROBOGRAMMAR_RULES, *THESIS_RULES)}


def rule(name: str) -> Rule:
    if name not in RULES:
        raise ValueError(f"unknown rule {name!r}; rules are {sorted(RULES)}")
    return RULES[name]


def rules_for(label: str) -> tuple[str, ...]:
    """The names of the rules that rewrite the nonterminal ``label``, in rule-set order."""
    return tuple(name for name, candidate in RULES.items() if candidate.rewrites == label)
