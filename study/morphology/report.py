"""One policy for the grammar's robots against a specialist per robot: the table and figure of issue 23.

    python train.py robot=grammar policy=token_mlp robot.morphologies=train robot.specialist=0 \\
        evaluation.morphologies=train epochs=300 seed=0 hydra.run.dir=runs/specialists/train0
    python train.py robot=grammar policy=token_mlp robot.morphologies=held_out robot.specialist=0 \\
        evaluation.morphologies=held_out epochs=300 seed=0 hydra.run.dir=runs/specialists/held_out0
    python train.py robot=grammar policy=token_transformer robot.training_morphologies=8 \\
        evaluation.morphologies=all epochs=2400 seed=0 hydra.run.dir=runs/universal/transformer8
    python study/morphology/report.py runs/specialists runs/universal [--out outputs/morphology_table]
    python study/morphology/report.py                  # the study's records (study/morphology/records)

Reads every grammar run's record (:mod:`study.records`; run folders are read into records on the
fly) under the roots (:mod:`study.morphology.table`): specialists are
the runs with ``robot.specialist`` set, the others universal entries (policy x number of
training morphologies). Prints, per entry, the median of the universal policy's grid mean
displacement over the specialist's on the morphologies it trained on and on the held-out ones
(zero-shot), and how many of its training morphologies it walks (grid mean >= 1 m); then one
line per entry and morphology. Writes ``morphology_table.csv`` and ``morphologies.png``: each
morphology rendered in PyBullet (at the mean design), titled with its side and every entry's
and its specialist's grid mean (``--no-pictures`` skips the renders). Every specialist's final
evaluation comes first (and ``specialists.csv``), so a study whose universal runs have not
finished still shows what it has measured: then the figure shows the specialists alone.

``--matched-steps 40000,80000,140000`` answers another question from the periodic evaluations
(unfinished runs included): each universal run against the specialists on every robot it trains
on, at equal real env steps *per robot* (the universal run's steps over its number of robots).
"""

from __future__ import annotations

import argparse
import csv
import math
import sys
from dataclasses import asdict
from pathlib import Path
from typing import NamedTuple

import numpy as np
import pybullet

# Run as a file, the script's folder leads sys.path (where ``queue.py`` would shadow the standard
# library's): the repository root takes its place, for ``import study``.
if __package__ in (None, ""):
    sys.path[0] = str(Path(__file__).resolve().parents[2])

from study import records as run_records  # noqa: E402
from study.morphology.table import (  # noqa: E402
    compare,
    compare_at_matched_steps,
    format_matched_steps,
    format_specialists,
    format_table,
    is_grammar_run,
    specialist_scores,
    summarize,
)
from unipolicy_rl.report.runs import ReportError  # noqa: E402
from unipolicy_rl.robots import load_robot  # noqa: E402
from unipolicy_rl.robots.grammar import describe  # noqa: E402
from unipolicy_rl.robots.kinematics import rest_height  # noqa: E402

DEFAULT_OUT = Path("outputs") / "morphology_table"
RECORDS = Path(__file__).resolve().parent / "records"  # the study's grammar records


def render(derivation: str, width: int = 240, height: int = 180) -> np.ndarray:
    """The morphology at the mean design, standing on the ground, seen from the front left (RGB)."""
    description = describe(derivation.split())
    client = pybullet.connect(pybullet.DIRECT)
    try:
        plane = pybullet.createCollisionShape(pybullet.GEOM_PLANE, physicsClientId=client)
        pybullet.createMultiBody(0.0, plane, physicsClientId=client)
        body = load_robot(client, description, (0.0, 0.0, rest_height(description)), math.pi, 1.5,
                          visuals=True).body_id
        boxes = [pybullet.getAABB(body, link, physicsClientId=client)
                 for link in range(-1, pybullet.getNumJoints(body, physicsClientId=client))]
        low, high = np.min([box[0] for box in boxes], 0), np.max([box[1] for box in boxes], 0)
        # The whole robot in view, whatever its size: the camera backs off with its extent.
        distance = 0.1 + 0.75 * float(np.linalg.norm(high - low))
        view = pybullet.computeViewMatrixFromYawPitchRoll(tuple((low + high) / 2), distance, 35.0, -30.0, 0.0, 2,
                                                          physicsClientId=client)
        projection = pybullet.computeProjectionMatrixFOV(50.0, width / height, 0.05, 10.0, physicsClientId=client)
        _, _, rgba, _, _ = pybullet.getCameraImage(width, height, view, projection,
                                                   renderer=pybullet.ER_TINY_RENDERER, physicsClientId=client)
    finally:
        pybullet.disconnect(client)
    return np.asarray(rgba, dtype=np.uint8).reshape(height, width, 4)[..., :3]


class Panel(NamedTuple):
    """One morphology's picture in the figure and the lines of its title."""

    derivation: str
    side: str
    links: int
    lines: tuple[str, ...]


def specialist_panels(specialists) -> dict[str, Panel]:
    """A panel per specialist's morphology: its side, index and size, and the median over its
    seeds of the grid mean and the worst design."""
    by_morphology: dict[str, list] = {}
    for score in specialists:
        by_morphology.setdefault(score.derivation, []).append(score)
    panels = {}
    for derivation, scores in by_morphology.items():
        first = scores[0]
        mean = float(np.median([score.mean_displacement for score in scores]))
        worst = float(np.median([score.worst_displacement for score in scores]))
        seeds = "" if len(scores) == 1 else f" ({len(scores)} seeds)"
        lines = (f"{first.side} {first.index}, {first.links} links",
                 f"specialist {mean:.2f} m{seeds}", f"worst design {worst:.2f} m")
        panels[derivation] = Panel(derivation, first.side, first.links, lines)
    return panels


def figure_panels(specialists, comparisons) -> list[Panel]:
    """Every specialist's morphology, then every other morphology an entry was evaluated on, each
    with every entry's grid mean on it (the median over its runs there, with their count where
    more than one): an entry cut to one robot adds a line to that robot's panel, it does not
    replace the others."""
    panels = specialist_panels(specialists)
    by_entry: dict[str, dict[str, list[float]]] = {}
    for row in comparisons:
        if row.derivation not in panels:
            head = (f"{row.side}, {row.links} links",
                    "specialist " + ("-" if row.specialist is None else f"{row.specialist:.2f} m"))
            panels[row.derivation] = Panel(row.derivation, row.side, row.links, head)
        by_entry.setdefault(row.derivation, {}).setdefault(row.entry, []).append(row.universal)
    for derivation, entries in by_entry.items():
        lines = []
        for entry, values in entries.items():
            runs = "" if len(values) == 1 else f" ({len(values)} runs)"
            warm = " warm" if entry.endswith("from another run's policy") else ""  # started from init_policy
            name = f"{entry.split(',')[0]} x{entry.split(',')[1].split()[0]}{warm}"
            lines.append(f"{name}: {np.median(values):.2f} m{runs}")
        panels[derivation] = panels[derivation]._replace(lines=(*panels[derivation].lines, *lines))
    return list(panels.values())


def draw(panels: list[Panel], path: Path) -> None:
    """A grid of renders, one per morphology (training side first, then by size), each titled with its lines."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    order = sorted(panels, key=lambda panel: (panel.side == "held_out", panel.side, panel.links, panel.derivation))
    columns = min(6, len(order))
    rows = math.ceil(len(order) / columns)
    title_lines = max(len(panel.lines) for panel in order)  # room above each render for its title
    figure, axes = plt.subplots(rows, columns, figsize=(3.2 * columns, (2.4 + 0.12 * title_lines) * rows),
                                squeeze=False)
    for axis in axes.flat:
        axis.axis("off")
    for axis, panel in zip(axes.flat, order, strict=False):
        axis.imshow(render(panel.derivation))
        axis.set_title("\n".join(panel.lines), fontsize=7)
    figure.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    figure.savefig(path, dpi=110)
    plt.close(figure)


def _step_list(text: str) -> list[int]:
    """Comma-separated integers (their range is compare_at_matched_steps' to check)."""
    try:
        return [int(part) for part in text.split(",")]
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected comma-separated integers, got {text!r}") from None


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("roots", nargs="*", type=Path, default=[RECORDS],
                        help="folders of specialist and universal grammar runs' records or run folders "
                             "(the study's records)")
    parser.add_argument("--out", type=Path, default=DEFAULT_OUT, help=f"where the CSV and figure go ({DEFAULT_OUT})")
    parser.add_argument("--no-pictures", action="store_true", help="skip the PyBullet renders")
    parser.add_argument("--matched-steps", type=_step_list, metavar="N,N,...",
                        help="instead: each universal run against the specialists at these real env steps per "
                             "robot, from their periodic evaluations (unfinished runs too), e.g. 40000,80000,140000")
    args = parser.parse_args(argv)
    try:
        runs = [record for record in run_records.load(args.roots)[0] if is_grammar_run(record)]
    except ReportError as error:
        print(f"error: {error}", file=sys.stderr)
        return 1
    if args.matched_steps:
        try:
            rows = compare_at_matched_steps(runs, args.matched_steps)
        except ValueError as error:
            print(f"error: --matched-steps: {error}", file=sys.stderr)
            return 1
        table = format_matched_steps(rows)
        if table.count("\n") < 2:
            print("error: no universal run and specialist that both reached the first of those steps per robot",
                  file=sys.stderr)
            return 1
        print(table)
        return 0
    comparisons = compare(runs)
    specialists = specialist_scores(runs)
    if not comparisons and not specialists:
        print("error: no grammar run with a final evaluation (evaluation/morphologies.csv) under "
              f"{', '.join(map(str, args.roots))}", file=sys.stderr)
        return 1
    args.out.mkdir(parents=True, exist_ok=True)
    if specialists:
        print(format_specialists(specialists) + "\n")
        with (args.out / "specialists.csv").open("w", newline="") as file:
            writer = csv.DictWriter(file, fieldnames=list(asdict(specialists[0])))
            writer.writeheader()
            writer.writerows(asdict(score) for score in specialists)
    if not comparisons:
        print("no universal run has a final evaluation yet: the specialists only")
        if not args.no_pictures:
            draw(figure_panels(specialists, []), args.out / "morphologies.png")
            print(f"wrote {args.out / 'morphologies.png'}")
        return 0
    print(format_table(comparisons, summarize(comparisons)))
    with (args.out / "morphology_table.csv").open("w", newline="") as file:
        writer = csv.DictWriter(file, fieldnames=[*asdict(comparisons[0]), "ratio"])
        writer.writeheader()
        writer.writerows({**asdict(row), "ratio": row.ratio} for row in comparisons)
    if not args.no_pictures:
        draw(figure_panels(specialists, comparisons), args.out / "morphologies.png")
        print(f"wrote {args.out / 'morphologies.png'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
