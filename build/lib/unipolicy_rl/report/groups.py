"""Which runs may share a report, and which of them are seeds of the same thing.

Rewards and metres are only comparable for one robot with one reward: runs that differ in
``robot`` (links, physics, reward weights, episode length) are refused. Everything else that
differs is what the sweep compares: runs are grouped by their whole config less the seed and
the settings that do not change training, and a group is named by its source plus whatever
sets it apart from the other groups of that source (``se algo.max_kl=0.02``).
"""

from __future__ import annotations

from collections.abc import Sequence

from unipolicy_rl.report.runs import ReportError, Run

# Config subtrees that must agree across a report: the robot's build, physics and reward.
ROBOT_KEYS = ("robot.settings", "robot.physics", "robot.reward", "robot.episode_length")
# Config keys that do not change what a run learns.
NOT_TRAINING = ("seed", "resume", "progress_bar", "workers", "device", "checkpoint_every", "logger", "evaluation")


def flatten(config: dict, prefix: str = "") -> dict[str, object]:
    """Dotted keys to leaf values; lists become tuples so values compare and hash."""
    flat = {}
    for key, value in config.items():
        name = f"{prefix}{key}"
        if isinstance(value, dict):
            flat.update(flatten(value, f"{name}."))
        else:
            flat[name] = tuple(value) if isinstance(value, list) else value
    return flat


def _under(key: str, prefixes: Sequence[str]) -> bool:
    return any(key == prefix or key.startswith(f"{prefix}.") for prefix in prefixes)


def check_same_robot(runs: Sequence[Run], where: str) -> None:
    """Raises :class:`ReportError` naming ``where``, the first robot setting that differs and the runs."""
    flats = [(run, flatten(run.config)) for run in runs]
    keys = sorted({key for _, flat in flats for key in flat if _under(key, ROBOT_KEYS)})
    for key in keys:
        by_value: dict[str, Run] = {}
        for run, flat in flats:
            by_value.setdefault(repr(flat.get(key, "<unset>")), run)
        if len(by_value) > 1:
            examples = "; ".join(f"{value} in {run.name}" for value, run in list(by_value.items())[:3])
            raise ReportError(f"{where}: runs of different robots or reward weights cannot be "
                              f"compared ({key} is {examples}); report them separately")


def group_runs(runs: Sequence[Run]) -> dict[str, list[Run]]:
    """Label -> runs (seeds of one training setup), labels sorted, runs in the given order."""
    flats = {id(run): {key: value for key, value in flatten(run.config).items() if not _under(key, NOT_TRAINING)}
             for run in runs}
    by_source: dict[str, list[Run]] = {}
    for run in runs:
        by_source.setdefault(run.source, []).append(run)
    groups: dict[str, list[Run]] = {}
    for source, members in by_source.items():
        keys = sorted({key for run in members for key in flats[id(run)]})
        varying = [key for key in keys if len({repr(flats[id(run)].get(key)) for run in members}) > 1]
        labels = [_label(source, run, flats[id(run)], varying, short=True) for run in members]
        setups = {label: set() for label in labels}
        for label, run in zip(labels, members, strict=True):
            setups[label].add(repr([flats[id(run)].get(key) for key in varying]))
        if any(len(values) > 1 for values in setups.values()):  # a design name hid a difference
            labels = [_label(source, run, flats[id(run)], varying, short=False) for run in members]
        for label, run in zip(labels, members, strict=True):
            groups.setdefault(label, []).append(run)
    return dict(sorted(groups.items()))


def _label(source: str, run: Run, flat: dict, varying: Sequence[str], short: bool) -> str:
    parts, design_named = [source], False
    for key in varying:
        if short and key.startswith("design.") and "design" in run.choices:
            # The design group's name says it in one word where its values take several.
            if not design_named:
                parts.append(f"design={run.choices['design']}")
                design_named = True
            continue
        parts.append(f"{key}={_show(flat.get(key))}")
    return " ".join(parts)


def _show(value) -> str:
    if isinstance(value, tuple):
        return "[" + ",".join(str(item) for item in value) + "]"
    return str(value)
