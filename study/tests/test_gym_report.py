"""study/gym/report.py: steps to a return level (reached at the first evaluation, held at the third in
a row), censoring of runs cut before a level, returns at fixed budgets; and a gym run's record keeps
its returns."""

import math

from study import records
from study.gym import report
from study.records import Evaluation, Record


def run(seed, returns, entry="Pendulum-v1-moe-trpo", every=2000):
    evaluations = [Evaluation(steps=every * (i + 1), seconds=math.nan, grid_mean=math.nan, grid_min=math.nan,
                              mean_return=value) for i, value in enumerate(returns)]
    return Record(name=f"{entry}/seed{seed}", entry=entry, seed=seed, model_free=False, step_schedule=True,
                  finished=True, budget=len(returns), real_env_steps=every * len(returns), evaluations=evaluations)


def test_a_level_is_reached_at_the_first_evaluation_and_held_at_the_third_in_a_row():
    record = run(0, [-900, -190, -300, -150, -120, -180, -400])
    assert report.steps_to(record, -200, 1) == (4000, True)
    assert report.steps_to(record, -200, 3) == (12000, True)  # -150, -120, -180: the third confirms it
    assert report.steps_to(record, -100, 1) == (14000, False)  # never: censored at its last evaluation


def test_the_return_at_a_budget_is_the_last_evaluation_at_or_before_it_and_unknown_past_the_run():
    record = run(0, [-900, -500, -300])
    assert report.return_at(record, 4000) == -500
    assert report.return_at(record, 5000) == -500
    assert math.isnan(report.return_at(record, 8000))


def test_the_table_reads_medians_and_says_cut_where_fewer_than_half_reached():
    runs = [run(0, [-900, -150, -150, -150]), run(1, [-900, -900, -150, -150, -150]), run(2, [-900, -900])]
    table = report.table(runs, "Pendulum-v1")
    row = next(line for line in table.splitlines() if line.startswith("| moe-trpo"))
    cells = [cell.strip() for cell in row.strip("|").split("|")]
    assert cells[1] == "0,1,2"
    assert cells[2].startswith("6,000 [") and cells[2].endswith("(2/3)")  # reached at 4,000 and 6,000; one cut
    assert cells[3].startswith("10,000 [")  # held at 8,000 and 10,000; the cut run counts as beyond both
    only_one = report.table([run(0, [-150, -150, -150]), run(1, [-900]), run(2, [-900])], "Pendulum-v1")
    assert "not by 2,000 (cut; 1/3)" in only_one


def test_a_gym_run_s_record_keeps_its_returns(tmp_path):
    record = run(3, [-900.5, -150.25])
    folder = records.write(record, tmp_path / "Pendulum-v1-moe-trpo" / "seed3")
    again = records.read(folder, "Pendulum-v1-moe-trpo/seed3")
    assert [e.mean_return for e in again.evaluations] == [-900.5, -150.25]
    assert [e.steps for e in again.evaluations] == [2000, 4000]


def test_the_curve_figure_draws_each_entry_where_half_its_seeds_got(tmp_path):
    runs = [run(0, [-900, -150, -150]), run(1, [-900, -300]), run(0, [-1200] * 5, entry="Pendulum-v1-trpo")]
    path = report.curves(runs, "Pendulum-v1", tmp_path / "Pendulum-v1.png")
    assert path.is_file() and path.stat().st_size > 10_000
