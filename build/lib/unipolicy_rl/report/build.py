"""From sweep folders to a report folder: find and read the runs, then draw, tabulate, write.

Reads top to bottom in the order of report.md: curves, design grids, relative performance,
generalisation, summary, and what is missing. Each step reports on the runs that have what it
needs and says which do not; only a folder with nothing to report, or runs that cannot be
compared, stop it (:class:`ReportError`).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from unipolicy_rl.evaluation import GRID_WALKING_MEAN, WALKING_DISPLACEMENT, DesignResult, summarise
from unipolicy_rl.report import figures, generalisation, markdown
from unipolicy_rl.report.grids import GridValues, best_achievable, cell, relative_performance, seed_mean
from unipolicy_rl.report.groups import check_same_robot, group_runs
from unipolicy_rl.report.markdown import Section
from unipolicy_rl.report.metrics import series, steps_are_derived
from unipolicy_rl.report.runs import (
    SWEEP_FILE,
    ReportError,
    Run,
    discover,
    jobs_not_started,
    load_run,
    run_names,
)
from unipolicy_rl.report.summary import TABLE_HEADER, summarise_source, surrogate_rows, table_row, write_summary_csv
from unipolicy_rl.training.metrics_file import DISPLACEMENT, GRID_MEAN, GRID_MIN, IMAGINED_PREFIX, REWARD

DEFAULT_FOLDER = "report"
DEFAULT_WIDE_GRID = 5  # designs per axis of the generalisation grid (25 episodes per policy)
DEFAULT_WIDEN = 0.5  # the generalisation grid is this much wider per axis than the evaluation ranges
RELATIVE_COLOUR_CAP = 200.0  # percent


@dataclass
class Report:
    """What was written and what could not be reported."""

    markdown: Path
    figures: dict[str, Path]
    summary_csv: Path
    runs: list[Run]
    groups: dict[str, list[Run]]
    missing: list[str] = field(default_factory=list)  # one line per run or job with a problem


def build_report(roots: Sequence[Path | str], out: Path | str | None = None, wide_grid: int = DEFAULT_WIDE_GRID,
                 widen: float = DEFAULT_WIDEN, echo: Callable[[str], None] | None = None) -> Report:
    """Writes report.md, its figures and summary.csv into ``out`` (default ``<first root>/report``)."""
    echo = echo or (lambda message: None)
    roots = [Path(root) for root in roots]
    if not roots:
        raise ReportError("no sweep or run directory given")
    if wide_grid < 0 or widen < 0:
        raise ReportError(f"--wide-grid ({wide_grid}) and --widen ({widen}) must not be negative")
    out = Path(out) if out is not None else roots[0] / DEFAULT_FOLDER
    where = ", ".join(str(root) for root in roots)

    # -- Reading ------------------------------------------------------------------------
    paths, sweeps = discover(roots, exclude=[out])
    runs = [load_run(path, name) for path, name in zip(paths, run_names(paths, roots), strict=True)]
    usable = [run for run in runs if run.config is not None]
    if not any(run.rows or run.finished for run in usable):
        reasons = "; ".join(f"{run.name}: {run.problems[0]}" for run in runs if run.problems)
        raise ReportError(f"{where}: nothing to report ({reasons or 'no run logged an epoch'})")
    check_same_robot(usable, where)
    references = [run for run in usable if run.is_reference]
    groups = group_runs([run for run in usable if not run.is_reference] or references)
    echo(f"{len(runs)} runs under {where}: "
         + ", ".join(f"{label} x{len(members)}" for label, members in groups.items()))
    missing = [f"{run.name}: {problem}" for run in runs for problem in run.problems]
    for sweep in sweeps:
        inside = [run for run in runs if sweep.resolve() in run.path.resolve().parents]
        never_started = jobs_not_started(sweep, inside)
        if never_started is None:
            missing.append(f"{sweep / SWEEP_FILE}: could not be expanded into its jobs, so jobs that never "
                           "started are not listed")
        for job in never_started or []:
            missing.append(f"{sweep} job {job}: no folder: not started (the sweep stopped before it, "
                           "or it is waiting its turn) or its folder was removed")

    finished = {label: [run for run in members if run.finished] for label, members in groups.items()}
    finished = {label: members for label, members in finished.items() if members}
    evaluable = {label: [run for run in members if run.checkpoint is not None] for label, members in finished.items()}
    evaluable = {label: members for label, members in evaluable.items() if members}
    # Built before any slow work, so a --widen that leaves the positive designs fails at once.
    wide_designs = (generalisation.wide_grid(next(iter(evaluable.values()))[0], wide_grid, widen)
                    if wide_grid and evaluable else [])

    # -- Figures and tables, in report order --------------------------------------------
    out.mkdir(parents=True, exist_ok=True)
    written: dict[str, Path] = {}
    curves = _curves_section(groups, out, written)
    grid, relative = _grid_sections(finished, usable, references, out, written)
    wide: dict[str, list[DesignResult]] = {}  # run name -> its final policy on the wider grid
    for run in [run for members in evaluable.values() for run in members] if wide_designs else []:
        echo(f"{run.name}: on the {wide_grid} x {wide_grid} wider grid")
        wide[run.name] = generalisation.evaluate_wide(run, wide_designs, out / generalisation.CACHE_FOLDER)
    beyond = _generalisation_section(evaluable, wide, wide_designs, widen, out, written)
    summaries = [summarise_source(label, members, wide) for label, members in groups.items()]
    summary_csv = write_summary_csv(summaries, out / "summary.csv")
    lost = Section("Missing or incomplete runs",
                   [markdown.bullets(missing) if missing else "None: every run finished."])

    intro = [f"Sweep: {where}. {len(runs)} runs; sources: "
             + ", ".join(f"{label} ({len(finished.get(label, []))}/{len(members)} finished)"
                         for label, members in groups.items())
             + (f"; {len(references)} fixed-design reference runs." if references else ".")]
    sections = [_summary_section(summaries), curves, grid, relative, beyond, lost]
    report_path = markdown.write_markdown(out / "report.md", "Sweep report", intro, sections)
    return Report(report_path, written, summary_csv, runs, groups, missing)


def _curves_section(groups: dict[str, list[Run]], out: Path, written: dict[str, Path]) -> Section:
    """1. Real returns and displacement (and the periodic grid evaluation) against real env steps and wall time."""
    curves = {label: {name: [s for s in (series(run, name) for run in members) if s is not None]
                      for name in (REWARD, DISPLACEMENT, GRID_MEAN, GRID_MIN)}
              for label, members in groups.items()}
    section = Section("Training curves")
    if not any(curves[label][REWARD] for label in curves):
        section.blocks.append("No run logged a real training episode yet.")
        return section
    for axis, stem, caption in (("steps", "curves_real_steps", "against real env steps"),
                                ("seconds", "curves_wall_time", "against wall time")):
        written[stem] = figures.plot_curves(curves, axis, out / f"{stem}.png")
        section.blocks.append(markdown.image(written[stem], out, f"training curves {caption}"))
    section.blocks.append(_curve_notes(groups, curves))
    return section


def _grid_sections(finished: dict[str, list[Run]], usable: Sequence[Run], references: Sequence[Run], out: Path,
                   written: dict[str, Path]) -> tuple[Section, Section]:
    """2. Seed-mean reward and displacement per design; 3. reward as a percentage of the best there."""
    grid_section = Section("Design grid (final policies)")
    relative_section = Section("Relative performance")
    if not finished:
        grid_section.blocks.append("No run has a final design-grid evaluation yet (`evaluation/designs.csv`).")
        relative_section.blocks.append("Needs runs with a final design-grid evaluation.")
        return grid_section, relative_section
    for metric, stem, label, number in (
        ("mean_episode_reward", "grid_reward", "mean episode reward", "{:.1f}"),
        ("mean_forward_displacement", "grid_displacement", "mean forward displacement (m)", "{:.2f}"),
    ):
        panels = [_panel(group, members, seed_mean([run.designs for run in members], metric), number)
                  for group, members in finished.items()]
        written[stem] = figures.plot_heatmaps(panels, out / f"{stem}.png", label, number)
        grid_section.blocks.append(markdown.image(written[stem], out, f"{label} per design"))
    grid_section.blocks.append(
        "Each cell is the mean over a source's finished seeds of one deterministic episode on that design "
        "(the run's own final evaluation, `evaluation/designs.csv`); the red box is the worst design.")

    best = best_achievable(usable)
    panels = []
    for group, members in finished.items():
        relative = relative_performance(seed_mean([run.designs for run in members], "mean_episode_reward"), best)
        panels.append(_panel(group, members, relative, "{:.0f}%",
                             starred=_cells_in(relative, best.trained_there) if best.mixed else set()))
    # Past 100% the reference was beaten: colour saturates at 2x, the numbers still say how far.
    top = max([100.0] + [float(np.nanmax(p.grid.values)) for p in panels if np.isfinite(p.grid.values).any()])
    top = min(top, RELATIVE_COLOUR_CAP)
    written["relative_performance"] = figures.plot_heatmaps(
        panels, out / "relative_performance.png", "% of the best reward on the design", "{:.0f}",
        cmap="RdYlGn", vmin=0.0, vmax=top, note=best.kind)
    relative_section.blocks += [
        markdown.image(written["relative_performance"], out, "relative performance per design"),
        f"Each source's seed-mean reward on a design as a percentage of the best reward reached there; "
        f"{best.kind}. Cells where the best reward is not positive show n/a. "
        f"Runs trained at a fixed design (`design=fixed`; {len(references)} here) are references only.",
    ]
    return grid_section, relative_section


def _generalisation_section(evaluable: dict[str, list[Run]], wide: dict[str, list[DesignResult]],
                            designs: Sequence, widen: float, out: Path, written: dict[str, Path]) -> Section:
    """4. Final policies on the wider grid, the training range outlined, the share that walks."""
    section = Section("Generalisation beyond the training range")
    if not designs:
        section.blocks.append("Skipped (--wide-grid 0), or no finished run has a checkpoint.pt.")
        return section
    panels = []
    for group, members in evaluable.items():
        share = np.mean([summarise(wide[run.name])["walking_fraction"] for run in members])
        grid = seed_mean([wide[run.name] for run in members], "mean_forward_displacement")
        panels.append(_panel(group, members, grid, "{:.2f}", extra=f"walks on {100 * share:.0f}% of designs"))
    written["generalisation"] = figures.plot_heatmaps(panels, out / "generalisation.png",
                                                      "mean forward displacement (m)")
    lengths = sorted({design.length for design in designs})
    densities = sorted({design.density for design in designs})
    section.blocks += [
        markdown.image(written["generalisation"], out, "forward displacement on the wider grid"),
        f"Final policies on a {len(lengths)} x {len(densities)} grid {100 * widen:.0f}% wider per axis than the "
        f"evaluation ranges: l in [{lengths[0]:.4f}, {lengths[-1]:.4f}] m, rho in [{densities[0]:.3f}, "
        f"{densities[-1]:.3f}] kg/m, one deterministic episode per design; a design walks when it gets "
        f">= {WALKING_DISPLACEMENT:g} m (the share is the mean over seeds). "
        f"Results are cached in `{generalisation.CACHE_FOLDER}/`.",
    ]
    return section


def _summary_section(summaries: Sequence) -> Section:
    """5. One row per source; the surrogate's accuracy when a run logged it."""
    section = Section("Summary", [
        markdown.table(TABLE_HEADER, [table_row(summary) for summary in summaries]),
        "Mean ± sample sd over finished seeds. Reward and displacement are over the run's final design grid "
        f"(worst design: its lowest cell); a design walks at >= {WALKING_DISPLACEMENT:g} m. Real env steps and "
        f"wall time to walk: at the first periodic real-env grid evaluation (`evaluation.every_steps`) with a grid "
        f"mean >= {GRID_WALKING_MEAN:g} m and every design >= {WALKING_DISPLACEMENT:g} m; the median over the runs "
        "that logged, a run that never walked counting as longer than any that did (so \"not reached\" when "
        "fewer than half walked). The same numbers, unformatted: `summary.csv`.",
    ])
    header, rows = surrogate_rows(summaries)
    if rows:
        section.blocks += ["Surrogate accuracy (last logged value, mean ± sd over runs):", markdown.table(header, rows)]
    return section


def _training(members: Sequence[Run]):
    design = members[0].design_distribution
    return (design.length_range, design.density_range) if design is not None else None


def _panel(group: str, members: Sequence[Run], grid: GridValues, number: str, extra: str = "",
           starred: set[tuple[int, int]] | None = None) -> figures.Panel:
    worst = grid.worst()
    title = f"{group} ({len(members)} seed{'s' if len(members) != 1 else ''})"
    if worst is not None:
        row, column = worst
        title += (f"\nworst {number.format(grid.values[row, column])} at l={grid.lengths[column]:.3f}, "
                  f"rho={grid.densities[row]:.3f}")
    if extra:
        title += f"\n{extra}"
    return figures.Panel(title, grid, _training(members), starred or set())


def _cells_in(grid: GridValues, cells) -> set[tuple[int, int]]:
    return {(row, column) for row in range(len(grid.densities)) for column in range(len(grid.lengths))
            if cell(grid.lengths[column], grid.densities[row]) in cells}


def _curve_notes(groups: dict[str, list[Run]], curves) -> str:
    notes = ["Mean over seeds with a 95% confidence band of the mean (Student's t); each seed counts only "
             "over the range it logged. Returns are real-env returns only (rows with "
             f"`{REWARD}`; `{IMAGINED_PREFIX}*` columns are not returns)."]
    derived = sorted({label for label, members in groups.items() for run in members
                      if run.rows and steps_are_derived(run)})
    if derived:
        notes.append(f"Real env steps of {', '.join(derived)} are derived as epoch x episodes_per_epoch x "
                     "episode_length (no `real_env_steps` column).")
        model = sorted({label for label, members in groups.items() for run in members
                        if run.rows and steps_are_derived(run) and run.config.get("source", {}).get("kind") != "real"})
        if model:
            notes.append(f"{', '.join(model)} are not real sources: their derived steps overcount.")
    if not any(curves[label][GRID_MEAN] for label in curves):
        notes.append("No run logged a periodic design-grid evaluation (`eval/*` columns).")
    return " ".join(notes)
