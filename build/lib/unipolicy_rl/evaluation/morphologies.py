"""Evaluate one policy on every morphology of a set, each over a grid of designs (``robot=grammar``).

A universal policy of the grammar is judged per robot and over all of them: how far it walks
each morphology across the (l, rho) range, which morphology and which design it walks worst,
and how many walk at all. Every (morphology, design) cell is one deterministic episode of a
``MorphologyWalkerEnv``, its robots forced to the cell's morphology and design at reset, side by
side as :func:`~unipolicy_rl.evaluation.grid.design_rollouts` runs the vertebrate's grid; the
per-design figures are the vertebrate grid's :class:`~unipolicy_rl.evaluation.grid.DesignResult`.
"""

from __future__ import annotations

import csv
from collections.abc import Sequence
from dataclasses import asdict, dataclass
from pathlib import Path

import torch

from unipolicy_rl.envs import Design, MorphologyWalkerEnv
from unipolicy_rl.evaluation.grid import (
    CSV_COLUMNS,
    WALKING_DISPLACEMENT,
    DesignResult,
    _summarise_design,
    design_rollouts,
    episode_outcomes,
    summarise,
)
from unipolicy_rl.robots.grammar import Morphology


@dataclass(frozen=True)
class MorphologyResult:
    """One morphology's grid: ``index`` in the evaluated set, its size, one result per design."""

    index: int
    morphology: Morphology
    designs: tuple[DesignResult, ...]

    def summary(self) -> dict:
        return summarise(self.designs)


def evaluate_on_morphologies(policy, env_kwargs: dict, designs: Sequence[Design], num_robots: int | None = None,
                             seed: int = 0, progress: bool = False) -> list[MorphologyResult]:
    """One deterministic episode of ``policy`` per design on each morphology of
    ``env_kwargs["morphologies"]`` (keyword arguments of :class:`MorphologyWalkerEnv`); one result
    per morphology, in the set's order."""
    morphologies = tuple(env_kwargs["morphologies"])
    designs = list(designs)
    if not designs:
        raise ValueError("designs is empty: nothing to evaluate")
    cells = [(index, design) for index in range(len(morphologies)) for design in designs]
    outcomes = [
        {key: value[: len(batch)] for key, value in episode_outcomes(rollout, control_period).items()}
        for batch, rollout, control_period in design_rollouts(
            policy, env_kwargs, [design for _, design in cells], num_robots, seed, True,
            "evaluating morphologies" if progress else None, env_class=MorphologyWalkerEnv,
            morphologies=[index for index, _ in cells])
    ]
    merged = {key: torch.cat([outcome[key] for outcome in outcomes]) for key in outcomes[0]}
    per_cell = [_summarise_design(design, {key: value[i : i + 1] for key, value in merged.items()})
                for i, (_, design) in enumerate(cells)]
    return [MorphologyResult(index, morphology, tuple(per_cell[index * len(designs) : (index + 1) * len(designs)]))
            for index, morphology in enumerate(morphologies)]


def summarise_morphologies(results: Sequence[MorphologyResult],
                           walking_displacement: float = WALKING_DISPLACEMENT) -> dict:
    """Over every (morphology, design) cell: :func:`~unipolicy_rl.evaluation.grid.summarise`'s
    figures (grid mean, worst design, walking designs, ...), plus the morphologies evaluated,
    those whose own grid mean walks, the worst morphology (lowest grid mean) and its grid mean."""
    if not results:
        raise ValueError("results is empty: nothing to summarise")
    overall = summarise([design for result in results for design in result.designs], walking_displacement)
    means = [result.summary()["mean_forward_displacement"] for result in results]
    worst = min(range(len(results)), key=means.__getitem__)
    worst_cell = min(((result.index, design) for result in results for design in result.designs),
                     key=lambda cell: cell[1].mean_forward_displacement)
    return {
        **overall,
        "morphologies": len(results),
        "walking_morphologies": sum(mean >= walking_displacement for mean in means),
        "worst_morphology": results[worst].index,
        "worst_morphology_mean_displacement": means[worst],
        "worst_design_morphology": worst_cell[0],
    }


# -- CSV -------------------------------------------------------------------------------
MORPHOLOGY_COLUMNS = ("morphology", "segments", "leg_pairs", "links", "designs", "mean_forward_displacement",
                      "min_forward_displacement", "walking_designs", "mean_episode_reward", "physics_faults",
                      "derivation")


def morphology_rows(results: Sequence[MorphologyResult]) -> list[dict]:
    """One row per morphology (:data:`MORPHOLOGY_COLUMNS`): its size, its grid's figures, its derivation."""
    rows = []
    for result in results:
        summary = result.summary()
        rows.append({"morphology": result.index, "segments": result.morphology.segments,
                     "leg_pairs": result.morphology.leg_pairs, "links": result.morphology.num_links,
                     "designs": summary["designs"],
                     "mean_forward_displacement": repr(summary["mean_forward_displacement"]),
                     "min_forward_displacement": repr(summary["min_forward_displacement"]),
                     "walking_designs": summary["walking_designs"],
                     "mean_episode_reward": repr(summary["mean_episode_reward"]),
                     "physics_faults": summary["physics_faults"],
                     "derivation": " ".join(result.morphology.derivation())})
    return rows


def append_csv(path: str | Path, rows: Sequence[dict], columns: Sequence[str]) -> Path:
    """Appends ``rows`` to the CSV at ``path`` (header written when the file is new)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    new = not path.is_file()
    with path.open("a", newline="") as handle:
        writer = csv.DictWriter(handle, fieldnames=list(columns))
        if new:
            writer.writeheader()
        writer.writerows(rows)
    return path


def write_morphology_csvs(results: Sequence[MorphologyResult], out: str | Path) -> tuple[Path, Path]:
    """``morphologies.csv`` (one row per morphology) and ``designs.csv`` (one per morphology and
    design: the vertebrate grid's columns after a ``morphology`` one) in the folder ``out``."""
    out = Path(out)
    for name in ("morphologies.csv", "designs.csv"):
        (out / name).unlink(missing_ok=True)
    summary = append_csv(out / "morphologies.csv", morphology_rows(results), MORPHOLOGY_COLUMNS)
    designs = append_csv(out / "designs.csv", [
        {"morphology": result.index, **{key: repr(value) if isinstance(value, float) else value
                                        for key, value in asdict(design).items()}}
        for result in results for design in result.designs], ("morphology", *CSV_COLUMNS))
    return summary, designs


def format_morphology_summary(summary: dict) -> str:
    """What a finished ``robot=grammar`` run prints beside the grid summary."""
    return (f"morphologies {summary['morphologies']}: walking (grid mean >= {summary['walking_displacement']:g} m) "
            f"{summary['walking_morphologies']}/{summary['morphologies']}; worst morphology "
            f"{summary['worst_morphology']} (grid mean {summary['worst_morphology_mean_displacement']:.3f} m); "
            f"worst design on morphology {summary['worst_design_morphology']}")
