"""Derivations: a sequence of rule names applied, each to the leftmost nonterminal, from ``robot``.

Fixing where each rule applies makes a derivation a plain list of names and gives every robot
exactly one derivation, so derivations can be counted, enumerated and compared. "Leftmost" is
the robot's reading order: from the head along the body, a body segment's legs before the
segments behind it (a node's newest edges first), and every nonterminal node before any
nonterminal joint, so the derivation builds the structure first and then chooses its joints in
the same order. Choosing joints last also means no choice is spent on a joint that a later
``end_head`` or ``end_tail`` deletes.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Iterable
from dataclasses import dataclass, field

from unipolicy_rl.robots.grammar.parts import JointPart
from unipolicy_rl.robots.grammar.rules import Rule, rule, rules_for

START = "robot"


@dataclass(frozen=True)
class GraphNode:
    """A nonterminal (``label``) or a terminal capsule (``link``, a link kind's name)."""

    label: str | None = None
    link: str | None = None


@dataclass(frozen=True)
class GraphEdge:
    """A nonterminal (``label``) or a terminal ``joint``; an edge with neither is a plain
    attachment that only nonterminals use (a limb's last link to the ``limb`` still to come)."""

    parent: int
    child: int
    label: str | None = None
    joint: JointPart | None = None
    mirror: bool = False


@dataclass
class RobotGraph:
    """A sentential form of the grammar: nodes and edges keyed by id, ids in creation order."""

    nodes: dict[int, GraphNode] = field(default_factory=lambda: {0: GraphNode(START)})
    edges: dict[int, GraphEdge] = field(default_factory=dict)
    next_id: int = 1

    def new_id(self) -> int:
        self.next_id += 1
        return self.next_id - 1

    def in_edges(self, node: int) -> list[int]:
        return [edge_id for edge_id, edge in self.edges.items() if edge.child == node]

    def out_edges(self, node: int) -> list[int]:
        return [edge_id for edge_id, edge in self.edges.items() if edge.parent == node]

    def roots(self) -> list[int]:
        children = {edge.child for edge in self.edges.values()}
        return sorted(node for node in self.nodes if node not in children)

    def reading_order(self) -> list[tuple[str, int]]:
        """Every node and edge once, as ``("node", id)`` or ``("edge", id)``: pre-order from the
        root, a node's newest edge first (a shared node, a mirrored leg pair's, is read once)."""
        order: list[tuple[str, int]] = []
        seen: set[int] = set()
        outgoing: dict[int, list[int]] = {}
        for edge_id in sorted(self.edges, reverse=True):
            outgoing.setdefault(self.edges[edge_id].parent, []).append(edge_id)

        def visit(node: int) -> None:
            seen.add(node)
            order.append(("node", node))
            for edge_id in outgoing.get(node, ()):
                order.append(("edge", edge_id))
                if self.edges[edge_id].child not in seen:
                    visit(self.edges[edge_id].child)

        for root in self.roots():
            visit(root)
        return order

    def nonterminals(self) -> list[tuple[str, int]]:
        """The nonterminals in derivation order: nodes first, then edges, each in reading order."""
        order = self.reading_order()
        nodes = [item for item in order if item[0] == "node" and self.nodes[item[1]].label]
        edges = [item for item in order if item[0] == "edge" and self.edges[item[1]].label]
        return nodes + edges

    def label_of(self, item: tuple[str, int]) -> str:
        kind, key = item
        return (self.nodes[key] if kind == "node" else self.edges[key]).label

    @property
    def is_terminal(self) -> bool:
        return not self.nonterminals()


def leftmost(graph: RobotGraph) -> tuple[str, int] | None:
    """The nonterminal the next rule rewrites, or None when the graph is a robot."""
    first_edge = None
    for item in graph.reading_order():
        kind, key = item
        if kind == "node" and graph.nodes[key].label:
            return item
        if kind == "edge" and first_edge is None and graph.edges[key].label:
            first_edge = item
    return first_edge


def applicable_rules(graph: RobotGraph) -> tuple[str, ...]:
    """The rules that can rewrite the leftmost nonterminal (none once the graph is terminal)."""
    item = leftmost(graph)
    return () if item is None else rules_for(graph.label_of(item))


def _match(graph: RobotGraph, chosen: Rule, item: tuple[str, int]) -> tuple[dict[str, int], list[int]]:
    """Maps the rule's left nodes to graph nodes and its left edges to graph edges, anchored at ``item``."""
    kind, key = item
    nodes: dict[str, int] = {}
    edges: list[int] = []
    if kind == "edge":
        (spec,) = chosen.left_edges
        nodes = {spec.parent: graph.edges[key].parent, spec.child: graph.edges[key].child}
        return nodes, [key]
    anchor = next(spec.name for spec in chosen.left_nodes if spec.label)
    nodes[anchor] = key
    for spec in chosen.left_edges:
        incoming = spec.child == anchor
        candidates = graph.in_edges(key) if incoming else graph.out_edges(key)
        if len(candidates) != 1:
            direction = "incoming" if incoming else "outgoing"
            raise ValueError(f"rule {chosen.name!r} needs one {direction} edge at {graph.label_of(item)!r}, "
                             f"found {len(candidates)}")
        edge = graph.edges[candidates[0]]
        nodes[spec.parent if incoming else spec.child] = edge.parent if incoming else edge.child
        edges.append(candidates[0])
    return nodes, edges


def apply_rule(graph: RobotGraph, name: str) -> None:
    """Rewrites ``graph``'s leftmost nonterminal with rule ``name``, in place (a rule that does
    not apply raises before anything changes)."""
    chosen = rule(name)
    item = leftmost(graph)
    if item is None:
        raise ValueError(f"rule {name!r}: the robot is complete, nothing is left to rewrite")
    label = graph.label_of(item)
    if chosen.rewrites != label:
        raise ValueError(f"rule {name!r} rewrites {chosen.rewrites!r}, but the leftmost nonterminal is {label!r}; "
                         f"rules for it: {list(rules_for(label))}")
    matched_nodes, matched_edges = _match(graph, chosen, item)
    right_names = {spec.name for spec in chosen.right_nodes}
    doomed = {left_name: node_id for left_name, node_id in matched_nodes.items() if left_name not in right_names}
    for left_name, node_id in doomed.items():
        dangling = sorted(set(graph.in_edges(node_id) + graph.out_edges(node_id)) - set(matched_edges))
        if dangling:
            raise ValueError(f"rule {name!r} deletes {left_name!r}, which has edges the rule does not match: "
                             f"{dangling}")

    node_ids: dict[str, int] = {}
    for spec in chosen.right_nodes:
        if spec.name in matched_nodes:
            node_id = matched_nodes[spec.name]
            if spec.label is not None or spec.link is not None:  # else the node stays as it was
                graph.nodes[node_id] = GraphNode(spec.label, spec.link)
        else:
            node_id = graph.new_id()
            graph.nodes[node_id] = GraphNode(spec.label, spec.link)
        node_ids[spec.name] = node_id

    # An edge with the same id on both sides is kept (its place among its parent's edges too),
    # moved to the right side's ends; the other left edges go, the other right edges are new.
    kept = {spec.id: spec for spec in chosen.right_edges if spec.id is not None}
    for spec, edge_id in zip(chosen.left_edges, matched_edges, strict=True):
        if spec.id in kept:
            new = kept.pop(spec.id)
            edge = dataclasses.replace(graph.edges[edge_id], parent=node_ids[new.parent], child=node_ids[new.child])
            if new.label is not None or new.joint is not None:
                edge = dataclasses.replace(edge, label=new.label, joint=new.joint)
            graph.edges[edge_id] = edge
        else:
            del graph.edges[edge_id]
    for spec in chosen.right_edges:
        if spec.id is None or spec.id in kept:
            graph.edges[graph.new_id()] = GraphEdge(node_ids[spec.parent], node_ids[spec.child], spec.label,
                                                    spec.joint, spec.mirror)

    for node_id in doomed.values():
        del graph.nodes[node_id]


def derive(derivation: Iterable[str], complete: bool = True) -> RobotGraph:
    """Applies ``derivation`` from the start symbol; with ``complete`` the result must be a robot."""
    if isinstance(derivation, str):
        raise ValueError(f"a derivation is a sequence of rule names, got the string {derivation!r}")
    graph = RobotGraph()
    steps = list(derivation)
    for step, name in enumerate(steps):
        try:
            apply_rule(graph, name)
        except ValueError as error:
            raise ValueError(f"derivation step {step} ({name!r}): {error}") from None
    if complete and not graph.is_terminal:
        pending = sorted({graph.label_of(item) for item in graph.nonterminals()})
        raise ValueError(f"derivation of {len(steps)} steps leaves nonterminals {pending}; "
                         f"the next step may be one of {list(applicable_rules(graph))}")
    return graph
