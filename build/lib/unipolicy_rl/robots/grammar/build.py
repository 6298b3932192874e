"""A derived robot graph as a :class:`RobotDescription`: capsules sized by the design, joints named.

The graph is a DAG (a mirrored leg pair shares one subgraph); the description is its tree,
each shared subgraph read once per edge into it, mirrored where the edges say so, as
RoboGrammar builds its robots. Links are ordered as the thesis robot's: the body segments
from head to tail, then each segment's legs, left before right, each leg from its mount out.
"""

from __future__ import annotations

from collections.abc import Collection, Iterable
from dataclasses import dataclass

from unipolicy_rl.robots.description import Joint, Link, RobotDescription
from unipolicy_rl.robots.grammar.derivation import GraphEdge, RobotGraph, derive
from unipolicy_rl.robots.grammar.parts import LinkKind, link_kind

BODY = "body"


def _joint(name: str, edge: GraphEdge, parent: str, child: str, mirrored: bool, actuated) -> Joint:
    part = edge.joint.mirrored() if mirrored else edge.joint
    return Joint(name, part.kind, parent, child, part.attach_fraction, part.rpy, part.axis,
                 actuated=part.kind == "hinge" and actuated(name))


@dataclass(frozen=True)
class PartKinds:
    """What each part of a derived robot is, in :func:`describe`'s order: the :data:`LINK_KINDS`
    name of each link and the joint type (``roll``, ``obtuse_lift``, ...) of each joint.

    A :class:`RobotDescription` keeps only sizes and frames; a policy that reads a robot link by
    link also wants to know what each link is, and an env that drives some joint types only needs
    each joint's type.
    """

    links: tuple[str, ...]
    joints: tuple[str, ...]


def _graph(derivation: RobotGraph | Iterable[str]) -> RobotGraph:
    graph = derivation if isinstance(derivation, RobotGraph) else derive(derivation)
    if not graph.is_terminal:
        pending = sorted({graph.label_of(item) for item in graph.nonterminals()})
        raise ValueError(f"the graph still has nonterminals {pending}; derive it to the end first")
    return graph


def _tree(graph: RobotGraph) -> tuple[list[tuple[str, LinkKind]], list[tuple[str, GraphEdge, str, str, bool]]]:
    """The graph read as a tree: ``(link name, kind)`` per link and ``(joint name, edge, parent,
    child, mirrored)`` per joint, in the order of the module docstring."""
    (root,) = graph.roots()

    spine: list[int] = [root]
    spine_edges: list[int] = []
    while True:
        onward = [e for e in graph.out_edges(spine[-1]) if graph.nodes[graph.edges[e].child].link == BODY]
        if not onward:
            break
        spine_edges.append(onward[0])
        spine.append(graph.edges[onward[0]].child)

    links: list[tuple[str, LinkKind]] = []
    joints: list[tuple[str, GraphEdge, str, str, bool]] = []

    def add_link(link_name: str, node: int) -> None:
        links.append((link_name, link_kind(graph.nodes[node].link)))

    for index, node in enumerate(spine):
        add_link(f"body_{index}", node)
    for index, edge_id in enumerate(spine_edges, start=1):
        edge = graph.edges[edge_id]
        joints.append((f"body_{edge.joint.name}_{index}", edge, f"body_{index - 1}", f"body_{index}", edge.mirror))

    pair = 0
    for index, node in enumerate(spine):
        legs = [e for e in graph.out_edges(node) if e not in spine_edges]
        for edge_id in legs:
            edge = graph.edges[edge_id]
            leg = f"leg_{pair}_{'right' if edge.mirror else 'left'}"
            add_link(f"{leg}_mount", edge.child)
            joints.append((f"{leg}_mount", edge, f"body_{index}", f"{leg}_mount", edge.mirror))
            parent_name, below, mirrored, depth = f"{leg}_mount", edge.child, edge.mirror, 0
            while onward := graph.out_edges(below):
                if len(onward) > 1:
                    raise ValueError(f"leg {leg!r} branches; a limb is a chain of links")
                depth += 1
                limb_edge = graph.edges[onward[0]]
                mirrored = mirrored != limb_edge.mirror
                child_name = f"{leg}_link_{depth}"
                add_link(child_name, limb_edge.child)
                joints.append((f"{leg}_{limb_edge.joint.name}_{depth}", limb_edge, parent_name, child_name, mirrored))
                parent_name, below = child_name, limb_edge.child
        if legs:
            pair += 1
    return links, joints


def part_kinds(derivation: RobotGraph | Iterable[str]) -> PartKinds:
    """The kind of each link and the type of each joint of the robot ``derivation`` yields."""
    links, joints = _tree(_graph(derivation))
    return PartKinds(tuple(kind.name for _, kind in links), tuple(edge.joint.name for _, edge, *_ in joints))


def describe(
    derivation: RobotGraph | Iterable[str],
    length: float = 0.175,
    density: float = 0.5,
    actuated: Collection[str] | None = None,
    name: str = "grammar_robot",
) -> RobotDescription:
    """The robot a derivation (rule names, or the graph they derive) yields at design (``length``, ``density``).

    ``actuated`` names the hinges the policy drives; None drives every hinge, as RoboGrammar
    does. Body segments are ``body_<i>`` joined by ``body_<joint type>_<i>``; leg pair ``k``
    (counted from the head) has legs ``leg_<k>_left`` and ``leg_<k>_right``, each a
    ``<leg>_mount`` and links ``<leg>_link_<j>`` on joints ``<leg>_<joint type>_<j>``.
    """
    tree_links, joints = _tree(_graph(derivation))
    links = [Link(link_name, length * kind.length_factor, kind.radius, density * kind.density_factor)
             for link_name, kind in tree_links]

    hinges = [joint_name for joint_name, edge, *_ in joints if edge.joint.kind == "hinge"]
    if actuated is not None:
        unknown = sorted(set(actuated) - set(hinges))
        if unknown:
            raise ValueError(f"unknown actuated joint(s) {unknown}; hinges are {hinges}")
    drives = (lambda _: True) if actuated is None else set(actuated).__contains__
    built = tuple(_joint(joint_name, edge, parent, child, mirrored, drives)
                  for joint_name, edge, parent, child, mirrored in joints)
    return RobotDescription(name, tuple(links), built)
