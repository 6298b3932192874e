"""Final policies on a design grid wider than the one they were meant for, cached in the report.

Whether a universal policy extrapolates is the question training never asks: every run is
evaluated on its config's evaluation ranges (the SE ranges), so here each final policy walks a
grid ``widen`` wider per axis about the same centre (0.5: half as wide again). Evaluating takes
real simulator time, so results are kept next to the report, keyed by the checkpoint's content
and by the grid, and a re-run only evaluates what changed.
"""

from __future__ import annotations

import hashlib
import json
from collections.abc import Sequence
from pathlib import Path

from unipolicy_rl.envs import Design, DesignDistribution
from unipolicy_rl.evaluation import DesignResult, evaluate_on_designs, read_csv, write_csv
from unipolicy_rl.report.runs import ReportError, Run

CACHE_FOLDER = "generalisation"


def widened(low: float, high: float, widen: float) -> tuple[float, float]:
    """[low, high] stretched by ``widen`` of its width, half on each side."""
    margin = (high - low) * widen / 2
    return low - margin, high + margin


def wide_grid(run: Run, points_per_axis: int, widen: float) -> list[Design]:
    """``points_per_axis`` squared designs over the run's evaluation ranges widened by ``widen``."""
    evaluation = run.config["evaluation"]
    ranges = [widened(*evaluation[name], widen) for name in ("length_range", "density_range")]
    try:
        return DesignDistribution(*ranges).grid(points_per_axis)
    except ValueError as error:
        shown = ", ".join(f"[{low:.4g}, {high:.4g}]" for low, high in ranges)
        raise ReportError(f"--widen {widen:g} stretches the evaluation ranges of {run.path} to {shown}: "
                          f"{error}") from None


def evaluate_wide(run: Run, designs: Sequence[Design], cache_dir: Path, seed: int = 0) -> list[DesignResult]:
    """One deterministic episode of ``run``'s final policy per design, from the cache when it
    holds this checkpoint (by content, so a copied sweep still hits) on these designs."""
    digest = hashlib.sha256(run.checkpoint.read_bytes()).hexdigest()
    key = {"checkpoint_sha256": digest, "seed": seed, "designs": [[d.length, d.density] for d in designs]}
    stem = cache_dir / f"{run.path.name}-{digest[:12]}"
    csv_path, key_path = stem.with_suffix(".csv"), stem.with_suffix(".json")
    if csv_path.is_file() and key_path.is_file():
        try:
            stored = json.loads(key_path.read_text())
            stored.pop("run", None)  # where it was evaluated from, for a person reading the cache
            if stored == key:
                return read_csv(csv_path)
        except (OSError, ValueError, KeyError, AttributeError):
            pass  # a damaged entry is evaluated again
    # Imported here: loading a policy needs the training stack, which reading a sweep does not.
    from unipolicy_rl.checkpoint import load_policy

    loaded = load_policy(run.checkpoint)
    results = evaluate_on_designs(loaded.policy, dict(loaded.env_kwargs), designs, episodes_per_design=1, seed=seed)
    write_csv(results, csv_path)
    key_path.write_text(json.dumps({**key, "run": str(run.path)}))
    return results
