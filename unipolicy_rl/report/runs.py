"""Find the runs under a sweep folder and read what each left behind, saying what is missing and why.

A sweep is judged on what finished, but a user also needs to know what did not: a job that
crashed, was killed, is still running or never started. Nothing here raises on one bad run:
each :class:`Run` carries its own ``problems``; only input that cannot be a sweep at all raises
:class:`ReportError`, whose message is the one line the command prints.
"""

from __future__ import annotations

import csv
import io
import itertools
import math
import os
import re
import shutil
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

from hydra.core.override_parser.overrides_parser import OverridesParser
from hydra.utils import instantiate
from omegaconf import OmegaConf

from unipolicy_rl.envs import DesignDistribution
from unipolicy_rl.evaluation import DesignResult, read_csv
from unipolicy_rl.training.metrics_file import EPOCH, without_redone_epochs
from unipolicy_rl.training.metrics_file import FILE_NAME as METRICS
from unipolicy_rl.training.progress import FINAL_DESIGNS as DESIGNS
from unipolicy_rl.training.progress import FINAL_EVALUATIONS, FINAL_RETURNS

CONFIG = Path(".hydra") / "config.yaml"
HYDRA_CONFIG = Path(".hydra") / "hydra.yaml"
OVERRIDES = Path(".hydra") / "overrides.yaml"
CHECKPOINT = "checkpoint.pt"
# A finished run's final policy alone (no learner, collector or world model state: not resumable),
# what an archive carrying checkpoints keeps of it, for runs that build on it (algo=distill's teachers).
POLICY = "policy.pt"
SWEEP_FILE = "multirun.yaml"  # Hydra writes it at the root of every multirun
RUN_MARKERS = (CONFIG, Path(METRICS), Path(CHECKPOINT))
# A run's record: the small files the reports read (not its checkpoint or buffer), what an archive keeps.
COMMANDS = "commands.txt"  # study/queue.py's log of every command a run was given
RECORD = (CONFIG, HYDRA_CONFIG, OVERRIDES, Path(METRICS), Path(COMMANDS))
EVALUATION_TABLES = "evaluation/*.csv"
# A run whose metrics.csv changed this recently may still be training.
STILL_RUNNING_SECONDS = 600


class ReportError(Exception):
    """Input that cannot be reported on at all; the message names the path and is printed as is."""


@dataclass
class Run:
    """One training run's folder and what could be read from it (``None`` where it could not)."""

    path: Path
    name: str  # path relative to the report's roots, for messages
    config: dict | None = None  # resolved .hydra/config.yaml
    choices: dict = field(default_factory=dict)  # Hydra's config-group choices (e.g. design: fixed)
    overrides: list[str] = field(default_factory=list)  # this job's command-line overrides
    rows: list[dict[str, float]] = field(default_factory=list)  # metrics.csv, numbers only, NaN where blank
    columns: list[str] = field(default_factory=list)
    last_row_cut: bool = False  # metrics.csv's last row was cut short (killed while writing it) and dropped
    designs: list[DesignResult] | None = None  # the final design-grid evaluation
    checkpoint: Path | None = None
    checkpoint_epoch: int | None = None  # read only for runs that did not finish
    problems: list[str] = field(default_factory=list)  # what is missing and why, one sentence each

    @property
    def source(self) -> str | None:
        """What ran: the run's name (design, world model, algorithm: ``se-moe-trpo``), or, for runs
        from before runs were named so, the data source (``moe``)."""
        return _get(self.config, "run_name") or _get(self.config, "source", "name")

    @property
    def epochs(self) -> int | None:
        return _get(self.config, "epochs")

    @property
    def last_epoch(self) -> int:
        epochs = [row[EPOCH] for row in self.rows if math.isfinite(row.get(EPOCH, math.nan))]
        return int(max(epochs)) if epochs else 0

    @property
    def finished(self) -> bool:
        """Trained to its budget and evaluated: its final evaluation exists (the grid's, or a gym
        task's returns) and its last epoch is the configured ``epochs``. A run resumed with a larger
        budget (``epochs=300`` after 120) keeps the first budget's final evaluation until it gets
        there: not finished meanwhile."""
        if self.designs is None and not (self.path / FINAL_RETURNS).is_file():
            return False
        logged = self.last_epoch + (1 if self.last_row_cut else 0)  # a row cut short was the next epoch's
        return self.epochs is None or not self.rows or logged >= self.epochs

    @property
    def design_distribution(self) -> DesignDistribution | None:
        """The designs it trained on, built from its config as training built them."""
        try:
            return instantiate(self.config["design"])
        except Exception:
            return None

    @property
    def is_reference(self) -> bool:
        """A policy trained at one chosen design (``design=fixed``): a reference for relative
        performance, not a source to compare."""
        return self.choices.get("design") == "fixed"


def _get(mapping, *keys):
    for key in keys:
        if not isinstance(mapping, dict) or key not in mapping:
            return None
        mapping = mapping[key]
    return mapping


# -- discovery -------------------------------------------------------------------------
def is_run_dir(path: Path) -> bool:
    return any((path / marker).is_file() for marker in RUN_MARKERS)


def discover(roots: Sequence[Path], exclude: Sequence[Path] = ()) -> tuple[list[Path], list[Path]]:
    """(run folders, sweep roots holding a multirun.yaml) under ``roots``, in sorted order.

    A root may be one run, a sweep, or a folder of sweeps. Folders in ``exclude`` (the report's
    own output) and hidden folders are skipped; nothing inside a run folder is searched.
    """
    excluded = {path.resolve() for path in exclude}
    runs, sweeps = [], []
    for root in roots:
        if not root.exists():
            raise ReportError(f"{root}: no such directory")
        if not root.is_dir():
            raise ReportError(f"{root}: not a directory; give a sweep (multirun/<time>) or run directory")
        found = 0
        for folder, subfolders, files in os.walk(root):
            folder = Path(folder)
            if SWEEP_FILE in files:
                sweeps.append(folder)
            if is_run_dir(folder):
                runs.append(folder)
                found += 1
                subfolders.clear()
                continue
            subfolders[:] = sorted(name for name in subfolders
                                   if not name.startswith(".") and (folder / name).resolve() not in excluded)
        if not found:
            raise ReportError(f"{root}: not a sweep or run directory (no folder under it holds "
                              f"{', '.join(str(marker) for marker in RUN_MARKERS)})")
    return sorted(set(runs)), sorted(set(sweeps))


def run_names(paths: Sequence[Path], roots: Sequence[Path]) -> list[str]:
    """Each run's path relative to the roots' common parent (its own name when it is the root)."""
    base = Path(os.path.commonpath([root.resolve() for root in roots]))
    if len(roots) == 1 and is_run_dir(roots[0]):
        base = base.parent
    return [str(path.resolve().relative_to(base)) if path.resolve() != base else path.name for path in paths]


def load_runs(roots: Sequence[Path], exclude: Sequence[Path] = ()) -> list[Run]:
    """Every run under ``roots`` (:func:`discover`), read (:func:`load_run`) and named by
    :func:`run_names`; raises :class:`ReportError` where a root holds no run."""
    paths, _ = discover(roots, exclude)
    return [load_run(path, name) for path, name in zip(paths, run_names(paths, roots), strict=True)]


# -- keeping a run's record ----------------------------------------------------------
def record_files(run: Path) -> list[Path]:
    """The run's small files the league reads, relative to the run folder (those that exist)."""
    files = [name for name in RECORD if (run / name).is_file()]
    return files + sorted(path.relative_to(run) for path in run.glob(EVALUATION_TABLES))


def _copy_whole(source: Path, target: Path) -> None:
    """``source`` to ``target`` (folders created), written whole under another name before it
    replaces an older copy: a reader never sees half a file."""
    target.parent.mkdir(parents=True, exist_ok=True)
    partial = target.with_name(target.name + ".partial")
    shutil.copyfile(source, partial)
    partial.replace(target)


def archive_run(run: Path, destination: Path, checkpoint_limit: int = 0) -> list[Path]:
    """Copies ``run``'s record into ``destination`` (created); returns the files copied, relative
    to the run folder.

    With ``checkpoint_limit`` (bytes) above 0 the run's checkpoint comes too where it is no larger:
    a study whose machine is taken back mid-run then resumes on the next one from the archive
    (:func:`restore_run`), not from its first epoch. An on-policy run's checkpoint is small (a
    policy, a critic, the observation statistics: about 1 MB); an off-policy or model-based one
    holds its replay buffer (tens to hundreds of MB) and stays behind. A finished run (its final
    evaluation written) has nothing left to resume: its archived checkpoint is removed, so the
    archive holds checkpoints only while their runs are under way, and its final policy alone is
    kept as ``policy.pt`` (:func:`~unipolicy_rl.checkpoint.policy_only`, a few hundred kB): what
    a later run learns from, as ``algo=distill`` from specialists.
    """
    if checkpoint_limit < 0:
        raise ValueError(f"checkpoint_limit must be >= 0 bytes, got {checkpoint_limit!r}")
    files = record_files(run)
    if Path(METRICS) not in files:
        raise ReportError(f"{run}: no {METRICS}, so nothing to archive (it never finished an epoch)")
    checkpoint, finished = run / CHECKPOINT, any((run / name).is_file() for name in FINAL_EVALUATIONS)
    if checkpoint_limit and not finished and checkpoint.is_file() and checkpoint.stat().st_size <= checkpoint_limit:
        files.append(Path(CHECKPOINT))
    for name in files:
        _copy_whole(run / name, destination / name)
    if finished:
        (destination / CHECKPOINT).unlink(missing_ok=True)
        if checkpoint_limit and checkpoint.is_file():
            import torch

            from unipolicy_rl.checkpoint import policy_only, save_checkpoint

            state = torch.load(checkpoint, map_location="cpu", weights_only=False)
            save_checkpoint(destination / POLICY, policy_only(state))
            files.append(Path(POLICY))
    return files


def restore_run(archived: Path, run: Path) -> list[Path]:
    """Copies an archived run (its record and checkpoint, :func:`archive_run`) into the run folder
    ``run``, so training resumes there where the archive's checkpoint stopped; returns the files
    copied. Refuses (:class:`ReportError`) an archive without a checkpoint, and a run folder that
    has one of its own: that checkpoint is newer than any archived copy of it.
    """
    if not (archived / CHECKPOINT).is_file():
        raise ReportError(f"{archived}: no {CHECKPOINT} archived, nothing to resume from")
    if (run / CHECKPOINT).is_file():
        raise ReportError(f"{run}: has a {CHECKPOINT} of its own; it is not replaced by the archive's")
    files = record_files(archived) + [Path(CHECKPOINT)]
    for name in files:
        _copy_whole(archived / name, run / name)
    return files


# -- reading one run -------------------------------------------------------------------
def load_run(path: Path, name: str) -> Run:
    """Reads config, metrics, final evaluation and checkpoint state; problems are noted, never raised."""
    run = Run(path=path, name=name)
    _read_config(run)
    _read_metrics(run)
    if (path / DESIGNS).is_file():
        try:
            run.designs = read_csv(path / DESIGNS)
            if not run.designs:
                raise ValueError("no rows")
        except (OSError, ValueError, KeyError, TypeError, csv.Error, UnicodeDecodeError) as error:
            run.designs = None
            run.problems.append(f"unreadable {path / DESIGNS}: {_reason(error)}")
    if (path / CHECKPOINT).is_file():
        run.checkpoint = path / CHECKPOINT
    _diagnose(run)
    return run


def _resolved(config) -> dict:
    """The config as plain values, every interpolation resolved that can be outside Hydra; one
    that only Hydra can resolve (``${hydra:runtime.output_dir}`` in the logger) stays as written."""
    try:
        return OmegaConf.to_container(config, resolve=True)
    except Exception:  # any resolution failure: fall back to resolving leaf by leaf
        pass

    def walk(value, key: str):
        if isinstance(value, dict):
            return {name: walk(item, f"{key}.{name}" if key else str(name)) for name, item in value.items()}
        if isinstance(value, list):
            return [walk(item, f"{key}[{index}]") for index, item in enumerate(value)]
        if isinstance(value, str) and "${" in value:
            try:
                selected = OmegaConf.select(config, key, throw_on_resolution_failure=True)
            except Exception:  # only Hydra can resolve it
                return value
            return OmegaConf.to_container(selected, resolve=True) if OmegaConf.is_config(selected) else selected
        return value

    return walk(OmegaConf.to_container(config, resolve=False), "")


def _with_choices(text: str, choices: dict) -> str:
    """The config's text with Hydra's ``${hydra:runtime.choices.GROUP}`` replaced by the run's choice
    (what ``run_name`` is made of), which outside Hydra nothing else could resolve."""
    return re.sub(r"\$\{hydra:runtime\.choices\.([\w/]+)\}", lambda match: str(choices.get(match.group(1))), text)


def _read_config(run: Run) -> None:
    path = run.path / CONFIG
    if not path.is_file():
        run.problems.append(f"no {CONFIG}: cannot tell its source, seed or robot, so it is left out")
        return
    try:
        run.choices = dict(OmegaConf.load(run.path / HYDRA_CONFIG).hydra.runtime.choices)
    except Exception:
        run.choices = {}
    try:
        run.config = _resolved(OmegaConf.create(_with_choices(path.read_text(), run.choices)))
        if not isinstance(run.config, dict) or run.source is None:
            raise ValueError("no source.name in it")
    except Exception as error:  # a YAML error of any kind: one line, not a traceback
        run.config = None
        run.problems.append(f"unreadable {path}: {_reason(error)}; left out")
        return
    try:
        run.overrides = [str(item) for item in OmegaConf.load(run.path / OVERRIDES)]
    except Exception:
        run.overrides = []


def _read_metrics(run: Run) -> None:
    path = run.path / METRICS
    if not path.is_file():
        run.problems.append(f"no {METRICS}: it never finished an epoch")
        return
    try:
        text = path.read_text()
        reader = csv.DictReader(io.StringIO(text, newline=""))
        columns = list(reader.fieldnames or [])
        raw = list(reader)
    except (OSError, UnicodeDecodeError, csv.Error) as error:
        run.problems.append(f"unreadable {path}: {_reason(error)}")
        return
    if EPOCH not in columns:
        run.problems.append(f"unreadable {path}: no {EPOCH!r} column, so not a metrics CSV")
        return
    # Every row ends in a newline: a last row without one is a write the run did not finish.
    cut = bool(raw) and not text.endswith("\n")
    if cut:
        raw.pop()
    rows = []
    for line, record in enumerate(raw, start=2):
        if None in record or any(value is None for value in record.values()):
            run.problems.append(f"unreadable {path}: line {line} has the wrong number of fields")
            return
        try:
            rows.append({key: _number(value) for key, value in record.items()})
        except ValueError as error:
            run.problems.append(f"unreadable {path}: line {line}: {_reason(error)}")
            return
    run.last_row_cut = cut
    if cut:
        run.problems.append(f"{path}: its last row was cut short (killed while writing it?); that row is dropped")
    run.columns, run.rows = columns, without_redone_epochs(rows)


def _number(value: str) -> float:
    return math.nan if value.strip() == "" else float(value)


def _diagnose(run: Run) -> None:
    """Says why a run has no final evaluation, from what it left behind."""
    if run.config is None or run.finished:
        return
    epochs, last = run.epochs, run.last_epoch
    if run.checkpoint is not None:
        # Imported here: only an unfinished run's checkpoint is read, and the checkpoint module
        # brings the whole training stack with it.
        from unipolicy_rl.checkpoint import load_checkpoint

        try:
            run.checkpoint_epoch = int(load_checkpoint(run.checkpoint)["epoch"])
        except Exception as error:
            run.problems.append(f"unreadable {run.checkpoint}: {_reason(error)}")
    if run.checkpoint_epoch is not None and epochs is not None and run.checkpoint_epoch >= epochs:
        why = "trained to the end but has no final evaluation: stopped during it, or is still evaluating"
    elif run.checkpoint_epoch is not None:
        why = (f"stopped at epoch {last} of {epochs} (checkpoint at epoch {run.checkpoint_epoch}; "
               f"continue it with resume={run.checkpoint})")
    else:
        why = (f"no {CHECKPOINT}: crashed, killed or still running before its first checkpoint "
               f"({last} of {epochs} epochs logged)")
    metrics = run.path / METRICS
    if metrics.is_file() and time.time() - metrics.stat().st_mtime < STILL_RUNNING_SECONDS:
        why += f"; {METRICS} was written {time.time() - metrics.stat().st_mtime:.0f} s ago, so it may still be running"
    run.problems.insert(0, why)


def _reason(error: BaseException) -> str:
    text = str(error).strip().splitlines()
    return f"{type(error).__name__}: {text[0]}" if text else type(error).__name__


# -- jobs a sweep asked for but never started -----------------------------------------
def jobs_not_started(sweep: Path, runs: Sequence[Run]) -> list[str] | None:
    """The swept overrides of each job ``sweep``'s multirun.yaml asked for that has no folder.

    Expands the sweep's task overrides with Hydra's own override parser (the one its basic
    sweeper uses) and matches each job by the values in its ``.hydra/overrides.yaml``, so
    ``progress_bar=false`` and ``progress_bar=False`` agree. ``None`` when the sweep cannot be
    expanded (a sweeper plugin's syntax, an unreadable file, a Hydra whose parser changed): the
    parser is Hydra's plugin API rather than its user API, so any failure only loses this list.
    """
    try:
        parser = OverridesParser.create()
        task = [str(item) for item in OmegaConf.load(sweep / SWEEP_FILE).hydra.overrides.task]
        axes = [[(override.get_key_element(), value) for value in override.sweep_string_iterator()]
                for override in parser.parse_overrides(task) if override.is_sweep_override()]
        present = [{parsed.get_key_element(): parsed.value() for parsed in parser.parse_overrides(run.overrides)}
                   for run in runs]
        missing = []
        for job in itertools.product(*axes):
            wanted = {key: parser.parse_override(f"{key}={value}").value() for key, value in job}
            if not any(all(found.get(key) == value for key, value in wanted.items()) for found in present):
                missing.append(" ".join(f"{key}={value}" for key, value in job))
        return missing
    except Exception:
        return None
