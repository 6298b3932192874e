"""What a training run reports besides its learner's figures: real episodes' walking, the
periodic design-grid evaluation (and the best one so far), the final evaluation, and where the
rows go (logger, metrics.csv, progress bar). None of it is the algorithm; train.py calls it.
"""

from __future__ import annotations

import contextlib
import math
import time
from dataclasses import dataclass
from pathlib import Path

import tqdm
from tensordict import TensorDictBase

from unipolicy_rl.checkpoint import load_policy
from unipolicy_rl.envs.gym_task import GymTask, evaluate_returns, gym_episode_metrics
from unipolicy_rl.envs.reward import forward_displacement, mean_forward_speed
from unipolicy_rl.envs.tokens import walking_observation
from unipolicy_rl.evaluation import (
    evaluate_on_designs,
    evaluate_on_morphologies,
    grid_score,
    plot_heatmaps,
    summarise,
    summarise_morphologies,
    write_csv,
    write_morphology_csvs,
)
from unipolicy_rl.evaluation.morphologies import MORPHOLOGY_COLUMNS, append_csv, morphology_rows
from unipolicy_rl.evaluation.plots import plot_training_curve
from unipolicy_rl.learners.base import StalledLearning
from unipolicy_rl.training import metrics_file as columns
from unipolicy_rl.training.metrics_file import MetricsCSV


@dataclass(frozen=True)
class MorphologyGrid:
    """``robot=grammar``'s evaluation: every morphology of ``env_kwargs`` (those of
    ``evaluation.morphologies``: the training side by default; ``held_out`` or ``all`` for
    zero-shot transfer) over ``designs``, deterministic policy, one episode per cell.
    :meth:`__call__` returns the summary over all cells
    (:func:`~unipolicy_rl.evaluation.summarise_morphologies`) and the per-morphology results."""

    env_kwargs: dict
    designs: tuple
    seed: int

    @property
    def cells(self) -> int:
        return len(self.env_kwargs["morphologies"]) * len(self.designs)

    def __call__(self, policy, progress: bool = False):
        results = evaluate_on_morphologies(policy, self.env_kwargs, list(self.designs), seed=self.seed,
                                           progress=progress)
        return summarise_morphologies(results), results


@dataclass(frozen=True)
class EvaluationPlan:
    """What a run's reports and evaluations run on, and when: built once from the config by
    :func:`unipolicy_rl.settings.evaluation_plan` (this module reads no config).

    Every run has the seed, the real env steps of one epoch, the schedule in real env steps
    (every ``schedule[0]`` up to ``schedule[1]``, then every ``schedule[2]``) and the longest
    episode. The walker adds its design grid, the episodes per design of the final evaluation and
    its control period; ``robot=vertebrate`` the env's keyword arguments, ``robot=grammar`` the
    morphology grids of the periodic and the final evaluation; ``env=gym`` the task instead.
    """

    seed: int
    epoch_steps: int
    schedule: tuple[int, int, int]
    episode_length: int
    designs: tuple = ()
    final_episodes: int = 1
    control_period: float = math.nan
    env_kwargs: dict | None = None
    morphologies: MorphologyGrid | None = None
    final_morphologies: MorphologyGrid | None = None
    gym: GymTask | None = None


def episode_metrics(batch: TensorDictBase, plan: EvaluationPlan) -> dict[str, float]:
    """Mean episode reward, forward displacement (m) and speed (m/s) of the real episodes that ended
    (for ``env=gym``: their mean return, :func:`~unipolicy_rl.envs.gym_task.gym_episode_metrics`)."""
    if plan.gym is not None:
        return gym_episode_metrics(batch, plan.episode_length)
    done = batch["next", "done"].squeeze(-1)
    displacement = forward_displacement(walking_observation(batch["next"]))[done].mean().item()
    return {
        columns.REWARD: batch["next", "episode_reward"].squeeze(-1)[done].mean().item(),
        columns.REWARD_PER_STEP: batch["next", "reward"].mean().item(),
        columns.DISPLACEMENT: displacement,
        columns.SPEED: mean_forward_speed(displacement, plan.episode_length, plan.control_period),
        columns.PHYSICS_FAULTS: batch["next", "physics_fault"].sum().item(),
    }


# robot=grammar: the periodic evaluation's per-morphology rows, in the run's evaluation folder.
PERIODIC_MORPHOLOGIES = Path("evaluation") / "periodic_morphologies.csv"
# The final evaluation, in the run's folder: one row per design (and morphology) of the grid, or
# for env=gym one per episode's return. Either file marks a run trained to its budget.
FINAL_DESIGNS = Path("evaluation") / "designs.csv"
FINAL_RETURNS = Path("evaluation") / "returns.csv"
FINAL_EVALUATIONS = (FINAL_DESIGNS, FINAL_RETURNS)


def evaluation_points(real_env_steps: int, every_steps: int, dense_until: int, then_every_steps: int) -> int:
    """How many points of the evaluation schedule lie at or below ``real_env_steps``: every
    ``every_steps`` real env steps up to ``dense_until`` (``every_steps``, ``2 * every_steps``, ...),
    then every ``then_every_steps`` after it (``dense_until + then_every_steps``, ...); none when
    ``every_steps`` is 0."""
    if every_steps <= 0 or real_env_steps <= 0:
        return 0
    dense = min(real_env_steps, dense_until) // every_steps
    return dense + max(real_env_steps - dense_until, 0) // then_every_steps


def _epochs_hit(first: int, spacing: int, count: int, epoch_steps: int) -> tuple[int, int, int]:
    """Of the ``count`` points ``first, first + spacing, ...`` (count >= 1), the (number, first,
    last) of the epochs ``ceil(point / epoch_steps)`` that cross them: each point falls into its
    own epoch when ``spacing >= epoch_steps``; otherwise no epoch between the first and last is
    skipped."""
    low, high = -(-first // epoch_steps), -(-(first + (count - 1) * spacing) // epoch_steps)
    return (count if spacing >= epoch_steps else high - low + 1), low, high


def evaluations_done(real_env_steps: int, epoch_steps: int, every_steps: int, dense_until: int,
                     then_every_steps: int) -> int:
    """How many periodic evaluations a run of ``epoch_steps``-step epochs has run by
    ``real_env_steps`` (one after each epoch that crossed at least one schedule point), derived
    from the step counts alone so that a resumed run needs no state for it. Exact unless the run
    was resumed with another epoch size (then it counts as if every epoch had this one's)."""
    dense = evaluation_points(min(real_env_steps, dense_until), every_steps, dense_until, then_every_steps)
    sparse = evaluation_points(real_env_steps, every_steps, dense_until, then_every_steps) - dense
    done, dense_last = 0, None
    if dense:
        done, _, dense_last = _epochs_hit(every_steps, every_steps, dense, epoch_steps)
    if sparse:
        hit, sparse_first, _ = _epochs_hit(dense_until + then_every_steps, then_every_steps, sparse, epoch_steps)
        # One epoch may have crossed both the last dense point and the first sparse one.
        done += hit - (sparse_first == dense_last)
    return done


class PeriodicEvaluation:
    """The deterministic policy on the design grid in the real env, one episode per design, on a
    schedule in real env steps (the same for every source and algorithm): every
    ``evaluation.every_steps`` up to ``evaluation.dense_until``, then every
    ``evaluation.then_every_steps`` (:func:`evaluation_points`); and the best such evaluation so
    far (:func:`grid_score`): a run that walks and then falls back still hands over its best policy.

    After each real epoch it evaluates once if the epoch crossed one or more schedule points,
    told by the real env steps before and after the epoch, not by anything the process
    remembers: a resumed run evaluates at the same points as an uninterrupted one. The rows it
    adds carry the run's ``real_env_steps`` (where it evaluated) and the evaluation's own cost,
    cumulative over the run (``eval/episodes``, ``eval/env_steps``), and its wall seconds
    (``eval/seconds``, this evaluation's alone): evaluation episodes are never training steps,
    nothing trains on them, and the league's wall times leave them out.

    For ``robot=grammar`` the grid is every morphology of ``evaluation.morphologies`` over an
    ``evaluation.morphology_grid`` design grid (:class:`MorphologyGrid`); the ``eval/`` columns are
    then over every (morphology, design) cell, two more say how many morphologies walk and the
    worst one's grid mean, and each morphology's row goes to ``evaluation/periodic_morphologies.csv``
    in ``run_dir``.

    Args:
        plan: what the run evaluates on, and when.
        best: the best evaluation of the run so far (a resumed run's), or None.
        run_dir: the run folder (where a grammar run's per-morphology rows go), or None for none.
    """

    def __init__(self, plan: EvaluationPlan, best: dict | None = None, run_dir: Path | None = None) -> None:
        self.plan = plan
        self.morphology_grid = plan.morphologies
        self.designs = plan.designs if self.morphology_grid is None else self.morphology_grid.designs
        self.run_dir = run_dir
        self.best = best
        self.improved = False  # whether the last evaluation became the best

    @property
    def schedule(self) -> tuple[int, int, int]:
        """(every_steps, dense_until, then_every_steps)."""
        return self.plan.schedule

    def due(self, real_env_steps: int, epoch_steps: int) -> bool:
        """Whether the epoch that brought the run to ``real_env_steps`` (``epoch_steps`` of them
        its own) crossed a point of the schedule."""
        return (evaluation_points(real_env_steps, *self.schedule)
                > evaluation_points(real_env_steps - epoch_steps, *self.schedule))

    def __call__(self, epoch: int, real_env_steps: int, policy) -> dict[str, float]:
        """Evaluates if the epoch that just brought the run to ``real_env_steps`` crossed a
        schedule point (else returns no metrics)."""
        self.improved = False
        epoch_steps = self.plan.epoch_steps  # this epoch's real steps
        if not self.due(real_env_steps, epoch_steps):
            return {}
        extra = {}
        started = time.perf_counter()
        if self.morphology_grid is None:
            summary = summarise(evaluate_on_designs(policy, self.plan.env_kwargs, list(self.designs),
                                                    episodes_per_design=1, seed=self.plan.seed))
            cells = len(self.designs)
        else:
            summary, results = self.morphology_grid(policy)
            cells = self.morphology_grid.cells
            extra = {columns.WALKING_MORPHOLOGIES: float(summary["walking_morphologies"]),
                     columns.WORST_MORPHOLOGY_MEAN: summary["worst_morphology_mean_displacement"]}
            if self.run_dir is not None:
                rows = [{"epoch": epoch, "real_env_steps": real_env_steps, **row} for row in morphology_rows(results)]
                append_csv(self.run_dir / PERIODIC_MORPHOLOGIES, rows, ("epoch", "real_env_steps", *MORPHOLOGY_COLUMNS))
        episodes = evaluations_done(real_env_steps, epoch_steps, *self.schedule) * cells
        metrics = {
            columns.GRID_MEAN: summary["mean_forward_displacement"],
            columns.GRID_MIN: summary["min_forward_displacement"],
            columns.GRID_WALKING: float(summary["walking_designs"]),
            columns.GRID_REWARD: summary["mean_episode_reward"],
            columns.EVAL_EPISODES: float(episodes),
            columns.EVAL_ENV_STEPS: float(episodes * self.plan.episode_length),
            columns.EVAL_SECONDS: time.perf_counter() - started,
            **extra,
        }
        evaluation = {"epoch": epoch, "grid_mean": metrics[columns.GRID_MEAN], "grid_min": metrics[columns.GRID_MIN]}
        if self.best is None or (grid_score(evaluation["grid_mean"], evaluation["grid_min"])
                                 > grid_score(self.best["grid_mean"], self.best["grid_min"])):
            self.best, self.improved = evaluation, True
        return metrics


class ReturnEvaluation(PeriodicEvaluation):
    """``env=gym``'s periodic evaluation: the deterministic policy's mean return over
    ``env.evaluation_episodes`` real episodes, on the same schedule in real env steps as the
    walker's grid (:class:`PeriodicEvaluation`), the best one by mean return. Its rows:
    ``eval/mean_return``, ``eval/min_return``, the episodes so far and its seconds."""

    def __init__(self, plan: EvaluationPlan, best: dict | None = None, run_dir: Path | None = None) -> None:
        if plan.gym is None:
            raise ValueError("a ReturnEvaluation evaluates a gym task: the plan has none (env=gym)")
        self.plan, self.best, self.run_dir, self.improved = plan, best, run_dir, False
        self.task = plan.gym

    def __call__(self, epoch: int, real_env_steps: int, policy) -> dict[str, float]:
        self.improved = False
        epoch_steps = self.plan.epoch_steps
        if not self.due(real_env_steps, epoch_steps):
            return {}
        started = time.perf_counter()
        returns = evaluate_returns(policy, self.task.id, self.task.evaluation_episodes, self.plan.seed,
                                   self.task.episode_length)
        mean = sum(returns) / len(returns)
        episodes = evaluations_done(real_env_steps, epoch_steps, *self.schedule) * len(returns)
        if self.best is None or mean > self.best["mean_return"]:
            self.best, self.improved = {"epoch": epoch, "mean_return": mean}, True
        return {columns.EVAL_RETURN: mean, columns.EVAL_MIN_RETURN: min(returns),
                columns.EVAL_EPISODES: float(episodes), columns.EVAL_SECONDS: time.perf_counter() - started}


def make_evaluation(plan: EvaluationPlan, best: dict | None = None, run_dir: Path | None = None) -> PeriodicEvaluation:
    """The run's periodic evaluation: the walker's design grid, or a gym task's returns."""
    evaluation = PeriodicEvaluation if plan.gym is None else ReturnEvaluation
    return evaluation(plan, best=best, run_dir=run_dir)


def describe_best(best: dict) -> str:
    """The best periodic evaluation, in words."""
    if "mean_return" in best:
        return f"epoch {best['epoch']}, mean return {best['mean_return']:.1f}"
    return f"epoch {best['epoch']}, grid mean {best['grid_mean']:.2f} m, worst design {best['grid_min']:.2f} m"


def evaluate_final(plan: EvaluationPlan, checkpoint_path: Path, run_dir: Path, title: str) -> dict:
    """The saved policy on the evaluation grid (``evaluation.episodes`` per design): CSV, heatmaps,
    the training curve, and the summary. For ``robot=grammar``: every morphology of
    ``evaluation.morphologies`` on the ``evaluation.grid`` design grid (deterministic, one episode
    per cell), ``morphologies.csv`` (one row per morphology) and ``designs.csv`` (one per cell), and
    the summary over all cells with the per-morphology figures."""
    out = run_dir / "evaluation"
    loaded = load_policy(checkpoint_path)
    if plan.gym is not None:  # the deterministic policy's return in env.evaluation_episodes episodes
        task = plan.gym
        returns = evaluate_returns(loaded.policy, task.id, task.evaluation_episodes, plan.seed, task.episode_length)
        out.mkdir(parents=True, exist_ok=True)
        (run_dir / FINAL_RETURNS).write_text("episode,return\n" + "".join(f"{i},{r}\n" for i, r in enumerate(returns)))
        summary = {"mean_return": sum(returns) / len(returns), "min_return": min(returns),
                   "max_return": max(returns), "episodes": len(returns)}
    elif plan.final_morphologies is not None:
        summary, results = plan.final_morphologies(loaded.policy, progress=True)
        write_morphology_csvs(results, out)
    else:
        results = evaluate_on_designs(loaded.policy, dict(loaded.env_kwargs), list(plan.designs),
                                      episodes_per_design=plan.final_episodes, seed=plan.seed, progress=True)
        write_csv(results, run_dir / FINAL_DESIGNS)
        plot_heatmaps(results, out, title=f"{title} seed {plan.seed}")
        summary = summarise(results)
    metrics_csv = run_dir / columns.FILE_NAME
    if metrics_csv.is_file():
        plot_training_curve(metrics_csv, out / "training_curve.png")
    return summary


# What the progress bar shows: real steps, real and imagined reward, model fit, grid walk.
SHOWN = {columns.REAL_STEPS: ("steps", "{:.0f}"), columns.REWARD: ("reward", "{:.1f}"),
         columns.DISPLACEMENT: ("metres", "{:.2f}"), columns.IMAGINED_REWARD_PER_STEP: ("imag_r", "{:.2f}"),
         columns.MODEL_VALIDATION_MSE: ("model_mse", "{:.3f}"), columns.GRID_MIN: ("grid_min", "{:.2f}"),
         columns.KL: ("kl", "{:.4f}")}


def progress_figures(metrics: dict[str, float]) -> dict[str, str]:
    return {label: fmt.format(metrics[key]) for key, (label, fmt) in SHOWN.items() if key in metrics}


class RunLog:
    """Where a run's rows go: the TorchRL logger, ``metrics.csv`` (one row per imagined update and one
    per real epoch, appended over resumes) and the progress bar (one tick per real epoch).

    Args:
        logger: a TorchRL logger (``cfg.logger``).
        run_dir: the run folder (``metrics.csv`` goes there).
        epochs, initial: the run's last epoch and the epoch it starts from.
        title: the progress bar's label.
        show: draw the progress bar.
    """

    def __init__(self, logger, run_dir: Path, epochs: int, initial: int, title: str, show: bool) -> None:
        self.logger = logger
        self.csv = MetricsCSV(run_dir / columns.FILE_NAME)
        self.csv.drop_epochs_after(initial)  # a resume into its own folder redoes the epochs after its checkpoint
        self.bar = tqdm.tqdm(total=epochs, initial=initial, disable=not show, desc=title)
        self.rows = 0
        self.postfix: dict[str, str] = {}

    def row(self, epoch: int, metrics: dict[str, float]) -> None:
        self.rows += 1
        for name, value in metrics.items():
            self.logger.log_scalar(name, value, step=self.rows)
        self.csv.append({columns.EPOCH: epoch, **metrics})
        self.postfix.update(progress_figures(metrics))
        self.bar.set_postfix(self.postfix, refresh=False)

    def epoch_done(self) -> None:
        self.bar.update(1)

    def close(self) -> None:
        self.bar.close()


@contextlib.contextmanager
def naming_the_checkpoint_on_stall(path: Path):
    """A learner that stopped learning ends the run; its error says which checkpoint the run keeps."""
    try:
        yield
    except StalledLearning as error:
        raise StalledLearning(f"{error}; the last checkpoint, if any, is {path}") from None
