"""The sample-efficiency league: the protocol's levels, medians, intervals and ratios on hand-made
runs, their compact records, and the queue that runs a study."""

from __future__ import annotations

import csv
import dataclasses
import math
import re
import shutil
import subprocess
from pathlib import Path

import pytest
import torch
import yaml
from omegaconf import OmegaConf

from study import queue as study_queue
from study import records
from study.league import levels as league
from study.league import report
from study.scripts import league_archive
from unipolicy_rl.report.runs import ReportError, archive_run, load_run, restore_run
from unipolicy_rl.training import metrics_file as columns
from unipolicy_rl.training.progress import evaluation_points

ROOT = Path(__file__).resolve().parents[2]


def result_of(path: Path, machine: str | None = None) -> league.RunResult:
    """A run folder's league result, through its record as the report reads it (``machine``: the
    label of runs whose seconds compare)."""
    return league.run_result(records.from_run(load_run(path, path.name), machine=machine))


# -- hand-made runs ----------------------------------------------------------------------
EVALUATED_COLUMNS = ["epoch", "imagined", columns.REAL_STEPS, columns.ELAPSED, columns.GRID_MEAN, columns.GRID_MIN]


def write_run(root: Path, entry: str, kind: str, seed: int, segments: list[tuple[int, float, float]],
              last: int, epoch_times: tuple[float, float] | None = None, cpu: float | None = None,
              cpu_from: int = 1) -> Path:
    """A run folder as train.py leaves it: its config, Hydra's choices and a metrics.csv of
    1,000-step epochs up to ``last`` real steps (one second each), evaluated at 2,000-step
    points up to 100,000 and 10,000-step ones after; ``segments`` are ``(from step, grid mean,
    worst design)``, each holding until the next. With ``epoch_times`` (collect, update), each
    real epoch logs them (``time/collect``, ``time/update``), the rest of its second being its
    evaluation; a model-based run's imagined rows then log 0.1 s of each, parts of the update.
    With ``cpu``, real epochs from ``cpu_from`` on log that many CPU seconds (``time/cpu``; earlier
    ones, as a run resumed from before the column, leave it blank); imagined rows log 1,000 s,
    which must never count."""
    path = root / f"{entry}_seed{seed}"
    (path / ".hydra").mkdir(parents=True)
    config = {"run_name": entry, "seed": seed, "source": {"name": entry.split("-")[1] if kind == "model" else "se",
                                                           "kind": kind},
              "episodes_per_epoch": 10, "robot": {"episode_length": 100}, "epochs": last // 1000,
              "evaluation": {"every_steps": 2000, "dense_until": 100_000, "then_every_steps": 10_000}}
    OmegaConf.save(OmegaConf.create(config), path / ".hydra" / "config.yaml")
    choices = {"hydra": {"runtime": {"choices": {"design": "se"}}}}
    OmegaConf.save(OmegaConf.create(choices), path / ".hydra" / "hydra.yaml")
    with (path / "metrics.csv").open("w", newline="") as file:
        fields = (EVALUATED_COLUMNS + (list(columns.EPOCH_TIMES) if epoch_times is not None else [])
                  + ([columns.CPU_TIME] if cpu is not None else []))
        writer = csv.DictWriter(file, fieldnames=fields)
        writer.writeheader()
        for epoch in range(1, last // 1000 + 1):
            steps = epoch * 1000
            if kind == "model":  # an imagined batch's row first: no evaluation on it
                imagined = {"epoch": epoch, "imagined": 1.0, columns.REAL_STEPS: steps - 1000,
                            columns.ELAPSED: epoch - 0.5}
                if epoch_times is not None:
                    imagined.update({columns.COLLECT_TIME: 0.1, columns.UPDATE_TIME: 0.1})
                if cpu is not None:
                    imagined[columns.CPU_TIME] = 1000.0
                writer.writerow(imagined)
            row = {"epoch": epoch, "imagined": 0.0, columns.REAL_STEPS: steps, columns.ELAPSED: float(epoch)}
            if epoch_times is not None:
                row.update({columns.COLLECT_TIME: epoch_times[0], columns.UPDATE_TIME: epoch_times[1]})
            if cpu is not None and epoch >= cpu_from:
                row[columns.CPU_TIME] = cpu
            if evaluation_points(steps, 2000, 100_000, 10_000) > evaluation_points(steps - 1000, 2000, 100_000, 10_000):
                mean, worst = next((m, w) for start, m, w in reversed(segments) if start <= steps)
                row.update({columns.GRID_MEAN: mean, columns.GRID_MIN: worst})
            writer.writerow(row)
    return path


RUNS = {
    # crosses 3 m once at 4,000 and falls back; walks from 10,000 on; 5 m / 2.5 m at 30,000
    ("se-trpo", "real", 0): ([(0, 0.5, -0.2), (4000, 3.2, 1.1), (6000, 2.5, 0.8), (10_000, 3.5, 1.5),
                              (30_000, 5.2, 2.6), (60_000, 5.5, 3.0)], 120_000),
    # walks three times in a row from 6,000 (exactly at the thresholds), 5 m / 2.5 m at 20,000 (exactly)
    ("se-trpo", "real", 1): ([(0, 1.0, 0.0), (6000, 3.0, 1.0), (8000, 4.0, 2.0), (20_000, 5.0, 2.5)], 110_000),
    # never walks: the mean just short, then the worst design just short; stopped at 60,000
    ("se-trpo", "real", 2): ([(0, 2.9, 1.5), (40_000, 3.5, 0.9)], 60_000),
    # walks once at 2,000 and falls back for good
    ("se-moe-trpo", "model", 0): ([(0, 0.0, -0.5), (2000, 3.1, 1.2), (4000, 1.0, 0.1)], 20_000),
    ("se-moe-trpo", "model", 1): ([(0, 0.0, 0.0), (2000, 3.5, 1.5), (4000, 5.1, 2.6)], 20_000),
    ("de-trpo", "real", 0): ([(0, 0.0, 0.0), (4000, 3.0, 1.0)], 20_000),
}


@pytest.fixture(scope="module")
def sweep(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("league")
    for (entry, kind, seed), (segments, last) in RUNS.items():
        write_run(root, entry, kind, seed, segments, last)
    return root


@pytest.fixture(scope="module")
def runs(sweep) -> dict[tuple[str, int], league.RunResult]:
    results = {}
    for entry, _, seed in RUNS:
        path = sweep / f"{entry}_seed{seed}"
        results[entry, seed] = result_of(path)
    return results


@pytest.fixture(scope="module")
def entries(runs) -> dict[str, league.Entry]:
    return {entry.name: entry for entry in league.make_entries(list(runs.values()))}


def steps_at(result: league.RunResult) -> dict[str, float | None]:
    return {key: (found.steps if found else None) for key, found in result.levels.items()}


def test_a_run_that_crosses_once_and_falls_back_walks_first_and_stays_later(runs):
    # (b) is credited at the third walking evaluation in a row (10,000, 12,000, 14,000), when it is confirmed
    assert steps_at(runs["se-trpo", 0]) == {"first_walk": 4000, "stays_walking": 14_000, "se_trpo_final": 30_000}
    assert runs["se-trpo", 0].levels["first_walk"].seconds == 4.0  # wall time at it: time/elapsed
    assert steps_at(runs["se-moe-trpo", 0]) == {"first_walk": 2000, "stays_walking": None, "se_trpo_final": None}
    # The per-run table shows each level's real steps, and the run's own training seconds there where
    # its record names the machine it ran on.
    row = next(line for line in league.format_runs([runs["se-trpo", 0]]).splitlines() if line.startswith("se-trpo"))
    assert "4,000 " in row and "30,000 " in row and " s)" not in row


@pytest.mark.parametrize("kind", ["real", "model"])
def test_wall_times_are_the_seconds_spent_training_without_the_evaluations(tmp_path, kind):
    segments, last = RUNS["se-trpo", "real", 0]
    path = write_run(tmp_path, f"se-{kind}", kind, 0, segments, last, epoch_times=(0.5, 0.25))
    timed = result_of(path)
    # first walk at 4,000 steps: 4 epochs of 0.75 s training each (the imagined rows' times are
    # parts of their epoch's update, not added again), not the 4 s since the start
    assert timed.levels["first_walk"].seconds == 3.0
    assert timed.levels["se_trpo_final"].seconds == 30 * 0.75


@pytest.mark.parametrize("kind", ["real", "model"])
def test_cpu_seconds_add_up_the_real_epochs_and_a_run_missing_a_part_has_none(tmp_path, kind):
    segments, last = RUNS["se-trpo", "real", 0]
    path = write_run(tmp_path, f"se-{kind}", kind, 0, segments, last, epoch_times=(0.5, 0.25), cpu=1.5)
    timed = result_of(path, machine="here")
    assert timed.levels["first_walk"].cpu_seconds == 4 * 1.5  # the imagined rows' 1,000 s are not added
    assert timed.levels["se_trpo_final"].cpu_seconds == 30 * 1.5
    row = next(line for line in league.format_runs([timed]).splitlines() if line.startswith("se-"))
    assert "4,000 (3 s, 6 CPU s)" in row

    # Resumed from a commit before the column: no sum with its first part missing.
    partial = write_run(tmp_path / "partial", f"se-{kind}", kind, 1, segments, last, epoch_times=(0.5, 0.25),
                        cpu=1.5, cpu_from=3)
    resumed = result_of(partial, machine="here")
    assert math.isnan(resumed.levels["first_walk"].cpu_seconds)
    both = league.make_entries([timed, resumed], resamples=200)[0].levels["first_walk"]
    alone = league.make_entries([timed], resamples=200)[0].levels["first_walk"]
    assert math.isnan(both.cpu_seconds) and alone.cpu_seconds == 6.0
    table = league.format_league(league.make_entries([timed], resamples=200))
    walk = table.splitlines()[table.splitlines().index(next(line for line in table.splitlines()
                                                             if line.startswith("(a)"))) + 2]
    assert re.search(r"\]\s+(\S+)\s+(\S+)", walk).groups() == ("3", "6")  # after the interval: wall s, CPU s
    assert "median CPU s" in table


def test_three_walking_evaluations_in_a_row_stay_walking_from_the_third_of_them(runs):
    assert steps_at(runs["se-trpo", 1]) == {"first_walk": 6000, "stays_walking": 10_000, "se_trpo_final": 20_000}
    assert steps_at(runs["se-moe-trpo", 1]) == {"first_walk": 2000, "stays_walking": 6000, "se_trpo_final": 4000}


def test_a_run_short_of_either_threshold_never_walks(runs):
    assert steps_at(runs["se-trpo", 2]) == {"first_walk": None, "stays_walking": None, "se_trpo_final": None}
    evaluations = runs["se-trpo", 2].evaluations
    assert [e.steps for e in evaluations[:3]] == [2000, 4000, 6000] and evaluations[-1].steps == 60_000


def test_a_gym_run_is_finished_by_its_final_returns_and_its_archive_keeps_no_checkpoint(tmp_path):
    path = write_run(tmp_path, "Pendulum-v1-moe-trpo", "model", 0, [(0, 1.0, 0.0)], 20_000)
    torch.save({"epoch": 20, "policy": {"actor": torch.ones(2)}}, path / "checkpoint.pt")
    assert not load_run(path, path.name).finished
    (path / "evaluation").mkdir()
    (path / "evaluation" / "returns.csv").write_text("episode,return\n0,-150.0\n")
    assert load_run(path, path.name).finished
    files = archive_run(path, tmp_path / "archive", checkpoint_limit=2**20)
    assert Path("checkpoint.pt") not in files and Path("evaluation/returns.csv") in files


def test_a_run_resumed_with_a_larger_budget_is_unfinished_until_it_gets_there(tmp_path):
    """Its final evaluation of the first budget stays in the folder; the run is not done meanwhile."""
    path = write_run(tmp_path, "se-sac", "real", 0, [(0, 1.0, 0.0)], 20_000)
    designs = path / "evaluation" / "designs.csv"
    designs.parent.mkdir()
    designs.write_text("length,density,episodes,mean_episode_reward,std_episode_reward,mean_forward_displacement,"
                       "std_forward_displacement,mean_forward_speed,physics_faults\n0.15,0.4,1,1.0,0.0,1.0,0.0,0.1,0\n")
    assert load_run(path, path.name).finished
    config = OmegaConf.load(path / ".hydra" / "config.yaml")
    config.epochs = 30  # resume=... epochs=30: trained to 20 so far
    OmegaConf.save(config, path / ".hydra" / "config.yaml")
    assert not load_run(path, path.name).finished
    assert not result_of(path).finished


def test_the_grid_is_read_at_the_first_evaluation_at_or_after_each_milestone(runs, entries):
    se0, se2 = runs["se-trpo", 0].milestones, runs["se-trpo", 2].milestones
    assert (se0[50_000].steps, se0[50_000].grid_mean, se0[50_000].grid_min) == (50_000, 5.2, 2.6)
    assert (se0[100_000].grid_mean, se0[100_000].grid_min) == (5.5, 3.0) and se0[300_000] is None
    assert se2[50_000].grid_min == 0.9 and se2[100_000] is None  # stopped at 60,000
    assert entries["se-trpo"].milestones[50_000] == (5.0, 2.5, 3)  # medians of (5.2, 5.0, 3.5), (2.6, 2.5, 0.9)
    assert entries["se-trpo"].milestones[100_000] == (5.25, 2.75, 2)
    assert 300_000 not in entries["se-trpo"].milestones


def test_a_run_that_never_reached_a_level_counts_as_longer_than_any_that_did(entries):
    se = entries["se-trpo"].levels
    assert (se["first_walk"].reached, se["first_walk"].runs, se["first_walk"].steps) == (2, 3, 6000)
    assert se["stays_walking"].steps == 14_000 and se["se_trpo_final"].steps == 30_000  # the larger of the two
    assert se["first_walk"].seconds == 6.0
    moe = entries["se-moe-trpo"].levels
    assert moe["first_walk"].steps == 2000
    assert math.isinf(moe["stays_walking"].steps) and moe["stays_walking"].reached == 1  # 1 of 2: not reached
    assert not entries["se-moe-trpo"].model_free and entries["de-trpo"].model_free


def test_the_bootstrap_interval_holds_the_median_and_is_reproducible(entries):
    for entry in entries.values():
        for stats in entry.levels.values():
            low, high = stats.steps_interval
            assert low <= stats.steps <= high
    values = [4000, 6000, math.inf]
    assert league.bootstrap_interval(values, seed=3) == league.bootstrap_interval(values, seed=3)
    assert league.bootstrap_interval(values) == (4000, math.inf)  # a bound may be "not reached"
    low, high = league.bootstrap_interval([1.0, 2.0, 3.0, 4.0, 5.0], resamples=2000, seed=1)
    assert 1.0 <= low <= 3.0 <= high <= 5.0 and low < high
    assert league.bootstrap_interval([7.0]) == (7.0, 7.0)


def test_ratios_against_se_trpo_and_the_best_model_free_entry(entries):
    ordered = list(entries.values())
    assert [entry.name for entry in ordered] == ["se-trpo", "de-trpo", "se-moe-trpo"]
    assert league.best_model_free(ordered, "first_walk").name == "de-trpo"  # 4,000 < 6,000
    assert league.best_model_free(ordered, "se_trpo_final").name == "se-trpo"  # de-trpo never got there
    assert league.ratio_lines(ordered, "first_walk") == {
        "se-trpo": ("1.0x fewer", "0.7x fewer"),
        "de-trpo": ("1.5x fewer", "1.0x fewer"),
        "se-moe-trpo": ("3.0x fewer", "2.0x fewer"),
    }
    # cut before their budget without the level (hand-made runs have no final evaluation): censored
    assert league.ratio_lines(ordered, "se_trpo_final")["de-trpo"] == ("- (cut)", "- (cut)")
    assert league.ratio_lines(ordered, "stays_walking")["se-moe-trpo"] == ("- (cut)", "- (cut)")
    done = league.make_entries([dataclasses.replace(run, finished=True) for entry in ordered for run in entry.runs],
                               resamples=200)
    assert league.ratio_lines(done, "se_trpo_final")["de-trpo"] == ("not reached", "not reached")
    assert league.fewer(math.inf, 5.0) == math.inf and math.isnan(league.fewer(math.inf, math.inf))


def test_the_benchmark_prints_the_table_and_draws_the_figure(sweep, tmp_path, capsys):
    assert report.main([str(sweep), "--out", str(tmp_path / "out"), "--resamples", "500"]) == 0
    printed = capsys.readouterr().out
    assert "(a) first_walk" in printed and "(c) se_trpo_final" in printed
    assert "6,000 [4,000, not reached]" in printed
    assert "5.00 / 2.50 (3/3)" in printed and "3.0x fewer" in printed
    assert (tmp_path / "out" / "league.png").stat().st_size > 0
    with (tmp_path / "out" / "league.csv").open() as file:
        rows = list(csv.DictReader(file))
    assert len(rows) == 3 * 3 and {row["entry"] for row in rows} == {"se-trpo", "de-trpo", "se-moe-trpo"}


def test_compact_records_rebuild_the_same_league_as_the_run_folders(sweep, tmp_path, capsys):
    assert records.main([str(sweep), str(tmp_path / "records")]) == 0
    assert f"wrote {len(RUNS)} records" in capsys.readouterr().out

    def printed(root: Path) -> list[str]:
        assert report.main([str(root), "--out", str(tmp_path / "out"), "--resamples", "500"]) == 0
        return [line for line in capsys.readouterr().out.splitlines() if not line.startswith("wrote")]

    assert printed(tmp_path / "records") == printed(sweep)
    name = "se-trpo_seed0"
    kept = records.read(tmp_path / "records" / name, name)
    original = records.from_run(load_run(sweep / name, name))
    assert repr(kept.evaluations) == repr(original.evaluations)  # NaN where neither logged CPU seconds
    assert len(kept.evaluations) == 52  # every 2,000 to 100,000, then 110,000 and 120,000
    assert (kept.entry, kept.seed, kept.model_free, kept.finished, kept.budget, kept.machine) == (
        "se-trpo", 0, True, False, 120, None)
    labelled = records.read(records.write(records.from_run(load_run(sweep / name, name), machine="here"),
                                          tmp_path / "labelled"), name)
    assert labelled.machine == "here" and repr(labelled.evaluations) == repr(original.evaluations)
    assert sorted(path.name for path in (tmp_path / "records" / name).iterdir()) == [
        "commands.txt", "evaluations.csv", "record.yaml"]


def test_training_columns_keep_each_epoch_s_last_real_row_and_a_column_no_run_has_is_refused(tmp_path, capsys):
    path = write_run(tmp_path / "runs", "se-moe-trpo", "model", 0, [(0, 1.0, 0.0)], 3000)
    metrics = path / "metrics.csv"
    lines = metrics.read_text().splitlines()
    header = lines[0].split(",")
    epoch, imagined = header.index("epoch"), header.index("imagined")
    lines[0] += ",train/alpha"
    for i, line in enumerate(lines[1:], start=1):
        cells = line.split(",")
        lines[i] += f",{'9' if cells[imagined] == '1.0' else cells[epoch]}"  # imagined rows: 9, never kept
    lines.append(lines[-1].rsplit(",", 1)[0] + ",7")  # the last epoch logged again, as after a resume
    metrics.write_text("\n".join(lines) + "\n")
    assert records.main([str(tmp_path / "runs"), str(tmp_path / "records"), "--training-columns", "train/alpha"]) == 0
    kept = (tmp_path / "records" / path.name / "training.csv").read_text().splitlines()
    assert kept[0] == "epoch,real_env_steps,train/alpha"
    assert [row.split(",")[-1] for row in kept[1:]] == ["1", "2", "7"]
    # A column some runs lack (another learner's) is kept where it is, and said where it is not;
    # one that no run has (a typo) is refused.
    other = write_run(tmp_path / "runs", "se-trpo", "real", 0, [(0, 1.0, 0.0)], 3000)
    capsys.readouterr()
    assert records.main([str(tmp_path / "runs"), str(tmp_path / "both"), "--training-columns", "train/alpha"]) == 0
    assert (tmp_path / "both" / path.name / "training.csv").read_text().splitlines() == kept
    assert not (tmp_path / "both" / other.name / "training.csv").exists()
    assert f"{other.name}: its metrics.csv has no column train/alpha" in capsys.readouterr().err
    assert records.main([str(tmp_path / "runs"), str(tmp_path / "other"), "--training-columns", "train/nope"]) == 1
    assert "no run's metrics.csv has the column train/nope" in capsys.readouterr().err


def test_seconds_show_only_where_every_run_ran_on_one_machine_and_each_seed_counts_once(sweep, tmp_path, capsys):
    def wall_of_se_trpo_first_walk(table: str) -> str:
        lines = table.splitlines()
        row = lines[lines.index(next(line for line in lines if line.startswith("(a)"))) + 2]
        return re.search(r"\]\s+(\S+)\s+(\S+)", row).group(1)

    runs = [sweep / f"{entry}_seed{seed}" for entry, _, seed in RUNS]
    one = [result_of(path, machine="A") for path in runs]
    assert wall_of_se_trpo_first_walk(league.format_league(league.make_entries(one, resamples=100))) == "6"
    mixed = [result_of(path, machine="A" if i else "B") for i, path in enumerate(runs)]
    table = league.format_league(league.make_entries(mixed, resamples=100))
    assert wall_of_se_trpo_first_walk(table) == "-" and "do not compare" in table
    unlabelled = [result_of(path) for path in runs]
    assert wall_of_se_trpo_first_walk(league.format_league(league.make_entries(unlabelled, resamples=100))) == "-"

    for label in ("A", "B"):
        assert records.main([str(sweep), str(tmp_path / label), "--machine", label]) == 0
    capsys.readouterr()
    assert report.main([str(tmp_path / "A"), str(tmp_path / "B"), "--out", str(tmp_path / "out")]) == 1
    assert "se-trpo seed 0 in A/se-trpo_seed0, B/se-trpo_seed0" in capsys.readouterr().err
    assert report.main([str(tmp_path / "A"), str(tmp_path / "B"), "--out", str(tmp_path / "out"), "--entries",
                        "se-trpo", "--seeds", "0-1", "--resamples", "100"]) == 1  # still both roots' seeds 0-1
    assert report.main([str(tmp_path / "A"), "--out", str(tmp_path / "out"), "--entries", "se-trpo",
                        "--seeds", "0-1", "--resamples", "100"]) == 0
    printed = capsys.readouterr().out
    assert "se-trpo  model-free     2  0, 1 " in printed and "de-trpo" not in printed


def load_queue():
    return study_queue


def test_the_queue_plans_every_entrys_seed_in_turn_and_resumes_a_started_run(tmp_path):
    queue = load_queue()
    assert queue.parse_seeds("0-2,7") == [0, 1, 2, 7]
    plan = yaml.safe_load(queue.PLAN.read_text())  # (every entry composes: the test below)
    runs = queue.plan_runs(plan, ["se-trpo", "se-moe-trpo"], [0, 1], tmp_path)
    assert [(run.entry, run.seed) for run in runs] == [("se-trpo", 0), ("se-moe-trpo", 0), ("se-trpo", 1),
                                                       ("se-moe-trpo", 1)]
    fresh = runs[0].command("python")
    assert "seed=0" in fresh and "epochs=600" in fresh and not any(part.startswith("resume=") for part in fresh)
    assert runs[0].epochs_done() == 0
    runs[0].folder.mkdir(parents=True)
    torch.save({"epoch": 12}, runs[0].folder / "checkpoint.pt")
    assert runs[0].epochs_done() == 12
    assert runs[0].command("python")[-1] == f"resume={runs[0].folder / 'checkpoint.pt'}"
    with pytest.raises(SystemExit, match="se-a2c"):
        queue.plan_runs(plan, ["se-a2c"], [0], tmp_path)


def committed_code(folder: Path, train_script: str) -> Path:
    """A one-commit repository whose train.py is ``train_script``: what a queue runs, without training."""
    folder.mkdir()
    (folder / "train.py").write_text(train_script)
    commit = ["-c", "user.name=t", "-c", "user.email=t@t", "commit", "-qm", "c"]
    for command in (["init", "-q"], ["add", "train.py"], commit):
        subprocess.run(["git", *command], cwd=folder, check=True)
    return folder


def test_a_queue_resumes_a_run_stopped_during_its_final_evaluation_and_skips_an_evaluated_one(tmp_path, capsys):
    queue = load_queue()
    # A train.py that, resumed, writes its final evaluation and records how it was called.
    code = committed_code(tmp_path / "code", """import sys
from pathlib import Path
arguments = dict(part.split("=", 1) for part in sys.argv[1:])
folder = Path(arguments["hydra.run.dir"])
(folder / "evaluation").mkdir()
(folder / "evaluation" / "designs.csv").write_text("design\\n")
(folder / "called.txt").write_text(arguments.get("resume", "no resume"))
""")
    (tmp_path / "plan.yaml").write_text(yaml.safe_dump({"se-trpo": {"overrides": ["source=se"], "epochs": 3}}))
    folders = [tmp_path / "runs" / "se-trpo" / f"seed{seed}" for seed in (0, 1)]
    for folder in folders:
        folder.mkdir(parents=True)
        torch.save({"epoch": 3}, folder / "checkpoint.pt")
    (folders[1] / "evaluation").mkdir()
    (folders[1] / queue.FINAL_EVALUATIONS[0]).write_text("design\n")
    assert queue.main(["--code", str(code), "--runs", str(tmp_path / "runs"), "--plan", str(tmp_path / "plan.yaml"),
                       "--entries", "se-trpo", "--seeds", "0-1", "--jobs", "1"]) == 0
    printed = capsys.readouterr().out
    assert "seed 0: trained (3 of 3 epochs), resumed for its final evaluation" in printed
    assert (folders[0] / "called.txt").read_text() == str(folders[0] / "checkpoint.pt")
    assert (folders[0] / queue.FINAL_EVALUATIONS[0]).is_file()
    assert "seed 1: done (3 of 3 epochs)" in printed and not (folders[1] / "called.txt").exists()


def test_a_run_still_going_is_counted_apart_from_one_that_finished_without_the_level(runs):
    """Hand-made runs have no final evaluation: they have not trained to their budget. se-trpo seed 2
    has not walked yet: it may still, so it is counted unfinished at every level; finished, it never walked."""
    se = [runs["se-trpo", seed] for seed in range(3)]
    going = league.level_stats(se, "first_walk", resamples=100)
    assert (going.reached, going.unfinished) == (2, 1)
    done = league.level_stats([dataclasses.replace(run, finished=True) for run in se], "first_walk", resamples=100)
    assert (done.reached, done.unfinished, done.steps) == (2, 0, going.steps)
    table = league.format_league(league.make_entries(se, resamples=100))
    assert "2/3 (1 cut)" in table
    assert league.format_runs(se).splitlines()[3].endswith("cut")


def test_the_median_is_bounded_below_by_what_the_unfinished_runs_can_still_reach(tmp_path):
    """Three runs cut at 20,000: one walks from 4,000 on, one has not walked, one walks at its last
    two evaluations (18,000 and 20,000). (b)'s median is not known (two runs have no streak of
    three): it is not reached by 20,000, the earliest the cut runs could have completed one."""
    segments = {0: [(0, 1.0, 0.0), (4000, 3.5, 1.5)], 1: [(0, 1.0, 0.0)], 2: [(0, 1.0, 0.0), (18_000, 3.5, 1.5)]}
    runs = []
    for seed, walks in segments.items():
        path = write_run(tmp_path, "se-sac", "real", seed, walks, 20_000)
        runs.append(result_of(path))
    assert [league.earliest_still_possible(run.evaluations, "stays_walking") for run in runs[1:]] == [20_000, 20_000]
    stays = league.level_stats(runs, "stays_walking", resamples=100)
    assert (stays.reached, stays.unfinished, stays.steps, stays.steps_at_least) == (1, 2, math.inf, 20_000)
    first = league.level_stats(runs, "first_walk", resamples=100)
    assert (first.steps, first.steps_at_least) == (18_000, 18_000)  # known: the runs' own first walks decide it
    table = league.format_league(league.make_entries(runs, resamples=100))
    assert "1/3 (2 cut)  not reached by 20,000 (cut)" in table
    finished = league.level_stats([dataclasses.replace(run, finished=True) for run in runs], "stays_walking",
                                  resamples=100)
    assert (finished.unfinished, finished.steps_at_least) == (0, finished.steps)  # nothing left to go on


def test_the_archived_records_give_the_same_league_without_the_checkpoints(sweep, tmp_path, capsys):
    archive = league_archive
    runs = tmp_path / "runs"
    for (entry, kind, seed), (segments, last) in RUNS.items():
        path = write_run(runs, entry, kind, seed, segments, last)
        (path / "checkpoint.pt").write_bytes(b"weights")
        (path / "evaluation").mkdir()
        (path / "evaluation" / "designs.csv").write_text("length,density,displacement\n0.15,0.4,3.0\n")
    (runs / "started_seed9" / ".hydra").mkdir(parents=True)  # never finished an epoch: nothing to keep
    (runs / "started_seed9" / "checkpoint.pt").write_bytes(b"weights")
    assert archive.main([str(runs), str(tmp_path / "kept")]) == 0
    assert f"archived {len(RUNS)} of {len(RUNS) + 1} runs" in capsys.readouterr().out
    kept = tmp_path / "kept" / "se-trpo_seed0"
    assert sorted(str(path.relative_to(kept)) for path in kept.rglob("*") if path.is_file()) == [
        ".hydra/config.yaml", ".hydra/hydra.yaml", "evaluation/designs.csv", "metrics.csv"]
    for entry, _, seed in RUNS:
        name = f"{entry}_seed{seed}"
        original = result_of(runs / name)
        copy = result_of(tmp_path / "kept" / name)
        assert steps_at(copy) == steps_at(original) and copy.finished == original.finished


def test_a_queue_carrying_checkpoints_resumes_a_run_whose_folder_went_with_its_machine(tmp_path, capsys):
    queue = load_queue()
    # A train.py that trains one epoch a call: a metrics row and a checkpoint, resumed from the one it is given.
    code = committed_code(tmp_path / "code", """import sys, torch
from pathlib import Path
arguments = dict(part.split("=", 1) for part in sys.argv[1:])
folder = Path(arguments["hydra.run.dir"])
epoch = torch.load(arguments["resume"])["epoch"] + 1 if "resume" in arguments else 1
with open(folder / "metrics.csv", "a") as metrics:
    metrics.write("epoch,real_env_steps\\n" if epoch == 1 else "")
    metrics.write(f"{epoch},{1000 * epoch}\\n")
torch.save({"epoch": epoch}, folder / "checkpoint.pt")
""")
    (tmp_path / "plan.yaml").write_text(yaml.safe_dump({"se-trpo": {"overrides": ["source=se"], "epochs": 5}}))
    arguments = ["--code", str(code), "--runs", str(tmp_path / "runs"), "--plan", str(tmp_path / "plan.yaml"),
                 "--entries", "se-trpo", "--seeds", "0", "--archive", str(tmp_path / "kept")]
    assert queue.main(arguments + ["--carry-checkpoints", "1"]) == 0
    kept = tmp_path / "kept" / "se-trpo" / "seed0"
    assert torch.load(kept / "checkpoint.pt")["epoch"] == 1
    shutil.rmtree(tmp_path / "runs")  # the machine, and its run folders, went back
    assert queue.main(arguments + ["--carry-checkpoints", "1"]) == 0
    assert "se-trpo seed 0: restored from" in capsys.readouterr().out
    folder = tmp_path / "runs" / "se-trpo" / "seed0"
    assert "resume=" in (folder / "commands.txt").read_text().splitlines()[-1]
    assert (folder / "metrics.csv").read_text().splitlines() == ["epoch,real_env_steps", "1,1000", "2,2000"]
    assert torch.load(kept / "checkpoint.pt")["epoch"] == 2
    # Without the flag nothing is carried: a checkpoint above the limit stays behind, and an archive is
    # never restored over a run folder's own checkpoint.
    assert queue.main(arguments + ["--carry-checkpoints", "0.00001"]) == 0
    assert torch.load(kept / "checkpoint.pt")["epoch"] == 2 and torch.load(folder / "checkpoint.pt")["epoch"] == 3
    with pytest.raises(ReportError, match="of its own"):
        restore_run(kept, folder)
    with pytest.raises(SystemExit):
        queue.main(arguments[:-2] + ["--carry-checkpoints", "1"])  # no --archive to carry them in
    # Finished (its final evaluation written), a run has nothing to resume: the archive drops its checkpoint
    # and keeps its final policy alone, for runs that learn from it.
    (folder / "evaluation").mkdir()
    (folder / queue.FINAL_EVALUATIONS[0]).write_text("design\n")
    torch.save({"epoch": 3, "policy": {"actor": torch.ones(2)}, "learner": {"critic": torch.ones(2)}},
               folder / "checkpoint.pt")
    files = archive_run(folder, kept, checkpoint_limit=2**20)
    assert Path("checkpoint.pt") not in files and not (kept / "checkpoint.pt").exists()
    assert (kept / queue.FINAL_EVALUATIONS[0]).is_file()
    policy = torch.load(kept / "policy.pt")
    assert Path("policy.pt") in files and policy["resumable"] is False and "learner" not in policy
    assert torch.equal(policy["policy"]["actor"], torch.ones(2))
    assert Path("policy.pt") not in archive_run(folder, tmp_path / "plain")  # not carrying: no policy either


def test_a_queue_past_its_stop_time_starts_no_run(tmp_path, capsys):
    queue = load_queue()
    code = committed_code(tmp_path / "code", "raise SystemExit('must not run')\n")
    assert queue.main(["--code", str(code), "--runs", str(tmp_path / "runs"), "--entries", "se-trpo", "--seeds", "0-1",
                       "--stop-after", "0"]) == 0
    printed = capsys.readouterr().out
    assert "--stop-after reached" in printed and "started" not in printed
    assert not (tmp_path / "runs").exists()


def test_a_queue_stopping_at_a_level_stops_each_run_there_and_starts_none_that_reached_it(tmp_path, capsys,
                                                                                         monkeypatch):
    queue = load_queue()
    monkeypatch.setattr(queue, "LEVEL_CHECK_SECONDS", 0.0)
    # A train.py that evaluates every epoch (1,000 real steps) and reaches (c) at its third; on SIGTERM
    # it ends at its epoch's end, as train.py does.
    code = committed_code(tmp_path / "code", f"""import signal, sys, time
from pathlib import Path
arguments = dict(part.split("=", 1) for part in sys.argv[1:])
folder = Path(arguments["hydra.run.dir"])
stop = []
signal.signal(signal.SIGTERM, lambda *_: stop.append(1))
with open(folder / "metrics.csv", "w") as metrics:
    metrics.write("epoch,real_env_steps,{columns.GRID_MEAN},{columns.GRID_MIN}\\n")
    for epoch in range(1, 200):
        walks = epoch >= 3
        metrics.write(f"{{epoch}},{{1000 * epoch}},{{5.5 if walks else 1.0}},{{3.0 if walks else 0.0}}\\n")
        metrics.flush()
        if stop:
            break
        time.sleep(0.05)
""")
    (tmp_path / "plan.yaml").write_text(yaml.safe_dump({"se-trpo": {"overrides": ["source=se"], "epochs": 199}}))
    arguments = ["--code", str(code), "--runs", str(tmp_path / "runs"), "--plan", str(tmp_path / "plan.yaml"),
                 "--entries", "se-trpo", "--seeds", "0", "--stop-at-level", "c", "--stop-from-steps", "6000"]
    assert queue.main(arguments) == 0
    assert "se-trpo seed 0: level (c) reached at 3,000 real env steps; stopping it" in capsys.readouterr().out
    metrics = (tmp_path / "runs" / "se-trpo" / "seed0" / "metrics.csv").read_text().splitlines()
    assert 6 <= len(metrics) - 1 < 150  # past --stop-from-steps, then stopped long before its budget
    assert queue.main(arguments) == 0  # a run that reached the level is not started again
    printed = capsys.readouterr().out
    assert "se-trpo seed 0: level (c) reached at 3,000 real env steps" in printed and "started" not in printed
    with pytest.raises(SystemExit):
        queue.main(arguments[:-4] + ["--stop-from-steps", "6000"])  # a step floor without a level


def test_no_two_of_many_entries_are_drawn_alike():
    from study.league.levels import line_style

    looks = [line_style(i) for i in range(40)]
    assert len({(tuple(colour), style) for colour, style in looks}) == 40
    assert looks[3][1] == "-" and looks[13][0] == looks[3][0] and looks[13][1] != looks[3][1]


def test_every_league_plan_entry_runs_under_its_own_name():
    """league.py groups runs into entries by the run name in their config: an entry whose overrides
    leave the name another entry's (a setting on top of source=moe keeps se-moe-trpo) would have
    its seeds counted as that entry's."""
    import yaml
    from hydra import compose, initialize_config_dir
    from hydra.core.hydra_config import HydraConfig
    from omegaconf import OmegaConf

    entries = yaml.safe_load((ROOT / "study" / "league_plan.yaml").read_text())
    try:
        with initialize_config_dir(str(ROOT / "conf"), version_base=None):
            for name, entry in entries.items():
                cfg = compose("config", overrides=[*entry["overrides"], "seed=0"], return_hydra_config=True)
                HydraConfig.instance().set_config(cfg)  # run_name interpolates Hydra's choices
                assert OmegaConf.select(cfg, "run_name") == name, f"{name}: add run_name={name} to its overrides"
    finally:
        HydraConfig.instance().cfg = None  # (a process-wide singleton; no other test should see this one)


@pytest.mark.parametrize("plan", ["league_plan.yaml", "morphology_plan.yaml", "holding/plan.yaml", "gym/plan.yaml"])
def test_every_entry_of_the_queue_plans_composes_and_passes_validation(plan):
    """A typo in a plan's overrides would fail a run hours into a queue; here it fails at once."""
    import yaml
    from hydra import compose, initialize_config_dir

    from unipolicy_rl.validation import validate_config

    entries = yaml.safe_load((ROOT / "study" / plan).read_text())
    assert entries
    with initialize_config_dir(str(ROOT / "conf"), version_base=None):
        for name, entry in entries.items():
            assert isinstance(entry["epochs"], int) and entry["epochs"] > 0, name
            validate_config(compose("config", overrides=[*entry["overrides"], "seed=0", f"epochs={entry['epochs']}"]))


def test_the_holding_figures_count_the_evaluations_after_each_level_and_read_the_policy_at_a_budget(runs):
    from study.league import holding

    se0 = runs["se-trpo", 0]  # walks at 4,000, falls back at 6,000 and 8,000, walks from 10,000; (c) from 30,000
    after_a, after_b, after_c = (holding.holding([se0], key) for key in ("first_walk", "stays_walking",
                                                                          "se_trpo_final"))
    assert (after_a.held, after_a.after) == (48, 50)  # 6,000 ... 120,000: the two falls back do not walk
    assert (after_b.held, after_b.after, after_c.held, after_c.after) == (45, 45, 37, 37)
    assert (after_b.lowest.steps, after_b.lowest.grid_min) == (16_000, 1.5)
    assert holding.holding([runs["se-moe-trpo", 0]], "stays_walking").after == 0  # never reached: nothing after

    def run(entry: str, model_free: bool, seed: int, points) -> league.RunResult:
        evaluations = [records.Evaluation(steps, 0.0, mean, worst) for steps, mean, worst in points]
        return league.run_result(records.Record(f"{entry}/seed{seed}", entry, seed, model_free, True, True, None,
                                                points[-1][0], evaluations=evaluations))

    entries = league.make_entries([
        run("se-trpo", True, 0, [(590_000, 9.0, 9.0), (600_000, 5.0, 3.0)]),
        run("se-trpo", True, 1, [(600_000, 6.0, 4.0)]),
        run("se-moe-trpo", False, 0, [(50_000, 5.6, 3.6), (100_000, 5.4, 3.4)]),
        run("se-moe-trpo", False, 1, [(50_000, 5.6, 3.0), (98_000, 6.0, 6.0)]),  # cut before 100,000
    ], resamples=100)
    assert holding.target(entries) == (5.5, 3.5)  # the medians at 600,000, not the best evaluation
    moe = next(entry for entry in entries if entry.name == "se-moe-trpo")
    at50, at100 = (holding.at_budget(moe, steps, (5.5, 3.5)) for steps in holding.budgets(moe))
    assert (at50.there, at50.at_target, at50.grid_mean, at100.there, at100.at_target) == (2, 1, 5.6, 1, 0)
    text = holding.format_holding(entries)
    assert "se-trpo's final median (5.50 m / 3.50 m, at 600,000)" in text
    assert "se-moe-trpo     50,000  5.60 / 3.30 (2/2)        1/2" in text


def test_a_run_whose_metrics_are_garbage_is_left_out_for_that_reason(tmp_path, capsys):
    good = write_run(tmp_path, "se-trpo", "real", 0, [(0, 3.5, 1.5)], last=10_000)
    bad = write_run(tmp_path, "se-trpo", "real", 1, [(0, 3.5, 1.5)], last=10_000)
    (bad / "metrics.csv").write_text("\x00\x01 not a csv at all\n")
    assert good.exists()
    assert report.main([str(tmp_path), "--out", str(tmp_path / "out"), "--resamples", "100"]) == 0
    stderr = capsys.readouterr().err
    assert "se-trpo_seed1" in stderr and "unreadable" in stderr and "no periodic grid evaluation" not in stderr


def test_the_queue_runs_as_a_script_its_name_shadowing_no_module_torch_imports():
    import subprocess
    import sys

    script = Path(__file__).resolve().parents[1] / "queue.py"
    result = subprocess.run([sys.executable, str(script), "--help"], capture_output=True, text=True, timeout=300,
                            check=False)
    assert result.returncode == 0, result.stderr[-2000:]
    assert "--plan" in result.stdout
