"""One source of defaults: a class's defaults and its base yaml never disagree.

Every class a ``conf/`` yaml instantiates (``_target_``) has ONE base yaml node that lists every
constructor argument (but those the factory fills, :data:`FILLED_BY_FACTORY`) with the class's
default value. Other yamls either inherit from that base through Hydra's defaults list and set
only what differs (``imagination/short_branch.yaml`` from ``imagination/branch.yaml``), or are
another choice of the same class whose differing values are deliberate and declared here
(:data:`VARIANTS`). A new ``_target_`` with no entry in :data:`BASES` fails the test.
"""

from __future__ import annotations

import dataclasses
import inspect
import shutil
from pathlib import Path

import pytest
from hydra import compose, initialize_config_dir
from hydra.utils import get_object
from omegaconf import DictConfig, OmegaConf

ROOT = Path(__file__).resolve().parents[1]
CONF = ROOT / "conf"
# Constructor arguments a factory fills (make_dynamics_model): never in a yaml.
FILLED_BY_FACTORY = {"layout", "action_dim"}
# Hydra's own keys of a node.
HYDRA_KEYS = {"_target_", "_convert_", "_partial_", "_recursive_", "_args_", "defaults"}

# target -> (its base yaml under conf/, the node's path in it; "" is the file itself).
BASES: dict[str, tuple[str, str]] = {
    "unipolicy_rl.envs.RobotSettings": ("robot/vertebrate.yaml", "settings"),
    "unipolicy_rl.envs.PhysicsSettings": ("robot/vertebrate.yaml", "physics"),
    "unipolicy_rl.envs.RewardWeights": ("robot/vertebrate.yaml", "reward"),
    "unipolicy_rl.robots.grammar.split_morphologies": ("robot/grammar.yaml", "split"),
    "unipolicy_rl.robots.grammar.SizeLimits": ("robot/grammar.yaml", "split.held_out_limits"),
    "unipolicy_rl.envs.DesignDistribution": ("design/se.yaml", ""),
    "unipolicy_rl.envs.DesignDistribution.fixed": ("design/fixed.yaml", ""),  # no defaults: both are required
    "unipolicy_rl.collectors.ImaginationSettings": ("imagination/branch.yaml", ""),
    "unipolicy_rl.collectors.HorizonSchedule": ("imagination/branch.yaml", "horizon"),
    "unipolicy_rl.collectors.StoppingRule": ("imagination/branch.yaml", "stopping"),
    "unipolicy_rl.objectives.adaptive_kl.AdaptiveKL": ("imagination/branch.yaml", "adaptive_kl"),
    "unipolicy_rl.world_models.GaussianEnsemble": ("world_model/moe.yaml", "model"),
    "unipolicy_rl.world_models.ModelTrainer": ("world_model/moe_thesis.yaml", "trainer"),
    "unipolicy_rl.world_models.CellEnsemble": ("world_model/moe_thesis.yaml", "model"),
    "unipolicy_rl.world_models.TokenEnsemble": ("world_model/robot/grammar.yaml", "model"),
    "unipolicy_rl.world_models.PCEDynamics": ("world_model/pce.yaml", "model"),
    "unipolicy_rl.world_models.ClosedFormTrainer": ("world_model/pce.yaml", "trainer"),
    "unipolicy_rl.world_models.ThesisPCEDynamics": ("world_model/pce_thesis.yaml", "model"),
    "unipolicy_rl.world_models.SparsePCEDynamics": ("world_model/pce_sparse.yaml", "model"),
    "unipolicy_rl.token_networks.TokenTransformerSettings": ("policy/token_transformer.yaml", "network"),
}
# Every other node with a ``_target_``: a deliberate choice of the same class, and the values in
# which it differs from the class's defaults (anything else it sets must equal the default).
VARIANTS: dict[tuple[str, str], dict[str, object]] = {
    ("design/de.yaml", ""): {"length_range": [0.175, 0.175], "density_range": [0.5, 0.5]},  # DE: the SE centre
    ("robot/grammar.yaml", "split.train_limits"): {"segments": [2, 4], "leg_pairs": [1, 2]},  # split's TRAIN_LIMITS
    ("robot/grammar.yaml", "physics"): {"max_joint_speed": 10.0},  # the vertebrate's, with servos' top speed
    ("robot/grammar.yaml", "reward"): {},
    # the default MOE's fits: checks every 25 steps on 2,000 held-out rows, flat in the buffer; two threads;
    # bfloat16 where the CPU computes in it
    ("world_model/moe.yaml", "trainer"): {"check_every": 25, "validation_rows": 2000, "num_threads": 2,
                                          "precision": "auto"},
    ("world_model/pce_thesis.yaml", "trainer"): {"oversampling": 20.0},  # the thesis PCE's correlated samples
    ("world_model/pce_sparse.yaml", "trainer"): {},
}
# Targets outside this project, configured as their own documentation says: no defaults of ours.
EXTERNAL_PREFIXES = ("torchrl.record.loggers.",)
# The default of an argument that has none.
REQUIRED = object()


def yaml_files(conf: Path = CONF) -> list[Path]:
    return sorted(conf.rglob("*.yaml"))


def relative(path: Path, conf: Path = CONF) -> str:
    return path.relative_to(conf).as_posix()


def target_nodes(conf: Path = CONF):
    """``(yaml under conf/, node path, target)`` of every ``_target_`` in every yaml."""
    for path in yaml_files(conf):
        yield from _targets(OmegaConf.load(path), relative(path, conf), "")


def _targets(node, file: str, path: str):
    if OmegaConf.is_dict(node):
        if "_target_" in node:
            yield file, path, node._target_
        for key in node:
            if key != "defaults":
                yield from _targets(node._get_node(key), file, f"{path}.{key}" if path else str(key))


def context(conf: Path = CONF) -> DictConfig:
    """What a lone yaml's interpolations point to: conf/config.yaml's values and ``robot``."""
    root = OmegaConf.load(conf / "config.yaml")
    for key in ("defaults", "hydra"):
        root.pop(key, None)
    root.robot = OmegaConf.load(conf / "robot" / "vertebrate.yaml")
    return root


def resolved(file: str, path: str, conf: Path = CONF):
    """The node at ``path`` of ``conf/<file>``, its interpolations resolved against :func:`context`."""
    node = OmegaConf.load(conf / file)
    if "defaults" in node:
        node.pop("defaults")
    if path:
        node = OmegaConf.select(node, path)
    root = context(conf)
    root._node_under_test = node
    return OmegaConf.to_container(root._node_under_test, resolve=True)


def parameters(target: str) -> dict[str, object]:
    """Constructor argument -> default (:data:`REQUIRED` if none), less :data:`FILLED_BY_FACTORY`."""
    built = get_object(target)
    if dataclasses.is_dataclass(built):
        found = {}
        for field in dataclasses.fields(built):
            if not field.init:
                continue
            if field.default is not dataclasses.MISSING:
                found[field.name] = field.default
            elif field.default_factory is not dataclasses.MISSING:
                found[field.name] = field.default_factory()
            else:
                found[field.name] = REQUIRED
    else:
        found = {name: REQUIRED if p.default is inspect.Parameter.empty else p.default
                 for name, p in inspect.signature(built).parameters.items()
                 if p.kind not in (inspect.Parameter.VAR_POSITIONAL, inspect.Parameter.VAR_KEYWORD)}
    return {name: value for name, value in found.items() if name not in FILLED_BY_FACTORY}


def same(value, default) -> bool:
    """A yaml value equals a default: lists as tuples, a nested dataclass as its own node."""
    if dataclasses.is_dataclass(default) and not isinstance(default, type):
        return isinstance(value, dict) and not node_disagreements(value, type(default), base=True, defaults=default)
    if isinstance(default, (list, tuple)):
        return isinstance(value, (list, tuple)) and len(value) == len(default) and all(
            same(v, d) for v, d in zip(value, default, strict=True))
    if isinstance(default, bool) or isinstance(value, bool):
        return value is default
    return value == default


def node_disagreements(node: dict, target: str | type, base: bool, defaults=None,
                       deliberate: dict | None = None) -> list[str]:
    """What is wrong with a yaml node of ``target``: an argument the base does not list, a key that
    is no argument, a value that is not the default (on a variant, one not declared deliberate)."""
    cls = target if isinstance(target, type) else get_object(target)
    name = f"{cls.__module__}.{cls.__qualname__}"
    params = parameters(name)
    if defaults is not None:  # a nested dataclass default: its own fields are the defaults here
        params = {field.name: getattr(defaults, field.name) for field in dataclasses.fields(defaults)}
    if "_target_" in node and get_object(node["_target_"]) != cls:
        return [f"_target_ is {node['_target_']}, the default is a {name}"]
    problems = [f"{key}: not an argument of {name}" for key in node if key not in HYDRA_KEYS and key not in params]
    deliberate = deliberate or {}
    for key, default in params.items():
        if key not in node:
            if base:
                problems.append(f"{key}: missing (the class's default is {_show(default)})")
            continue
        if default is REQUIRED:
            continue
        if key in deliberate:
            if not same(node[key], deliberate[key]) or same(node[key], default):
                problems.append(f"{key}: {node[key]!r} is not the declared deliberate {deliberate[key]!r} "
                                f"(default {_show(default)})")
        elif not same(node[key], default):
            problems.append(f"{key}: yaml {node[key]!r} != default {_show(default)}")
    problems += [f"{key}: declared deliberate but not set" for key in deliberate if key not in node]
    return problems


def _show(default) -> str:
    return "none (required)" if default is REQUIRED else repr(default)


def uncovered_targets(conf: Path = CONF) -> list[str]:
    """``_target_`` nodes that are neither a class's base, nor a declared variant, nor external."""
    found = []
    for file, path, target in target_nodes(conf):
        if target.startswith(EXTERNAL_PREFIXES):
            continue
        if target not in BASES:
            found.append(f"{file}:{path or '<root>'}: {target} has no base yaml in BASES")
        elif BASES[target] != (file, path) and (file, path) not in VARIANTS:
            found.append(f"{file}:{path or '<root>'}: another {target} node, neither its base nor in VARIANTS")
    return found


# ---- The checks themselves


def test_every_target_in_conf_has_a_base_or_a_declared_variant():
    assert not uncovered_targets()


def test_every_table_entry_is_a_target_of_conf():
    nodes = {(file, path): target for file, path, target in target_nodes()}
    for target, place in BASES.items():
        assert nodes.get(place) == target, (target, place)
    for place in VARIANTS:
        assert place in nodes, place


@pytest.mark.parametrize("target", sorted(BASES))
def test_base_yaml_lists_every_argument_with_the_class_default(target):
    file, path = BASES[target]
    assert not node_disagreements(resolved(file, path), target, base=True)


@pytest.mark.parametrize("place", sorted(VARIANTS), ids=lambda place: ":".join(place))
def test_a_variant_differs_from_the_defaults_only_where_declared(place):
    file, path = place
    node = resolved(file, path)
    assert not node_disagreements(node, node["_target_"], base=False, deliberate=VARIANTS[place])


def inheriting_yamls():
    """``(variant, base)`` yamls of one group where the variant's defaults list names the base."""
    for path in yaml_files():
        for entry in OmegaConf.load(path).get("defaults", []):
            if isinstance(entry, str) and entry != "_self_":
                yield relative(path), relative(path.parent / f"{entry}.yaml")


def changed_leaves(variant, base, prefix=""):
    """Leaves of ``variant`` whose value equals ``base``'s: a variant sets only what differs."""
    for key, value in variant.items():
        path = f"{prefix}{key}"
        if isinstance(value, dict):
            yield from changed_leaves(value, base.get(key, {}), path + ".")
        elif key in base and same(value, base[key]):
            yield f"{path} restates the base's {base[key]!r}"


def test_inheriting_yamls_set_only_what_differs_from_their_base():
    pairs = list(inheriting_yamls())
    assert ("imagination/episode.yaml", "imagination/branch.yaml") in pairs
    for variant, base in pairs:
        assert not list(changed_leaves(resolved(variant, ""), resolved(base, ""))), variant


# ---- The checks can fail


def test_a_changed_default_a_missing_argument_and_a_typo_are_flagged():
    node = resolved("world_model/moe_thesis.yaml", "trainer")
    assert not node_disagreements(node, "unipolicy_rl.world_models.ModelTrainer", base=True)
    changed = {**node, "max_epochs": 50}
    assert node_disagreements(changed, "unipolicy_rl.world_models.ModelTrainer", base=True) == [
        "max_epochs: yaml 50 != default 30"]
    missing = {key: value for key, value in node.items() if key != "patience"}
    assert node_disagreements(missing, "unipolicy_rl.world_models.ModelTrainer", base=True) == [
        "patience: missing (the class's default is 3)"]
    typo = {**node, "max_epoch": 30}
    assert node_disagreements(typo, "unipolicy_rl.world_models.ModelTrainer", base=True) == [
        "max_epoch: not an argument of unipolicy_rl.world_models.trainer.ModelTrainer"]


def test_a_nested_dataclass_default_is_compared_field_by_field():
    node = resolved("imagination/branch.yaml", "")
    node["horizon"] = {**node["horizon"], "end": 10}
    assert node_disagreements(node, "unipolicy_rl.collectors.ImaginationSettings", base=True) == [
        f"horizon: yaml {node['horizon']!r} != default HorizonSchedule(start=10, end=25, first_epoch=5, "
        "last_epoch=30)"]


def test_an_undeclared_difference_in_a_variant_is_flagged():
    node = {**resolved("world_model/pce_thesis.yaml", "trainer"), "validation_fraction": 0.3}
    assert node_disagreements(node, node["_target_"], base=False, deliberate={"oversampling": 20.0}) == [
        "validation_fraction: yaml 0.3 != default 0.2"]
    node = resolved("world_model/pce_thesis.yaml", "trainer")
    assert node_disagreements(node, node["_target_"], base=False, deliberate={})  # 20.0 is not declared


def test_an_inheriting_yaml_that_restates_its_base_is_flagged():
    variant = {**resolved("imagination/short_branch.yaml", ""), "buffer_capacity": 200000}
    assert list(changed_leaves(variant, resolved("imagination/branch.yaml", ""))) == [
        "buffer_capacity restates the base's 200000"]


def test_a_new_target_without_a_base_is_flagged(tmp_path):
    conf = tmp_path / "conf"
    shutil.copytree(CONF, conf)
    assert not uncovered_targets(conf)
    (conf / "world_model" / "new.yaml").write_text(
        "model:\n  _target_: unipolicy_rl.world_models.GaussianEnsemble\n  members: 3\n"
        "trainer:\n  _target_: unipolicy_rl.world_models.FitReport\n")
    assert uncovered_targets(conf) == [
        "world_model/new.yaml:model: another unipolicy_rl.world_models.GaussianEnsemble node, neither its base nor "
        "in VARIANTS",
        "world_model/new.yaml:trainer: unipolicy_rl.world_models.FitReport has no base yaml in BASES",
    ]


# ---- Model grids cover the design space, not the evaluation's ranges


def composed(overrides):
    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        return compose("config", overrides=list(overrides))


@pytest.mark.parametrize("source, world_model", [("moe", "moe_thesis"), ("pce", "pce_thesis")])
def test_model_grids_follow_design_space_not_evaluation(source, world_model):
    plain = composed([f"source={source}", f"world_model={world_model}"])
    widened = composed([f"source={source}", f"world_model={world_model}", "evaluation.length_range=[0.1,0.3]"])
    assert list(widened.evaluation.length_range) == [0.1, 0.3]
    assert list(widened.world_model.model.length_range) == list(plain.world_model.model.length_range) == [0.15, 0.2]
    assert list(widened.world_model.model.density_range) == list(plain.design_space.density_range)
    # ... while the design space itself does move the grid (the assertion above could fail).
    moved = composed([f"source={source}", f"world_model={world_model}", "design_space.length_range=[0.1,0.3]"])
    assert list(moved.world_model.model.length_range) == [0.1, 0.3]
