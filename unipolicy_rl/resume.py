"""Resuming a run from its checkpoint alone: ``python train.py resume=<checkpoint>``.

A checkpoint carries the run's whole resolved config and its Hydra group choices
(``algo: ppo``, ``source: moe``, ...). A resume is the run it was: every setting is the run's
own, and the command line changes only the settings it names, each change printed
(``algo.max_kl: 0.01 -> 0.02``). What cannot change under a run's weights, optimisers and
buffers (the learner, the networks, the robot, the source, the world model: :data:`FIXED_GROUPS`
and :data:`FIXED_KEYS`) is refused by name when the command line sets it otherwise. A setting
newer than the checkpoint takes this version's default, and says so.

Two steps, because Hydra composes the config and names the run folder before ``main`` runs:
:func:`with_the_runs_groups` puts the run's group choices (and seed) on the command line before
Hydra reads it, so the config is composed from the run's groups and the folder is named after the
run; :func:`settings_for_resume` then lays the run's saved settings over that config, except
those the command line names.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path

from omegaconf import DictConfig, OmegaConf

from unipolicy_rl.policy import pin_token_critic

# Group choices a resume keeps: the run's learner, networks, robot, data source and world model.
FIXED_GROUPS = ("algo", "policy", "robot", "source", "world_model")
# Settings the run's weights, optimisers and buffers were built for (a dotted key names one
# setting, a bare group name every setting of the group).
FIXED_KEYS = ("algo.name", "algo.actor_hidden", "algo.critic_hidden", "algo.activation", "algo.num_critics",
              "algo.batch_renorm", "policy", "robot", "source.name", "source.kind", "world_model.model",
              "world_model.model_state")
# Settings a resume never takes from the checkpoint: where this run resumes from.
NOT_RESUMED = ("resume",)
# Interpolations that follow this process, not the run (where it writes): kept as this config has them.
THIS_PROCESS = ("hydra:runtime.output_dir", "now:")
RESUME_KEY = "resume"
_ABSENT = object()


def with_the_runs_groups(arguments: Sequence[str], config_dir: Path) -> list[str]:
    """``arguments`` (a train.py command line) with, before its ``resume=<checkpoint>``, the run's
    group choices and seed that it does not name itself.

    Hydra composes the config from the groups the command line selects, and names the run folder
    (``outputs/<run_name>/seed<seed>/``) before the run starts: ``resume=<a PPO run>`` alone would
    otherwise compose algo=trpo's config. A choice this version has no file for in
    ``config_dir`` is left out (then refused by name once the run starts, if it matters). A
    command line whose checkpoint cannot be read is returned unchanged: the run then reports
    that, clearly, when it loads it.
    """
    arguments = list(arguments)
    positions = [index for index, argument in enumerate(arguments) if argument.startswith(f"{RESUME_KEY}=")]
    if len(positions) != 1:
        return arguments
    path = arguments[positions[0]].split("=", 1)[1]
    from unipolicy_rl.checkpoint import load_checkpoint  # (the training stack: only when resuming)

    try:
        state = load_checkpoint(path)
    except (OSError, ValueError):
        return arguments
    named = {argument.split("=", 1)[0].lstrip("+~") for argument in arguments[1:] if "=" in argument}
    added = [f"{group}={choice}" for group, choice in run_choices(state).items()
             if group not in named and (config_dir / group / f"{choice}.yaml").is_file()]
    seed = state["config"].get("seed")
    if "seed" not in named and seed is not None:
        added.append(f"seed={seed}")
    return arguments[:positions[0]] + added + arguments[positions[0]:]


def run_choices(state: dict) -> dict[str, str]:
    """The run's own group choices (``algo: ppo``, ...): the top-level groups it selected, not
    Hydra's own nor a group's nested one (which its parent's defaults select again)."""
    return {group: choice for group, choice in state.get("choices", {}).items()
            if choice is not None and "/" not in group}


def named_keys(task_overrides: Iterable[str], groups: Iterable[str]) -> list[str]:
    """The settings a command line names (``algo.max_kl=0.02`` -> ``algo.max_kl``); a group choice
    (``algo=ppo``) names the group, not its settings."""
    keys = [item.split("=", 1)[0].lstrip("+~") for item in task_overrides]
    return [key for key in keys if key not in set(groups)]


def settings_for_resume(cfg: DictConfig, state: dict, named: Sequence[str], choices: Mapping[str, str | None],
                        path: str | Path) -> DictConfig:
    """``cfg`` (composed from this command line) with the settings of the run that saved ``state``,
    except those the command line names.

    ``named`` are the dotted settings this command line sets (:func:`named_keys`), ``choices``
    this config's group choices (Hydra's ``runtime.choices``). Every other setting is the run's,
    an interpolation of this config included (the run's ``algo.critic_fit=inline`` stays inline);
    a group whose choice this command line changes (``logger=tensorboard``) is this config's.
    Raises ValueError naming what a resume cannot change (:data:`FIXED_GROUPS`, :data:`FIXED_KEYS`).
    """
    saved = OmegaConf.create(state["config"])
    pin_token_critic(saved)  # a token policy saved before policy.critic existed keeps its critic
    changed = {group: (choice, choices[group]) for group, choice in run_choices(state).items()
               if group in choices and choices[group] != choice}
    refused = _refused(cfg, saved, named, changed)
    if refused:
        raise ValueError(f"cannot resume {str(path)!r} with another learner, network, robot, source or world model "
                         f"({'; '.join(refused)}): a resume keeps the ones the run's weights were trained with; "
                         f"drop those overrides, or start a new run")

    def followed(key: str) -> bool:
        """The command line (or this process) decides ``key``: it is this config's."""
        if _under(key, [*named, *NOT_RESUMED, *changed]):
            return True
        raw = _raw(cfg, key)
        return isinstance(raw, str) and "${" in raw and any(name in raw for name in (*THIS_PROCESS, *named))

    resumed = cfg.copy()
    changes = [f"{group}: {then} -> {now}" for group, (then, now) in changed.items()]
    whole = _other_objects(cfg, saved, followed)
    for node in whole:
        value = OmegaConf.select(saved, node).copy()
        for key in _setting_keys(OmegaConf.select(cfg, node)):
            if followed(f"{node}.{key}") and OmegaConf.select(value, key, default=_ABSENT) is not _ABSENT:
                OmegaConf.update(value, key, _raw(cfg, f"{node}.{key}"), merge=False)  # where this run writes
        OmegaConf.update(resumed, node, value, merge=False)
        changes.append(f"{node}: the checkpoint's, whole (a {value._target_})")
    newer = []
    for key in _setting_keys(cfg):
        then = _stored(saved, key)
        if _under(key, whole):
            continue
        if followed(key):
            if (_under(key, named) and not _under(key, NOT_RESUMED) and then is not _ABSENT
                    and _plain(then) != (now := _value(cfg, key))):
                changes.append(f"{key}: {_plain(then)!r} -> {now!r}")
        elif then is _ABSENT:
            if not _interpolated(cfg, key):
                newer.append(f"{key}={_value(cfg, key)!r}")
        else:
            OmegaConf.update(resumed, key, then, merge=False)
    unused = [key for key in _setting_keys(saved) if not _under(key, [*changed, *whole, *NOT_RESUMED])
              and not _present(cfg, key)]
    for change in changes:
        print(f"resume: {change}")
    if newer:
        print(f"resume: {', '.join(newer)}: newer than the checkpoint, this version's default")
    if unused:
        print(f"resume: the checkpoint's {', '.join(unused)} are not settings of this version: not used")
    return resumed


def _refused(cfg: DictConfig, saved: DictConfig, named: Sequence[str], changed: Mapping[str, tuple]) -> list[str]:
    """What this command line changes that a resume cannot: a group of :data:`FIXED_GROUPS`
    chosen otherwise, a setting of :data:`FIXED_KEYS` set otherwise."""
    refused = [f"{group}={now} here, {group}={then} in the checkpoint" for group, (then, now) in changed.items()
               if group in FIXED_GROUPS]
    for key in named:
        if _under(key, FIXED_KEYS) or any(_under(fixed, (key,)) for fixed in FIXED_KEYS):
            ours = _plain(OmegaConf.select(cfg, key, default=None, throw_on_resolution_failure=False))
            then = _plain(_stored(saved, key))
            if then is not _ABSENT and ours != then:
                refused.append(f"{key}: {ours!r} here, {then!r} in the checkpoint")
    return refused


def _other_objects(cfg: DictConfig, saved: DictConfig, followed) -> list[str]:
    """The nodes the run built from another class than this config does (a checkpoint from before
    group choices were saved, with another logger): taken whole, not mixed with this config's."""
    nodes = []
    for key in _setting_keys(saved):
        node = key.rpartition(".")[0]
        if key.endswith("._target_") and not followed(key) and \
                OmegaConf.is_dict(OmegaConf.select(cfg, node, default=None)) and \
                OmegaConf.select(cfg, key, default=_ABSENT) != OmegaConf.select(saved, key):
            nodes.append(node)
    return nodes


def record_resumed_config(cfg: DictConfig, run_dir: Path, output_subdir: str | None) -> None:
    """Writes the resumed run's config over the one Hydra saved in the run folder
    (``.hydra/config.yaml``, composed before the run's own settings were laid over it), so what
    reads the folder (the report: the run's epochs, source, seed) sees the run that trains there."""
    if output_subdir is not None:
        OmegaConf.save(cfg, run_dir / output_subdir / "config.yaml")


def _under(key: str, names: Iterable[str]) -> bool:
    """Whether ``key`` is one of ``names`` or a setting inside one of them."""
    return any(key == name or key.startswith(f"{name}.") for name in names)


def _setting_keys(node: DictConfig, prefix: str = "") -> list[str]:
    """The dotted keys of ``node``'s settings: its leaves, a list counting as one."""
    keys = []
    for name in node:
        key, child = f"{prefix}{name}", node._get_node(name)
        if OmegaConf.is_dict(child) and not child._is_interpolation() and len(child):
            keys.extend(_setting_keys(child, f"{key}."))
        else:
            keys.append(key)
    return keys


def _parent(cfg: DictConfig, key: str):
    parent, _, name = key.rpartition(".")
    node = OmegaConf.select(cfg, parent, default=None, throw_on_resolution_failure=False) if parent else cfg
    return node, name


def _stored(saved: DictConfig, key: str):
    """The saved setting ``key`` (an interpolation as written: a config saved unresolved), or _ABSENT."""
    if not _present(saved, key):
        return _ABSENT
    return _raw(saved, key) if _interpolated(saved, key) else OmegaConf.select(saved, key)


def _present(cfg: DictConfig, key: str) -> bool:
    node, name = _parent(cfg, key)
    return OmegaConf.is_dict(node) and name in node


def _interpolated(cfg: DictConfig, key: str) -> bool:
    node, name = _parent(cfg, key)
    return OmegaConf.is_dict(node) and name in node and OmegaConf.is_interpolation(node, name)


def _raw(cfg: DictConfig, key: str):
    node, name = _parent(cfg, key)
    return node._get_node(name)._value() if OmegaConf.is_dict(node) and name in node else None


def _value(cfg: DictConfig, key: str):
    """``key``'s value, resolved where it can be (a ``${hydra:...}`` outside a run stays as written)."""
    try:
        return _plain(OmegaConf.select(cfg, key))
    except Exception:  # noqa: BLE001 - an interpolation that resolves only inside a Hydra run
        return _raw(cfg, key)


def _plain(value):
    return OmegaConf.to_container(value, resolve=True) if OmegaConf.is_config(value) else value
