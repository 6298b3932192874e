"""The specialist/universal table (issue 23) computed right on hand-made run folders, through
their compact records (:mod:`study.records`) as the report reads them."""

from __future__ import annotations

import csv
import math
import tempfile
from pathlib import Path

import pytest
from omegaconf import OmegaConf

from study import records
from study.morphology import grammar_runs, table
from study.morphology import report as benchmark
from study.scripts import morphology_windows
from unipolicy_rl.report.runs import load_run

ROOT = Path(__file__).resolve().parents[2]
SIDES = {"a": table.TRAINED, "b": table.TRAINED, "c": table.UNTRAINED, "x": table.HELD_OUT, "y": table.HELD_OUT}


def record_of(path: Path, sides_of=lambda run: SIDES) -> records.Record:
    """The run folder's record, written to disk and read back (the split's sides as ``sides_of`` draws them)."""
    with pytest.MonkeyPatch.context() as patch, tempfile.TemporaryDirectory() as folder:
        patch.setattr(grammar_runs, "split_sides", sides_of)
        record = records.from_run(load_run(path, path.name))
        return records.read(records.write(record, Path(folder)), path.name)


def write_run(root: Path, name: str, policy: str, scores: dict[str, float], specialist: int | None = None,
              training_morphologies: int | None = None) -> Path:
    """A grammar run folder: its config and its final evaluation's morphologies.csv."""
    path = root / name
    (path / ".hydra").mkdir(parents=True)
    (path / "evaluation").mkdir()
    config = {"run_name": "se-trpo", "seed": 0, "source": {"name": "se"}, "policy": {"name": policy},
              "robot": {"kind": "grammar", "specialist": specialist, "training_morphologies": training_morphologies}}
    OmegaConf.save(OmegaConf.create(config), path / ".hydra" / "config.yaml")
    (path / "metrics.csv").write_text("epoch\n1\n")
    with (path / grammar_runs.MORPHOLOGIES_CSV).open("w", newline="") as file:
        writer = csv.DictWriter(file, fieldnames=["morphology", "links", "mean_forward_displacement",
                                                  "min_forward_displacement", "derivation"])
        writer.writeheader()
        for index, (derivation, mean) in enumerate(scores.items()):
            writer.writerow({"morphology": index, "links": 7 + index, "mean_forward_displacement": mean,
                             "min_forward_displacement": mean / 2, "derivation": derivation})
    return path


@pytest.fixture()
def runs(tmp_path):
    paths = [
        write_run(tmp_path, "spec_a0", "token_mlp", {"a": 4.0}, specialist=0),
        write_run(tmp_path, "spec_a1", "token_mlp", {"a": 2.0}, specialist=0),  # two seeds: the median is 3.0
        write_run(tmp_path, "spec_b", "token_mlp", {"b": 2.0}, specialist=1),
        write_run(tmp_path, "spec_x", "token_mlp", {"x": 4.0}, specialist=0),
        write_run(tmp_path, "spec_y", "token_mlp", {"y": -0.5}, specialist=1),  # goes backwards: no ratio
        write_run(tmp_path, "transformer", "token_transformer", {"a": 3.0, "b": 0.5, "c": 9.0, "x": 3.0, "y": 1.0},
                  training_morphologies=2),
        write_run(tmp_path, "mlp", "token_mlp", {"a": 1.5, "b": 2.0, "x": 1.0, "y": 0.0, "z": 5.0},
                  training_morphologies=2),
    ]
    return [record_of(path) for path in paths]


def test_each_morphology_is_compared_with_its_specialists_median_by_derivation(runs):
    rows = {(row.entry, row.derivation): row for row in table.compare(runs)}
    transformer = "token_transformer, 2 morphologies"
    assert rows[transformer, "a"].specialist == 3.0 and rows[transformer, "a"].ratio == 1.0
    assert rows[transformer, "b"].ratio == 0.25 and rows[transformer, "x"].ratio == 0.75
    assert math.isnan(rows[transformer, "y"].ratio)  # its specialist went backwards
    assert rows[transformer, "c"].side == table.UNTRAINED and rows[transformer, "c"].specialist is None
    assert rows["token_mlp, 2 morphologies", "z"].side == table.UNTRAINED  # not in the split at all


def test_the_summary_takes_medians_over_trained_and_held_out_morphologies_and_counts_walkers(runs):
    comparisons = table.compare(runs)
    summary = {row.entry: row for row in table.summarize(comparisons)}
    transformer = summary["token_transformer, 2 morphologies"]
    assert transformer.trained_ratio == pytest.approx(0.625)  # median of 1.0 and 0.25
    assert (transformer.held_out_ratio, transformer.held_out_compared) == (0.75, 1)
    assert (transformer.trained_walking, transformer.trained) == (1, 2)  # b at 0.5 m does not walk
    assert transformer.held_out_mean == 2.0
    mlp = summary["token_mlp, 2 morphologies"]
    assert mlp.trained_ratio == pytest.approx((0.5 + 1.0) / 2) and mlp.trained_walking == 2
    text = table.format_table(comparisons, table.summarize(comparisons))
    assert "| token_transformer, 2 morphologies | 62% (2 compared) | 1/2 | 75% (1 compared) | 2.00 m |" in text


def test_a_model_based_run_is_an_entry_measured_against_the_real_specialists(tmp_path):
    """source=moe cut to one robot is not a reference: it is compared with the real specialist."""
    paths = [write_run(tmp_path, "spec_a", "token_mlp", {"a": 4.0}, specialist=0),
             write_run(tmp_path, "moe_a", "token_mlp", {"a": 3.0}, specialist=0)]
    config = OmegaConf.load(paths[1] / ".hydra" / "config.yaml")
    config.source = {"name": "moe", "kind": "model"}
    OmegaConf.save(config, paths[1] / ".hydra" / "config.yaml")
    runs = [record_of(path) for path in paths]
    assert [table.is_specialist(run) for run in runs] == [True, False]
    assert [score.mean_displacement for score in table.specialist_scores(runs)] == [4.0]
    (row,) = table.compare(runs)
    assert (row.entry, row.universal, row.specialist, row.ratio) == ("token_mlp on moe, 1 morphologies", 3.0, 4.0, 0.75)
    text = table.format_table([row], table.summarize([row]))
    assert "| token_mlp on moe, 1 morphologies | 75% (1 compared) | 1/1 | - (0 compared) | - |" in text


def test_a_run_with_another_learner_is_an_entry_not_a_specialist(tmp_path):
    paths = [write_run(tmp_path, "spec_a", "token_mlp", {"a": 4.0}, specialist=0),
             write_run(tmp_path, "ppo_a", "token_mlp", {"a": 2.0}, specialist=0)]
    config = OmegaConf.load(paths[1] / ".hydra" / "config.yaml")
    config.algo = {"name": "ppo"}
    OmegaConf.save(config, paths[1] / ".hydra" / "config.yaml")
    runs = [record_of(path) for path in paths]
    assert [table.is_specialist(run) for run in runs] == [True, False]
    (row,) = table.compare(runs)
    assert (row.entry, row.specialist, row.ratio) == ("token_mlp with ppo, 1 morphologies", 4.0, 0.5)


def test_a_run_started_from_another_run_s_policy_is_an_entry_not_a_specialist(tmp_path):
    """A warm start (init_policy) on one robot, even the specialist's own network and learner, is
    measured against the specialists that started from nothing, not counted among them."""
    paths = [write_run(tmp_path, "spec_x", "token_mlp", {"x": 2.0}, specialist=0),
             write_run(tmp_path, "warm_x", "token_mlp", {"x": 3.0}, specialist=0)]
    config = OmegaConf.load(paths[1] / ".hydra" / "config.yaml")
    config.init_policy = "runs/distilled/checkpoint.pt"
    OmegaConf.save(config, paths[1] / ".hydra" / "config.yaml")
    runs = [record_of(path) for path in paths]
    assert [table.is_specialist(run) for run in runs] == [True, False]
    (row,) = table.compare(runs)
    assert (row.entry, row.specialist, row.ratio) == ("token_mlp, 1 morphologies, from another run's policy", 2.0, 1.5)


def test_a_run_on_the_structural_layout_is_an_entry_of_its_own(runs, tmp_path):
    path = write_run(tmp_path, "mlp_structural", "token_mlp", {"a": 3.0, "x": 2.0}, training_morphologies=2)
    config = OmegaConf.load(path / ".hydra" / "config.yaml")
    config.robot.token_layout = "structural"
    OmegaConf.save(config, path / ".hydra" / "config.yaml")
    rows = table.compare([*runs, record_of(path)])
    by_entry = {}
    for row in rows:
        by_entry.setdefault(row.entry, []).append(row.derivation)
    assert sorted(by_entry["token_mlp, 2 morphologies, structural layout"]) == ["a", "x"]
    assert sorted(by_entry["token_mlp, 2 morphologies"]) == ["a", "b", "x", "y", "z"]  # the packed run alone


def test_a_run_cut_to_one_robot_trained_on_that_robot_alone(tmp_path):
    from hydra import compose, initialize_config_dir

    from unipolicy_rl.env_factories import grammar_morphologies

    with initialize_config_dir(str(ROOT / "conf"), version_base="1.3"):
        cfg = compose("config", overrides=["source=moe", "robot=grammar", "policy=token_mlp", "robot.specialist=1",
                                           "robot.split.train_size=3", "robot.split.held_out_size=2"])
    cfg.run_name = "se-moe-trpo"
    path = write_run(tmp_path, "moe_train1", "token_mlp", {})
    OmegaConf.save(cfg, path / ".hydra" / "config.yaml")
    split, _ = grammar_morphologies(cfg, "all")
    sides = grammar_runs.split_sides(load_run(path, path.name))
    names = [" ".join(morphology.derivation()) for morphology in (*split.train, *split.held_out)]
    assert [sides[name] for name in names] == [table.UNTRAINED, table.TRAINED, table.UNTRAINED,
                                               table.HELD_OUT, table.HELD_OUT]


def test_an_evaluation_run_again_counts_once_with_its_last_row(tmp_path):
    path = write_run(tmp_path, "spec", "token_mlp", {"a": 1.0}, specialist=0)
    with (path / grammar_runs.MORPHOLOGIES_CSV).open("a", newline="") as file:
        file.write("0,7,2.5,1.0,a\n")
    scores = table.final_scores(record_of(path))
    assert [(score.derivation, score.mean_displacement) for score in scores] == [("a", 2.5)]


def test_the_benchmark_prints_the_table_from_real_split_sides(tmp_path, capsys):
    """Through the split itself: a universal run of the config's split, its derivations read from it."""
    from hydra import compose, initialize_config_dir

    from unipolicy_rl.env_factories import grammar_morphologies

    with initialize_config_dir(str(ROOT / "conf"), version_base="1.3"):
        cfg = compose("config", overrides=["robot=grammar", "policy=token_mlp", "robot.split.train_size=3",
                                           "robot.split.held_out_size=2", "robot.training_morphologies=2"])
    split, _ = grammar_morphologies(cfg, "all")
    names = [" ".join(morphology.derivation()) for morphology in (*split.train, *split.held_out)]
    universal = write_run(tmp_path, "universal", "token_mlp", dict.fromkeys(names, 2.0), training_morphologies=2)
    cfg.run_name = "se-trpo"  # what Hydra's runtime resolves in a run
    OmegaConf.save(cfg, universal / ".hydra" / "config.yaml")
    write_run(tmp_path, "specialist", "token_mlp", {names[3]: 4.0}, specialist=0)
    assert benchmark.main([str(tmp_path), "--out", str(tmp_path / "out")]) == 0
    printed = capsys.readouterr().out
    assert "| token_mlp, 2 morphologies | - (0 compared) | 2/2 | 50% (1 compared) | 2.00 m |" in printed
    assert printed.count("train side, not trained on") == 1  # the third training morphology
    assert (tmp_path / "out" / "morphologies.png").stat().st_size > 0


def test_the_specialists_are_listed_before_any_universal_run_has_finished(tmp_path, capsys):
    """A study whose universal runs have not finished shows its specialists (table and CSV)."""
    write_run(tmp_path, "spec_a", "token_mlp", {"a": 4.0}, specialist=0)
    write_run(tmp_path, "spec_b", "token_mlp", {"b": 0.5}, specialist=1)
    OmegaConf.save(OmegaConf.create({"run_name": "se-trpo", "seed": 3, "source": {"name": "se"},
                                     "policy": {"name": "token_mlp"},
                                     "robot": {"kind": "grammar", "specialist": 0, "morphologies": "held_out"}}),
                   write_run(tmp_path, "spec_x", "token_mlp", {"x": 2.0}, specialist=0) / ".hydra" / "config.yaml")
    write_periodic(tmp_path / "spec_a", [(1000, "a", 0.5)])  # a robot in both evaluations: one row of its record
    runs = [record_of(path) for path in sorted(tmp_path.iterdir())]
    assert [robot.derivation for robot in runs[0].robots] == ["a"]
    scores = table.specialist_scores(runs)
    assert [(s.side, s.index, s.seed, s.derivation, s.mean_displacement) for s in scores] == [
        ("train", 0, 0, "a", 4.0), ("train", 1, 0, "b", 0.5), ("held_out", 0, 3, "x", 2.0)]
    assert "2 of 3 specialists walk" in table.format_specialists(scores)
    assert benchmark.main([str(tmp_path), "--out", str(tmp_path / "out"), "--no-pictures"]) == 0
    printed = capsys.readouterr().out
    assert "| held_out | 0 | 3 | 7 | 2.00 m | 1.00 m | x |" in printed and "the specialists only" in printed
    with (tmp_path / "out" / "specialists.csv").open(newline="") as file:
        assert [row["derivation"] for row in csv.DictReader(file)] == ["a", "b", "x"]


def test_before_any_universal_run_the_figure_shows_each_specialists_median(tmp_path, capsys):
    """Panels from specialists alone: one per morphology, the median over its seeds, training side first."""
    scores = [table.SpecialistScore("held_out", 0, 0, 9, 2.0, 1.0, "x"),
              table.SpecialistScore("train", 1, 0, 12, 1.0, 0.5, "b"),
              table.SpecialistScore("train", 1, 1, 12, 3.0, 1.5, "b"),
              table.SpecialistScore("train", 1, 2, 12, 8.0, 0.0, "b")]
    panels = {panel.derivation: panel for panel in benchmark.figure_panels(scores, [])}
    assert panels["b"].lines == ("train 1, 12 links", "specialist 3.00 m (3 seeds)", "worst design 0.50 m")
    assert panels["x"].lines == ("held_out 0, 9 links", "specialist 2.00 m", "worst design 1.00 m")
    # An entry cut to one robot adds its line to that robot's panel; the other specialists keep theirs,
    # and a morphology only an entry was evaluated on gets a panel of its own.
    # Two runs of one entry on a robot: one line, their median.
    one_robot = [table.Comparison("token_transformer, 1 morphologies", "b", "trained", 12, 2.5, 3.0),
                 table.Comparison("token_transformer, 1 morphologies", "b", "trained", 12, 1.5, 3.0),
                 table.Comparison("token_transformer, 1 morphologies", "y", "held_out", 7, 0.1, None)]
    panels = benchmark.figure_panels(scores, one_robot)
    assert [panel.derivation for panel in panels] == ["x", "b", "y"]
    assert panels[1].lines[-1] == "token_transformer x1: 2.00 m (2 runs)"
    assert panels[0].lines[-1] == "worst design 1.00 m"
    assert panels[2].lines == ("held_out, 7 links", "specialist -", "token_transformer x1: 0.10 m")

    from hydra import compose, initialize_config_dir

    from unipolicy_rl.env_factories import grammar_morphologies

    with initialize_config_dir(str(ROOT / "conf"), version_base="1.3"):
        cfg = compose("config", overrides=["robot=grammar", "robot.split.train_size=3", "robot.split.held_out_size=2"])
    split, _ = grammar_morphologies(cfg, "all")
    write_run(tmp_path, "specialist", "token_mlp", {" ".join(split.train[0].derivation()): 2.5}, specialist=0)
    assert benchmark.main([str(tmp_path), "--out", str(tmp_path / "out")]) == 0
    assert "the specialists only" in capsys.readouterr().out
    assert (tmp_path / "out" / "morphologies.png").stat().st_size > 0


def write_periodic(path: Path, rows: list[tuple[int, str, float]]) -> None:
    """The run's periodic evaluations: (real env steps, derivation, grid mean) per row."""
    with (path / grammar_runs.PERIODIC_CSV).open("w", newline="") as file:
        writer = csv.DictWriter(file, fieldnames=["epoch", "real_env_steps", "morphology",
                                                  "mean_forward_displacement", "derivation"])
        writer.writeheader()
        for steps, derivation, mean in rows:
            writer.writerow({"epoch": steps // 1000, "real_env_steps": steps, "morphology": 0,
                             "mean_forward_displacement": mean, "derivation": derivation})


def test_matched_steps_compare_each_robot_at_equal_real_steps_per_robot(tmp_path):
    """A universal run over 2 robots at 40,000 real steps has given each robot 20,000: it is read
    there against the specialists' first evaluation at or after 20,000 of their own."""
    spec_a = write_run(tmp_path, "spec_a", "token_mlp", {}, specialist=0)
    write_periodic(spec_a, [(10000, "a", 0.1), (20000, "a", 0.5), (40000, "a", 2.0)])
    spec_b = write_run(tmp_path, "spec_b", "token_mlp", {}, specialist=1)
    write_periodic(spec_b, [(20000, "b", 0.3)])
    # The transformer as one robot's specialist is not a reference: an entry of its own.
    other = write_run(tmp_path, "spec_a_transformer", "token_transformer", {}, specialist=0)
    write_periodic(other, [(20000, "a", 9.0)])
    universal = write_run(tmp_path, "universal", "token_transformer", {}, training_morphologies=2)
    write_periodic(universal, [(steps, name, value) for steps, values in ((20000, (0.2, 0.1)), (40000, (1.0, 0.4)),
                                                                          (80000, (1.5, 0.6)))
                               for name, value in zip("ab", values, strict=True)])
    def sides_of(run):  # a run cut to one robot trained on that robot alone (split_sides)
        return {"a": table.TRAINED} if run.name == "spec_a_transformer" else SIDES

    runs = [record_of(path, sides_of) for path in (spec_a, spec_b, other, universal)]
    assert [table.is_specialist(run) for run in runs] == [True, True, False, False]
    rows = table.compare_at_matched_steps(runs, [20000, 40000])
    found = {(row.run, row.derivation, row.steps): (row.universal, row.specialist) for row in rows}
    assert found["universal", "a", 20000] == (1.0, 0.5)
    assert found["universal", "b", 20000] == (0.4, 0.3)
    assert found["universal", "a", 40000] == (1.5, 2.0)
    assert found["universal", "b", 40000] == (0.6, None)  # its specialist stopped at 20,000
    # The transformer cut to robot a (trained: a only) reads its own steps.
    assert found["spec_a_transformer", "a", 20000] == (9.0, 0.5)
    text = table.format_matched_steps(rows)
    # ratios 2.0 and 1.33: median 167%, ahead on both; at 40,000 one robot, behind
    assert "| universal | 20,000 | 1.00 0.40 | 0.50 0.30 | 0.70 m | 0.40 m (2 robots) | 167% | 2 of 2 |" in text
    assert "| universal | 40,000 | 1.50 0.60 | 2.00 - | 1.50 m | 2.00 m (1 robots) | 75% | 0 of 1 |" in text
    with pytest.raises(ValueError, match=r"steps must be positive integers \(real env steps per robot\), got \[0\]"):
        table.compare_at_matched_steps(runs, [0])


def test_the_windows_benchmark_groups_evaluations_by_steps_per_training_robot(tmp_path, capsys):
    """Two training robots and two held out (the run's own split): evaluations at 2,000 and 6,000
    real steps fall in the first and second 2,000-step window per robot; one cut short (a robot
    missing) is left out; the held-out mean and its range come from the robots past the training ones."""
    from hydra import compose, initialize_config_dir

    with initialize_config_dir(str(ROOT / "conf"), version_base="1.3"):
        cfg = compose("config", overrides=["robot=grammar", "policy=token_modular", "robot.split.train_size=3",
                                           "robot.split.held_out_size=2", "robot.training_morphologies=2",
                                           "evaluation.morphologies=all"])
    run = tmp_path / "universal" / "seed0"
    (run / ".hydra").mkdir(parents=True)
    (run / "evaluation").mkdir()
    cfg.run_name = "se-trpo"
    OmegaConf.save(cfg, run / ".hydra" / "config.yaml")
    rows = [(2000, [1.0, 3.0, 0.5, -0.5]), (6000, [2.0, 4.0, 0.2, 0.6]), (8000, [9.0, 9.0, 9.0])]
    with (run / "evaluation" / "periodic_morphologies.csv").open("w", newline="") as file:
        writer = csv.writer(file)
        writer.writerow(["epoch", "real_env_steps", "morphology", "mean_forward_displacement"])
        for steps, values in rows:
            writer.writerows([steps // 1000, steps, robot, value] for robot, value in enumerate(values))
    windows_of = morphology_windows.windows
    trained, windows = windows_of(run, 2000.0)
    assert trained == 2
    assert windows == [pytest.approx((0.0, 1, 2.0, 0.0, 0.0, 0.0)), pytest.approx((2000.0, 1, 3.0, 0.4, 0.4, 0.4))]
    # in the run's real env steps in all: 2,000 and 6,000 fall in the 2,000-4,000 and 6,000-8,000 windows
    _, in_total = windows_of(run, 2000.0, per_robot=False)
    assert [window[0] for window in in_total] == [2000.0, 6000.0]
    with pytest.raises(SystemExit, match="no evaluation/periodic_morphologies.csv"):
        morphology_windows.seed_folder(tmp_path / "missing", 0)


def test_a_distilled_entry_counts_its_own_real_steps_and_its_teachers_beside_them(tmp_path):
    """The issue's budget is the specialists' real steps together: a run taught by specialists
    (algo=distill) spent theirs before its own, so the table shows both."""
    from unipolicy_rl.checkpoint import save_checkpoint

    teachers = []
    for index, epochs in enumerate((300, 200)):
        config = {"episodes_per_epoch": 10, "robot": {"episode_length": 100}}
        state = {"format": 3, "epoch": epochs, "config": config, "policy": {}}
        teachers.append(str(save_checkpoint(tmp_path / f"teacher{index}.pt", state)))
    path = write_run(tmp_path, "distilled", "token_modular", {"a": 3.0, "b": 2.0, "x": 0.5}, training_morphologies=2)
    config = OmegaConf.load(path / ".hydra" / "config.yaml")
    config.algo = {"name": "distill", "teachers": teachers}
    OmegaConf.save(config, path / ".hydra" / "config.yaml")
    (path / "metrics.csv").write_text("epoch,real_env_steps\n1,1000\n2,2000\n")
    assert grammar_runs.teacher_real_steps(load_run(path, path.name)) == 300 * 1000 + 200 * 1000
    run = record_of(path)
    comparisons = table.compare([run])
    (summary,) = table.summarize(comparisons)
    assert (summary.entry, summary.real_steps, summary.teacher_steps) == (
        "token_modular with distill, 2 morphologies", 2000, 500_000)
    assert "| 2,000 + 500,000 (teachers) |" in table.format_table(comparisons, [summary])
    # a teacher that cannot be read leaves the teachers' steps unknown, not zero
    Path(teachers[1]).unlink()
    assert math.isnan(grammar_runs.teacher_real_steps(load_run(path, path.name)))
