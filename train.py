"""Train a universal walking policy with TRPO.

    python train.py                         # SE-TRPO, thesis protocol (600 epochs x 10 episodes)
    python train.py source=de epochs=100    # any override
    python train.py -m source=de,se seed=0,1,2
    python train.py resume=outputs/se/seed0/<run>/checkpoint.pt

Flat loop, top to bottom, over the collector's labelled batches: a real epoch of whole
episodes (SE/DE: one TRPO update on it), or, for a model-based source, a real epoch followed
by imagined batches (one TRPO update each); log; checkpoint after every real epoch. Ends with
a saved policy, a design-grid evaluation and a summary.
"""

from __future__ import annotations

import contextlib
import csv
import signal
import time
from pathlib import Path

import hydra
import torch
import tqdm
from hydra.core.hydra_config import HydraConfig
from hydra.utils import instantiate
from omegaconf import DictConfig, OmegaConf

from unipolicy_rl.checkpoint import (
    check_resumable,
    collector_state,
    load_checkpoint,
    policy_only,
    restore_training_state,
    save_checkpoint,
    settings_for_resume,
    training_state,
)
from unipolicy_rl.collectors import is_imagined
from unipolicy_rl.envs import DesignDistribution
from unipolicy_rl.envs.reward import forward_displacement, mean_forward_speed
from unipolicy_rl.evaluation import (
    evaluate_on_designs,
    format_summary,
    grid_score,
    plot_heatmaps,
    summarise,
    write_csv,
)
from unipolicy_rl.evaluation.plots import plot_training_curve
from unipolicy_rl.factories import (
    env_kwargs,
    make_actor_critic,
    make_collecting_policy,
    make_observation_norm,
    make_training_collector,
    make_trpo_updater,
    probe_dimensions,
)
from unipolicy_rl.observation_statistics import ObservationStatistics, refresh_normalizer
from unipolicy_rl.validation import validate_config


def episode_metrics(batch, control_period: float, episode_length: int) -> dict[str, float]:
    """Mean episode reward, forward displacement (m) and speed (m/s) of the real episodes that ended."""
    done = batch["next", "done"].squeeze(-1)
    displacement = forward_displacement(batch["next", "observation"])[done].mean().item()
    return {
        "train/episode_reward": batch["next", "episode_reward"].squeeze(-1)[done].mean().item(),
        "train/reward_per_step": batch["next", "reward"].mean().item(),
        "train/forward_displacement": displacement,
        "train/forward_speed": mean_forward_speed(displacement, episode_length, control_period),
        "train/physics_faults": batch["next", "physics_fault"].sum().item(),
    }


def policy_parameters(policy, observations) -> tuple[torch.Tensor, torch.Tensor]:
    """The policy's Gaussian (loc, scale) on raw observations."""
    with torch.no_grad():
        out = policy(observations.clone())
    return out["loc"], out["scale"]


def gaussian_kl(old: tuple[torch.Tensor, torch.Tensor], new: tuple[torch.Tensor, torch.Tensor]) -> float:
    """Mean KL(old || new) of diagonal Gaussians (summed over action dimensions)."""
    (m1, s1), (m2, s2) = old, new
    kl = torch.log(s2 / s1) + (s1**2 + (m1 - m2) ** 2) / (2 * s2**2) - 0.5
    return kl.sum(-1).mean().item()


class MetricsCSV:
    """``metrics.csv``: one row per training batch, appended (a resumed run continues the file).

    Real and imagined batches log different figures, so a row may bring a column the file
    has not had yet: the file is then rewritten once with the wider header (cells a row
    lacks stay empty).
    """

    def __init__(self, path: Path) -> None:
        self.path = path
        self.columns: list[str] = []
        if path.is_file():
            with path.open(newline="") as file:
                self.columns = next(csv.reader(file), [])

    def append(self, row: dict[str, float]) -> None:
        new = [key for key in row if key not in self.columns]
        if new:
            rows = []
            if self.path.is_file():
                with self.path.open(newline="") as file:
                    rows = list(csv.DictReader(file))
            self.columns += new
            with self.path.open("w", newline="") as file:
                writer = csv.DictWriter(file, fieldnames=self.columns)
                writer.writeheader()
                writer.writerows(rows)
        with self.path.open("a", newline="") as file:
            csv.DictWriter(file, fieldnames=self.columns).writerow(row)


def evaluation_designs(cfg) -> list:
    """The evaluation grid: ``evaluation.grid`` designs per axis over the evaluation ranges."""
    grid = cfg.evaluation
    return DesignDistribution(tuple(grid.length_range), tuple(grid.density_range)).grid(grid.grid)


def grid_metrics(policy, cfg, designs, prefix: str = "eval/") -> dict[str, float]:
    """The deterministic policy on the evaluation grid in the real env: how far the grid walks."""
    results = evaluate_on_designs(policy, env_kwargs(cfg), designs, episodes_per_design=1, seed=cfg.seed)
    summary = summarise(results)
    return {
        f"{prefix}grid_mean_displacement": summary["mean_forward_displacement"],
        f"{prefix}grid_min_displacement": summary["min_forward_displacement"],
        f"{prefix}walking_designs": float(summary["walking_designs"]),
        f"{prefix}grid_mean_reward": summary["mean_episode_reward"],
    }


def evaluate_final(cfg, checkpoint_path: Path, run_dir: Path, metrics_csv: Path | None) -> dict:
    from unipolicy_rl.checkpoint import load_policy

    loaded = load_policy(checkpoint_path)
    results = evaluate_on_designs(loaded.policy, dict(loaded.env_kwargs), evaluation_designs(cfg),
                                  episodes_per_design=cfg.evaluation.episodes, seed=cfg.seed, progress=True)
    out = run_dir / "evaluation"
    write_csv(results, out / "designs.csv")
    plot_heatmaps(results, out, title=f"{cfg.source.name}-TRPO seed {cfg.seed}")
    if metrics_csv is not None and metrics_csv.is_file():
        plot_training_curve(metrics_csv, out / "training_curve.png")
    return summarise(results)


@contextlib.contextmanager
def shutting_down(collector):
    try:
        yield collector
    finally:
        collector.shutdown()


class StopAtEpochEnd:
    """Ctrl-C or SIGTERM (``kill``, a scheduler's pre-emption) asks the loop to stop after the
    epoch in progress, so the checkpoint it then writes holds whole epochs and resumes exactly.
    A second signal stops at once (keeping the last periodic checkpoint)."""

    SIGNALS = (signal.SIGINT, signal.SIGTERM)

    def __init__(self) -> None:
        self.requested = False
        self._previous = {}

    def __enter__(self) -> StopAtEpochEnd:
        self._previous = {number: signal.signal(number, self._request) for number in self.SIGNALS}
        return self

    def __exit__(self, *exc_info) -> None:
        for number, handler in self._previous.items():
            signal.signal(number, handler)

    def _request(self, signum, frame) -> None:
        if self.requested:
            raise KeyboardInterrupt
        self.requested = True
        print(f"\n{signal.Signals(signum).name}: stopping after this epoch (again to stop now)", flush=True)


@hydra.main(version_base="1.3", config_path="conf", config_name="config")
def main(cfg: DictConfig) -> dict:
    state = load_checkpoint(cfg.resume) if cfg.resume else None
    if state is not None:
        check_resumable(state, cfg.resume)
        overridden = [item.split("=", 1)[0].lstrip("+~") for item in HydraConfig.get().overrides.task]
        cfg = settings_for_resume(cfg, state, overridden, cfg.resume)
    validate_config(cfg)  # every setting, before any robot is built or any time is spent
    torch.set_num_threads(1)  # PyBullet robots and small networks: threads only contend on 2 cores
    torch.manual_seed(cfg.seed)  # network initialisation
    run_dir = Path(HydraConfig.get().runtime.output_dir)

    observation_dim, action_dim = probe_dimensions(cfg)
    actor, critic = make_actor_critic(cfg, observation_dim, action_dim)
    normalizer = make_observation_norm(observation_dim)
    statistics = ObservationStatistics(observation_dim)
    updater = make_trpo_updater(cfg, actor, critic)
    if state is not None:
        restore_training_state(state, actor=actor, critic=critic, statistics=statistics, updater=updater)
    statistics.copy_to(normalizer)
    policy = make_collecting_policy(normalizer, actor)
    collector = make_training_collector(cfg, policy, action_dim)
    # From here on, a failure anywhere still shuts the collector's worker processes down
    # (else the interpreter waits for them forever on exit).
    with shutting_down(collector):
        if state is not None:
            collector.load_state_dict(collector_state(state))
            print(f"resumed from {cfg.resume} at epoch {state['epoch']}")
        elapsed_before = state.get("elapsed", 0.0) if state is not None else 0.0

        logger = instantiate(cfg.logger)
        checkpoint_path = run_dir / "checkpoint.pt"
        # The policy of the best periodic evaluation so far (grid_score), kept apart from the
        # run's last state: a run that walks and then falls back still hands over its best policy.
        best_path = run_dir / "best.pt"
        best = state.get("best_evaluation") if state is not None else None
        metrics_csv = MetricsCSV(run_dir / "metrics.csv")
        designs = evaluation_designs(cfg)
        episode_length = cfg.robot.episode_length
        control_period = cfg.robot.physics.time_step * cfg.robot.physics.substeps
        config = OmegaConf.to_container(cfg, resolve=True)
        started = time.perf_counter()

        def current_state(with_collector: bool = True) -> dict:
            return training_state(epoch=collector.epoch, config=config, observation_dim=observation_dim,
                                  action_dim=action_dim, actor=actor, critic=critic, statistics=statistics,
                                  updater=updater, collector=collector if with_collector else None,
                                  elapsed=elapsed_before + time.perf_counter() - started)

        def checkpoint() -> Path:
            return save_checkpoint(checkpoint_path, {**current_state(), "best_evaluation": best})

        iteration = 0
        progress = tqdm.tqdm(total=cfg.epochs, initial=collector.epoch, disable=not cfg.progress_bar,
                             desc=f"{cfg.source.name}-TRPO")
        postfix: dict[str, str] = {}
        with StopAtEpochEnd() as stop:
            tick = time.perf_counter()
            for batch in collector:
                # ---- Data: real episodes (which also refresh the observation statistics) or imagined ones
                collected = time.perf_counter()
                imagined = is_imagined(batch)
                metrics = {"imagined": float(imagined)}
                if not imagined:
                    metrics.update(episode_metrics(batch, control_period, episode_length))
                # ---- Policy training
                if imagined or collector.trains_policy_on_real:
                    normalizer(batch["next"])  # the critic's input at the next states, as the policy saw them
                    metrics.update(updater.update(batch))
                    if updater.consecutive_skips >= cfg.algo.max_consecutive_skips:
                        raise RuntimeError(
                            f"stopping: {updater.consecutive_skips} updates in a row were skipped "
                            f"({'; '.join(updater.skip_reasons)}); the last checkpoint, if any, is {checkpoint_path}"
                        )
                if not imagined:
                    # The next epoch's policy normalises with statistics that include this epoch;
                    # the trust region does not bound what the refresh does to the policy: log it.
                    observations = batch.select("observation").reshape(-1)
                    before = policy_parameters(policy, observations)
                    statistics.update(batch["observation"])
                    refresh_normalizer(statistics, normalizer, (actor, critic), cfg.algo.normalizer_refresh)
                    metrics["train/refresh_kl"] = gaussian_kl(before, policy_parameters(policy, observations))
                collector.update_policy_weights_()
                metrics.update(collector.metrics())
                metrics["time/collect"] = collected - tick
                metrics["time/update"] = time.perf_counter() - collected
                epoch = collector.epoch
                if not imagined and cfg.evaluation.every and epoch % cfg.evaluation.every == 0:
                    metrics.update(grid_metrics(policy, cfg, designs))
                    evaluation = {"epoch": epoch, "grid_mean": metrics["eval/grid_mean_displacement"],
                                  "grid_min": metrics["eval/grid_min_displacement"]}
                    if best is None or (grid_score(evaluation["grid_mean"], evaluation["grid_min"])
                                        > grid_score(best["grid_mean"], best["grid_min"])):
                        best = evaluation
                        save_checkpoint(best_path, {**policy_only(current_state(with_collector=False)),
                                                    "best_evaluation": best})
                metrics["time/elapsed"] = elapsed_before + time.perf_counter() - started
                iteration += 1
                for name, value in metrics.items():
                    logger.log_scalar(name, value, step=iteration)
                metrics_csv.append({"epoch": epoch, **metrics})
                postfix.update(_progress_figures(metrics))
                progress.set_postfix(postfix, refresh=False)
                tick = time.perf_counter()
                if imagined:
                    continue
                # ---- Checkpoint (after every real epoch, where a run can resume exactly)
                progress.update(1)
                if epoch % cfg.checkpoint_every == 0 or stop.requested:
                    checkpoint()
                if stop.requested:
                    progress.close()
                    print(f"stopped: saved epoch {epoch} to {checkpoint_path}; continue with resume={checkpoint_path}")
                    return {"epoch": epoch, "checkpoint": str(checkpoint_path)}
    progress.close()
    path = checkpoint()

    summary = evaluate_final(cfg, path, run_dir, metrics_csv.path)
    print(f"saved policy: {path}")
    print(f"design grid {cfg.evaluation.grid}x{cfg.evaluation.grid}:")
    print(format_summary(summary))
    if best is not None:
        print(f"best periodic evaluation: epoch {best['epoch']}, grid mean {best['grid_mean']:.2f} m, worst design "
              f"{best['grid_min']:.2f} m; its policy: {best_path}")
    return {"epoch": collector.epoch, "checkpoint": str(path), "best": best, **summary}


def _progress_figures(metrics: dict[str, float]) -> dict[str, str]:
    """What the progress bar shows: real steps, real and imagined reward, model fit, grid walk."""
    shown = {"real_env_steps": ("steps", "{:.0f}"), "train/episode_reward": ("reward", "{:.1f}"),
             "train/forward_displacement": ("metres", "{:.2f}"), "imagined/reward_per_step": ("imag_r", "{:.2f}"),
             "model/validation_mse": ("model_mse", "{:.3f}"), "eval/grid_min_displacement": ("grid_min", "{:.2f}"),
             "train/kl": ("kl", "{:.4f}")}
    return {label: fmt.format(metrics[key]) for key, (label, fmt) in shown.items() if key in metrics}


if __name__ == "__main__":
    main()
