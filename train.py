"""Train a universal walking policy with TRPO.

    python train.py                         # SE-TRPO, thesis protocol (600 epochs x 10 episodes)
    python train.py source=de epochs=100    # any override
    python train.py -m source=de,se seed=0,1,2
    python train.py resume=outputs/se/seed0/<run>/checkpoint.pt

Flat loop, top to bottom: collect one epoch of whole episodes, one TRPO update, log,
checkpoint. Ends with a saved policy, a design-grid evaluation and a summary.
"""

from __future__ import annotations

import csv
import signal
import time
from pathlib import Path

import hydra
import numpy as np
import torch
import tqdm
from hydra.core.hydra_config import HydraConfig
from hydra.utils import instantiate
from omegaconf import DictConfig, OmegaConf
from torchrl.collectors import Collector

from unipolicy_rl.checkpoint import load_checkpoint, save_checkpoint
from unipolicy_rl.envs import BatchedWalkerEnv, DesignDistribution
from unipolicy_rl.evaluation import evaluate_on_designs, plot_heatmaps, summarise, write_csv
from unipolicy_rl.evaluation.plots import plot_training_curve
from unipolicy_rl.factories import (
    env_kwargs,
    make_actor_critic,
    make_collecting_policy,
    make_collector,
    make_observation_norm,
)
from unipolicy_rl.objectives import TRPOLoss, TRPOUpdater, TrustRegion
from unipolicy_rl.observation_statistics import ObservationStatistics


def epoch_seed(seed: int, epoch: int) -> int:
    """The seed a run restarts its designs and action noise from at ``epoch``."""
    return int(np.random.SeedSequence([seed, epoch]).generate_state(1)[0])


def restart_randomness(collector, seed: int, epoch: int) -> None:
    """Reseeds every env's designs and every action sampler and resets every robot, from
    ``epoch_seed``: each epoch is then a function of the weights and statistics that start
    it, so a run resumed from any checkpoint continues exactly as the uninterrupted run.
    (The multi-process collector seeds each worker's torch and resets its robots itself.)
    """
    collector.set_seed(epoch_seed(seed, epoch))
    if isinstance(collector, Collector):
        torch.manual_seed(epoch_seed(seed, epoch))
        collector.reset()


def episode_metrics(batch, control_period: float, episode_length: int) -> dict[str, float]:
    """Mean episode reward, forward displacement (m) and speed (m/s) of the episodes that ended."""
    done = batch["next", "done"].squeeze(-1)
    displacement = batch["next", "observation"][..., 0][done]
    return {
        "train/episode_reward": batch["next", "episode_reward"].squeeze(-1)[done].mean().item(),
        "train/forward_displacement": displacement.mean().item(),
        "train/forward_speed": displacement.mean().item() / (episode_length * control_period),
        "train/physics_faults": batch["next", "physics_fault"].sum().item(),
    }


def append_metrics_row(path: Path, epoch: int, metrics: dict[str, float]) -> None:
    """One row per epoch in ``metrics.csv`` (appended, so a resumed run continues the file)."""
    row = {"epoch": epoch, **metrics}
    new = not path.is_file()
    with path.open("a", newline="") as file:
        writer = csv.DictWriter(file, fieldnames=list(row))
        if new:
            writer.writeheader()
        writer.writerow(row)


def training_state(epoch, actor, critic, statistics, updater, cfg, observation_dim, action_dim) -> dict:
    return {
        "epoch": epoch,
        "config": OmegaConf.to_container(cfg, resolve=True),
        "observation_dim": observation_dim,
        "action_dim": action_dim,
        "actor": actor.state_dict(),
        "critic": critic.state_dict(),
        "observation_statistics": statistics.state_dict(),
        "observation_loc": statistics.loc,
        "observation_scale": statistics.scale,
        "critic_optimizer": updater.critic_optimizer.state_dict(),
        "critic_generator": updater.generator.get_state(),
    }


def evaluate_final(cfg, checkpoint_path: Path, run_dir: Path, metrics_csv: Path | None) -> dict:
    from unipolicy_rl.checkpoint import load_policy

    loaded = load_policy(checkpoint_path)
    grid = cfg.evaluation
    designs = DesignDistribution(tuple(grid.length_range), tuple(grid.density_range)).grid(grid.grid)
    results = evaluate_on_designs(loaded.policy, dict(loaded.env_kwargs), designs,
                                  episodes_per_design=cfg.evaluation.episodes, seed=cfg.seed, progress=True)
    out = run_dir / "evaluation"
    write_csv(results, out / "designs.csv")
    plot_heatmaps(results, out, title=f"{cfg.source.name}-TRPO seed {cfg.seed}")
    if metrics_csv is not None and metrics_csv.is_file():
        plot_training_curve(metrics_csv, out / "training_curve.png")
    return summarise(results)


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
    torch.set_num_threads(1)  # PyBullet robots and small networks: threads only contend on 2 cores
    torch.manual_seed(cfg.seed)  # network initialisation
    run_dir = Path(HydraConfig.get().runtime.output_dir)

    probe = BatchedWalkerEnv(1, **env_kwargs(cfg))
    observation_dim = probe.observation_spec["observation"].shape[-1]
    action_dim = probe.action_spec.shape[-1]
    probe.close()
    actor, critic = make_actor_critic(cfg, observation_dim, action_dim)
    normalizer = make_observation_norm(observation_dim)
    statistics = ObservationStatistics(observation_dim)
    algo = cfg.algo
    loss = TRPOLoss(actor, critic, normalize_advantage=algo.normalize_advantage)
    loss.make_value_estimator(gamma=algo.gamma, lmbda=algo.lmbda)
    trust_region = TrustRegion(max_kl=algo.max_kl, damping=algo.damping, cg_iters=algo.cg_iters,
                               backtrack_factor=algo.backtrack_factor, max_backtracks=algo.max_backtracks)
    updater = TRPOUpdater(
        loss, trust_region=trust_region, critic_lr=algo.critic_lr, critic_epochs=algo.critic_epochs,
        critic_minibatch_size=algo.critic_minibatch_size, generator=torch.Generator().manual_seed(cfg.seed),
    )
    episode_length = cfg.robot.episode_length
    control_period = cfg.robot.physics.time_step * cfg.robot.physics.substeps

    start_epoch = 0
    if cfg.resume:
        state = load_checkpoint(cfg.resume)
        actor.load_state_dict(state["actor"])
        critic.load_state_dict(state["critic"])
        statistics.load_state_dict(state["observation_statistics"])
        updater.critic_optimizer.load_state_dict(state["critic_optimizer"])
        updater.generator.set_state(state["critic_generator"])
        start_epoch = state["epoch"]
        print(f"resumed from {cfg.resume} at epoch {start_epoch}")
    statistics.copy_to(normalizer)
    collector = make_collector(cfg, make_collecting_policy(normalizer, actor), cfg.epochs - start_epoch)

    logger = instantiate(cfg.logger)
    checkpoint_path = run_dir / "checkpoint.pt"
    metrics_csv = run_dir / "metrics.csv"

    def checkpoint(epoch: int) -> Path:
        state = training_state(epoch, actor, critic, statistics, updater, cfg, observation_dim, action_dim)
        return save_checkpoint(checkpoint_path, state)

    epoch = start_epoch
    batches = iter(collector)
    progress = tqdm.tqdm(range(start_epoch, cfg.epochs), initial=start_epoch, total=cfg.epochs,
                         disable=not cfg.progress_bar, desc=f"{cfg.source.name}-TRPO")
    with StopAtEpochEnd() as stop:
        for epoch in progress:
            started = time.perf_counter()
            restart_randomness(collector, cfg.seed, epoch)
            batch = next(batches)
            collected = time.perf_counter()
            normalizer(batch["next"])  # the critic's input at the next states, as the policy saw them
            metrics = episode_metrics(batch, control_period, episode_length)
            metrics.update(updater.update(batch))
            # The next epoch's policy normalises with statistics that include this epoch.
            statistics.update(batch["observation"])
            statistics.copy_to(normalizer)
            collector.update_policy_weights_()
            metrics["time/collect"] = collected - started
            metrics["time/update"] = time.perf_counter() - collected
            for name, value in metrics.items():
                logger.log_scalar(name, value, step=epoch + 1)
            append_metrics_row(metrics_csv, epoch + 1, metrics)
            progress.set_postfix(reward=f"{metrics['train/episode_reward']:.1f}",
                                 metres=f"{metrics['train/forward_displacement']:.2f}",
                                 kl=f"{metrics['train/kl']:.4f}")
            if (epoch + 1) % cfg.checkpoint_every == 0 or stop.requested:
                checkpoint(epoch + 1)
            if stop.requested:
                progress.close()
                collector.shutdown()
                print(f"stopped: saved epoch {epoch + 1} to {checkpoint_path}; continue with resume={checkpoint_path}")
                return {"epoch": epoch + 1, "checkpoint": str(checkpoint_path)}
    epoch = cfg.epochs
    path = checkpoint(epoch)
    collector.shutdown()

    summary = evaluate_final(cfg, path, run_dir, metrics_csv)
    print(f"saved policy: {path}")
    print(
        f"design grid {cfg.evaluation.grid}x{cfg.evaluation.grid}: mean forward displacement "
        f"{summary['mean_forward_displacement']:.2f} m (min {summary['min_forward_displacement']:.2f} m), "
        f"mean episode reward {summary['mean_episode_reward']:.1f}, "
        f"{summary['walking_designs']}/{summary['designs']} designs walk >= 1 m"
    )
    return {"epoch": epoch, "checkpoint": str(path), **summary}


if __name__ == "__main__":
    main()
