"""MetricsCSV: appends, widens its header when a row brings new columns, continues a resumed
run's file, and writes what the report reads."""

from __future__ import annotations

import csv
import math
import os

import pytest

from unipolicy_rl.report.metrics import series
from unipolicy_rl.report.runs import load_run
from unipolicy_rl.training import MetricsCSV
from unipolicy_rl.training.metrics_file import (
    EPOCH,
    FILE_NAME,
    GRID_MEAN,
    IMAGINED,
    IMAGINED_REWARD_PER_STEP,
    REAL_STEPS,
    REWARD,
)


def read(path) -> tuple[list[str], list[dict[str, str]]]:
    with path.open(newline="") as file:
        reader = csv.DictReader(file)
        return list(reader.fieldnames or []), list(reader)


def test_appends_rows(tmp_path):
    metrics = MetricsCSV(tmp_path / FILE_NAME)
    metrics.append({EPOCH: 1, REWARD: 1.5})
    metrics.append({EPOCH: 2, REWARD: 2.5})
    columns, rows = read(tmp_path / FILE_NAME)
    assert columns == [EPOCH, REWARD]
    assert rows == [{EPOCH: "1", REWARD: "1.5"}, {EPOCH: "2", REWARD: "2.5"}]


def test_widens_the_header_keeping_earlier_rows(tmp_path):
    metrics = MetricsCSV(tmp_path / FILE_NAME)
    metrics.append({EPOCH: 1, IMAGINED: 0.0, REWARD: 1.5})
    metrics.append({EPOCH: 1, IMAGINED: 1.0, IMAGINED_REWARD_PER_STEP: 0.25})  # a column the file lacks
    metrics.append({EPOCH: 2, IMAGINED: 0.0, REWARD: 2.5})  # lacks one the file has
    columns, rows = read(tmp_path / FILE_NAME)
    assert columns == [EPOCH, IMAGINED, REWARD, IMAGINED_REWARD_PER_STEP]
    assert rows == [
        {EPOCH: "1", IMAGINED: "0.0", REWARD: "1.5", IMAGINED_REWARD_PER_STEP: ""},
        {EPOCH: "1", IMAGINED: "1.0", REWARD: "", IMAGINED_REWARD_PER_STEP: "0.25"},
        {EPOCH: "2", IMAGINED: "0.0", REWARD: "2.5", IMAGINED_REWARD_PER_STEP: ""},
    ]
    assert sorted(os.listdir(tmp_path)) == [FILE_NAME]  # no temporary file left behind


def test_a_failed_rewrite_leaves_the_file_whole(tmp_path, monkeypatch):
    path = tmp_path / FILE_NAME
    metrics = MetricsCSV(path)
    metrics.append({EPOCH: 1, REWARD: 1.5})
    before = path.read_text()

    def crash(*args, **kwargs):
        raise OSError("disk full")

    monkeypatch.setattr(os, "replace", crash)
    with pytest.raises(OSError, match="disk full"):
        metrics.append({EPOCH: 2, REWARD: 2.5, GRID_MEAN: 3.0})
    assert path.read_text() == before
    assert sorted(os.listdir(tmp_path)) == [FILE_NAME]


def test_a_resumed_run_continues_the_file(tmp_path):
    path = tmp_path / FILE_NAME
    MetricsCSV(path).append({EPOCH: 1, REWARD: 1.5, REAL_STEPS: 1000})
    resumed = MetricsCSV(path)
    assert resumed.columns == [EPOCH, REWARD, REAL_STEPS]
    resumed.append({EPOCH: 2, REWARD: 2.5, REAL_STEPS: 2000})
    resumed.append({EPOCH: 3, REWARD: 3.5, REAL_STEPS: 3000, GRID_MEAN: 4.0})
    columns, rows = read(path)
    assert columns == [EPOCH, REWARD, REAL_STEPS, GRID_MEAN]
    assert [row[EPOCH] for row in rows] == ["1", "2", "3"]
    assert [row[GRID_MEAN] for row in rows] == ["", "", "4.0"]


def test_the_report_reads_what_it_wrote(tmp_path):
    metrics = MetricsCSV(tmp_path / FILE_NAME)
    metrics.append({EPOCH: 1, IMAGINED: 0.0, REAL_STEPS: 1000, REWARD: 1.5})
    metrics.append({EPOCH: 1, IMAGINED: 1.0, IMAGINED_REWARD_PER_STEP: 0.25})
    metrics.append({EPOCH: 2, IMAGINED: 0.0, REAL_STEPS: 2000, REWARD: 2.5, GRID_MEAN: 3.0})
    run = load_run(tmp_path, "run")
    assert not [problem for problem in run.problems if FILE_NAME in problem]
    assert run.columns == [EPOCH, IMAGINED, REAL_STEPS, REWARD, IMAGINED_REWARD_PER_STEP, GRID_MEAN]
    assert [row[EPOCH] for row in run.rows] == [1.0, 1.0, 2.0]
    assert math.isnan(run.rows[1][REWARD]) and run.rows[1][IMAGINED_REWARD_PER_STEP] == 0.25
    reward = series(run, REWARD)  # real rows only, on the real-step axis carried over imagined rows
    assert reward.steps.tolist() == [1000.0, 2000.0]
    assert reward.values.tolist() == [1.5, 2.5]
    assert series(run, GRID_MEAN).values.tolist() == [3.0]
