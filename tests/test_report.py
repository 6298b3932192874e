"""The sweep report: every figure and the table from a real (tiny) sweep, lost jobs reported
rather than fatal, mixed robots refused, bad input named in one line."""

from __future__ import annotations

import math
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from omegaconf import OmegaConf

from unipolicy_rl.envs import DesignDistribution
from unipolicy_rl.evaluation import DesignResult
from unipolicy_rl.report import ReportError, build_report, generalisation
from unipolicy_rl.report.__main__ import main
from unipolicy_rl.report.bands import T_975, seed_band
from unipolicy_rl.report.grids import best_achievable, relative_performance, seed_mean
from unipolicy_rl.report.groups import group_runs
from unipolicy_rl.report.metrics import (
    DISPLACEMENT,
    REWARD,
    elapsed_seconds,
    median_to_walk,
    real_env_steps,
    series,
)
from unipolicy_rl.report.runs import Run

ROOT = Path(__file__).resolve().parents[1]
TINY = ["epochs=2", "episodes_per_epoch=2", "robot.episode_length=10", "evaluation.grid=2", "progress_bar=false",
        "algo.critic_epochs=2", "workers=1"]
FIGURES = {"curves_real_steps", "curves_wall_time", "grid_reward", "grid_displacement", "relative_performance",
           "generalisation"}


def train(*overrides: str) -> None:
    result = subprocess.run([sys.executable, str(ROOT / "train.py"), *overrides, *TINY], cwd=ROOT,
                            capture_output=True, text=True, timeout=300, check=False)
    assert result.returncode == 0, result.stderr


@pytest.fixture(scope="module")
def sweeps(tmp_path_factory) -> tuple[Path, Path]:
    """A DE/SE sweep of two seeds each, and one DE run trained at the grid corner (0.15, 0.4)."""
    base = tmp_path_factory.mktemp("sweeps")
    train("-m", "source=de,se", "seed=0,1", f"hydra.sweep.dir={base / 'sweep'}")
    # The README's reference sweep, cut to one design.
    train("-m", "source=de", "design=fixed", "design.length=0.15", "design.density=0.4", "seed=0",
          f"hydra.sweep.dir={base / 'best'}",
          "hydra.sweep.subdir=de_l${design.length}_rho${design.density}_seed${seed}")
    return base / "sweep", base / "best"


@pytest.fixture(scope="module")
def report(sweeps, tmp_path_factory):
    return build_report(list(sweeps), tmp_path_factory.mktemp("report") / "out")


@pytest.mark.slow
def test_report_has_every_figure_and_the_table(report):
    assert set(report.figures) == FIGURES
    text = report.markdown.read_text()
    for name, path in report.figures.items():
        assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n", name
        assert f"]({path.name})" in text, f"report.md does not embed {path.name}"
    assert list(report.groups) == ["de-trpo", "se-trpo"]
    assert "| de-trpo | 2/2 |" in text and "| se-trpo | 2/2 |" in text
    summary = report.summary_csv.read_text().splitlines()
    assert summary[0].startswith("source,runs,finished")
    assert [row.split(",")[0] for row in summary[1:]] == ["de-trpo", "se-trpo"]
    assert "None: every run finished." in text
    # The fixed-design run is a reference, not a source: it sets the best reward at its own design.
    reference = [run for run in report.runs if run.is_reference]
    assert [run.name for run in reference] == ["best/de_l0.15_rho0.4_seed0"]
    assert reference[0].design_distribution == DesignDistribution.fixed(0.15, 0.4)
    assert "trained at the design on 1 of 4 designs" in text
    # Every final policy of the two sources walked the wider grid, cached per run.
    cached = sorted(path.name.rsplit("-", 1)[0] for path in (report.markdown.parent / "generalisation").glob("*.csv"))
    assert cached == ["de-trpo_seed0", "de-trpo_seed1", "se-trpo_seed0", "se-trpo_seed1"]
    assert "l in [0.1375, 0.2125] m, rho in [0.350, 0.650] kg/m" in text


@pytest.mark.slow
def test_a_second_report_reuses_the_cached_evaluations(report, sweeps, monkeypatch):
    def no_evaluation(*args, **kwargs):
        raise AssertionError("evaluated again although the checkpoint did not change")

    monkeypatch.setattr(generalisation, "evaluate_on_designs", no_evaluation)
    again = build_report(list(sweeps), report.markdown.parent)
    assert set(again.figures) == FIGURES


@pytest.mark.slow
def test_lost_jobs_are_reported_and_the_rest_still_is(report, sweeps, tmp_path):
    sweep = Path(shutil.copytree(sweeps[0], tmp_path / "sweep"))
    shutil.copytree(report.markdown.parent / "generalisation", tmp_path / "out" / "generalisation")
    # de seed 1 died in its first epochs: no checkpoint, no evaluation, one epoch logged.
    (sweep / "de-trpo_seed1" / "checkpoint.pt").unlink()
    shutil.rmtree(sweep / "de-trpo_seed1" / "evaluation")
    metrics = sweep / "de-trpo_seed1" / "metrics.csv"
    metrics.write_text("".join(metrics.read_text().splitlines(keepends=True)[:2]))
    # se seed 0 was killed while writing its last metrics row; se seed 1 never started.
    metrics = sweep / "se-trpo_seed0" / "metrics.csv"
    metrics.write_text(metrics.read_text()[:-40])
    shutil.rmtree(sweep / "se-trpo_seed1")

    partial = build_report([sweep], tmp_path / "out")
    assert {"curves_real_steps", "grid_reward", "generalisation"} <= set(partial.figures)
    missing = "\n".join(partial.missing)
    assert "de-trpo_seed1: no checkpoint.pt: crashed, killed or still running before its first checkpoint" in missing
    assert "(1 of 2 epochs logged)" in missing
    assert "se-trpo_seed0/metrics.csv: its last row was cut short" in missing
    assert "job source=se seed=1: no folder: not started" in missing
    text = partial.markdown.read_text()
    assert "| de-trpo | 1/2 |" in text and "| se-trpo | 1/1 |" in text
    assert "de-trpo_seed1: no checkpoint.pt" in text


@pytest.mark.slow
def test_runs_of_different_robots_are_refused(sweeps, tmp_path, capsys):
    mixed = tmp_path / "mixed"
    for name in ("de-trpo_seed0", "se-trpo_seed0"):
        shutil.copytree(sweeps[0] / name, mixed / name)
    config = mixed / "se-trpo_seed0" / ".hydra" / "config.yaml"
    edited = OmegaConf.load(config)
    edited.robot.reward.w_x = 2.0
    OmegaConf.save(edited, config)
    with pytest.raises(ReportError, match=r"different robots or reward weights .*robot\.reward\.w_x"):
        build_report([mixed], tmp_path / "out")
    assert main([str(mixed), "--out", str(tmp_path / "out")]) == 1
    error = capsys.readouterr().err.strip().splitlines()
    assert len(error) == 1 and str(mixed) in error[0] and "se-trpo_seed0" in error[0]


@pytest.mark.slow
def test_unreadable_files_are_named_and_the_rest_reported(sweeps, tmp_path):
    sweep = Path(shutil.copytree(sweeps[0], tmp_path / "sweep"))
    (sweep / "se-trpo_seed0" / "metrics.csv").write_bytes(b"\xff\xfe\x00garbage")
    (sweep / "de-trpo_seed0" / "evaluation" / "designs.csv").write_text("length,density\nnot,numbers\n")
    (sweep / "multirun.yaml").write_text("hydra: [unexpected")
    partial = build_report([sweep], tmp_path / "out", wide_grid=0)
    missing = "\n".join(partial.missing)
    assert f"{sweep / 'multirun.yaml'}: could not be expanded" in missing
    assert f"unreadable {sweep / 'se-trpo_seed0' / 'metrics.csv'}" in missing
    assert f"unreadable {sweep / 'de-trpo_seed0' / 'evaluation' / 'designs.csv'}" in missing
    assert "grid_reward" in partial.figures


@pytest.mark.slow  # (a report process of about 8 s)
def test_a_folder_that_is_not_a_sweep_is_one_clear_line(tmp_path):
    (tmp_path / "notes.txt").write_text("not a run")
    result = subprocess.run([sys.executable, "-m", "unipolicy_rl.report", str(tmp_path)], cwd=ROOT,
                            capture_output=True, text=True, timeout=120, check=False)
    assert result.returncode == 1
    assert result.stderr.strip().splitlines()[-1] == (
        f"error: {tmp_path}: not a sweep or run directory (no folder under it holds "
        ".hydra/config.yaml, metrics.csv, checkpoint.pt)")
    assert "Traceback" not in result.stderr
    with pytest.raises(ReportError, match="nowhere: no such directory"):
        build_report([tmp_path / "nowhere"])


# -- parts, on made-up numbers ---------------------------------------------------------
def made_up_run(name: str, rows: list[dict], columns: list[str], **config) -> Run:
    base = {"source": {"name": "moe", "kind": "model"}, "seed": 0, "episodes_per_epoch": 10,
            "robot": {"episode_length": 100}, "design": {"_target_": "unipolicy_rl.envs.DesignDistribution"}}
    return Run(path=Path(name), name=name, config={**base, **config},
               rows=[{key: row.get(key, math.nan) for key in columns} for row in rows], columns=columns)


def test_model_based_rows_plot_real_returns_against_real_steps():
    columns = ["epoch", REWARD, DISPLACEMENT, "real_env_steps", "time/elapsed", "imagined/episode_reward",
               "eval/grid_mean_displacement"]
    rows = [{"epoch": 1, REWARD: 5.0, DISPLACEMENT: 0.5, "real_env_steps": 1000, "time/elapsed": 10.0},
            {"epoch": 1, "imagined/episode_reward": 99.0, "time/elapsed": 20.0},  # an imagined batch
            {"epoch": 2, REWARD: 7.0, DISPLACEMENT: 1.5, "real_env_steps": 2000, "time/elapsed": 30.0,
             "eval/grid_mean_displacement": 1.2}]
    run = made_up_run("moe_seed0", rows, columns)
    reward = series(run, REWARD)
    assert list(reward.values) == [5.0, 7.0] and list(reward.steps) == [1000, 2000] and list(reward.seconds) == [10, 30]
    grid = series(run, "eval/grid_mean_displacement")
    assert list(grid.steps) == [2000] and list(grid.values) == [1.2]


def test_real_steps_and_wall_time_are_derived_when_not_logged():
    columns = ["epoch", REWARD, "time/collect", "time/update"]
    rows = [{"epoch": 1, REWARD: 1.0, "time/collect": 2.0, "time/update": 1.0},
            {"epoch": 2, REWARD: 2.0, "time/collect": 2.5, "time/update": 0.5}]
    run = made_up_run("se-trpo_seed0", rows, columns)
    assert list(real_env_steps(run)) == [1000, 2000]  # epoch x 10 episodes x 100 steps
    assert list(elapsed_seconds(run)) == [3.0, 6.0]


def test_seed_band_is_a_t_interval_over_the_seeds_that_reach_each_x():
    band = seed_band([(np.array([0, 1, 2]), np.zeros(3)), (np.array([0, 1]), np.full(2, 2.0))])
    assert list(band.x) == [0, 1, 2] and list(band.seeds) == [2, 2, 1]
    np.testing.assert_allclose(band.mean, [1, 1, 0])
    np.testing.assert_allclose(band.high[:2], 1 + T_975[0] * math.sqrt(2) / math.sqrt(2))
    assert math.isnan(band.low[2])  # one seed: no band


def results(values: dict[tuple[float, float], float]) -> list[DesignResult]:
    return [DesignResult(length, density, 1, reward, 0.0, reward / 100, 0.0, 0.0, 0)
            for (length, density), reward in values.items()]


def test_relative_performance_prefers_policies_trained_at_the_design():
    cells = {(0.15, 0.4): 100.0, (0.2, 0.6): 50.0, (0.15, 0.6): -5.0}
    fixed = {"_target_": "unipolicy_rl.envs.DesignDistribution.fixed", "length": 0.15, "density": 0.4}
    trained_there = made_up_run("best", [], ["epoch"], design=fixed)
    trained_there.designs = results({(0.15, 0.4): 80.0})
    source = made_up_run("se", [], ["epoch"])
    source.designs = results(cells)
    best = best_achievable([trained_there, source])
    assert best.reward == {(0.15, 0.4): 80.0, (0.2, 0.6): 50.0, (0.15, 0.6): -5.0}
    assert best.mixed and "1 of 3 designs" in best.kind
    relative = relative_performance(seed_mean([source.designs], "mean_episode_reward"), best)
    assert relative.values[0, 0] == pytest.approx(125.0)  # better than the DE policy trained there
    assert relative.values[1, 1] == pytest.approx(100.0)
    assert math.isnan(relative.values[1, 0])  # a percentage of a negative best says nothing


def test_groups_are_named_by_what_sets_them_apart():
    runs = [made_up_run(f"se_{kl}_{seed}", [], ["epoch"], seed=seed, source={"name": "se"}, algo={"max_kl": kl})
            for kl in (0.01, 0.02) for seed in (0, 1)]
    runs.append(made_up_run("de_0", [], ["epoch"], source={"name": "de"}, algo={"max_kl": 0.01}))
    groups = group_runs(runs)
    assert {label: len(members) for label, members in groups.items()} == {
        "de": 1, "se algo.max_kl=0.01": 2, "se algo.max_kl=0.02": 2}


def test_a_run_that_never_walked_counts_as_longer_than_any_that_did():
    assert median_to_walk([120_000.0, 260_000.0], runs=3) == 260_000.0  # not 190,000: the median of the lucky two
    assert median_to_walk([16_000.0, 20_000.0, 20_000.0], runs=3) == 20_000.0
    assert math.isinf(median_to_walk([5.0], runs=3)) and math.isinf(median_to_walk([], runs=0))
    with pytest.raises(ValueError, match="runs must be an integer >= the 2 runs that walked, got 1"):
        median_to_walk([1.0, 2.0], runs=1)
