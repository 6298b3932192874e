"""Train a universal walking policy on the real robot or on a world model fitted to it (or any gymnasium task's).

    python train.py                         # SE-TRPO, thesis protocol (600 epochs x 10 episodes)
    python train.py source=moe              # SE-MOE-TRPO: the ensemble world model, 20 imagined updates per fit
    python train.py env=gym env.id=Pendulum-v1 source=moe   # ME-TRPO on a gymnasium task
    python train.py source=de epochs=100    # any override
    python train.py -m source=de,se seed=0,1,2
    python train.py resume=outputs/se-trpo/seed0/<run>/checkpoint.pt
    python train.py robot=grammar policy=token_modular init_policy=<distilled run>/checkpoint.pt   # fine-tune

One loop, one real epoch per pass, read top to bottom: real episodes -> a policy update on them
(a real source; a model-based one where ``imagination.train_on_real``) -> the observation
normaliser's refresh -> for a model-based source: the replay buffer, the model fit (every
``imagination.fit_every`` epochs; with ``imagination.background_fit`` on a second thread beside the
updates, which then use the previous fit), then policy updates on imagined branches until the
stopping rule says stop -> evaluation -> checkpoint. Ends with the saved policy evaluated on the design grid.
"""

from __future__ import annotations

import sys
import time
from contextlib import closing
from functools import partial
from pathlib import Path

import hydra
import torch
from hydra.core.hydra_config import HydraConfig
from hydra.utils import instantiate
from omegaconf import DictConfig, OmegaConf

from unipolicy_rl import metric_columns as columns
from unipolicy_rl.checkpoint import RunCheckpoints, check_resumable, load_checkpoint, restore_training_state
from unipolicy_rl.collectors import imagined_metrics
from unipolicy_rl.evaluation import format_morphology_summary, format_summary
from unipolicy_rl.factories import (
    make_learner,
    make_real_collector,
    make_refits_within_epoch,
    make_world_model_parts,
    probe_dimensions,
)
from unipolicy_rl.initial_policy import policy_to_start_from
from unipolicy_rl.learners.policy_average import end_of_epoch, learning_policy
from unipolicy_rl.objectives.adaptive_kl import imagined_trust_region
from unipolicy_rl.resume import named_keys, record_resumed_config, settings_for_resume, with_the_runs_groups
from unipolicy_rl.seeding import MODEL_FIT, reseed
from unipolicy_rl.settings import evaluation_plan
from unipolicy_rl.training import RunLock, StopAtEpochEnd, process_tree_cpu_seconds
from unipolicy_rl.training.progress import (
    RunLog,
    describe_best,
    episode_metrics,
    evaluate_final,
    make_evaluation,
    naming_the_checkpoint_on_stall,
)
from unipolicy_rl.validation import validate_config
from unipolicy_rl.world_models import PendingFit
from unipolicy_rl.world_models.fresh_error import fresh_error

CONFIG_DIR = Path(__file__).resolve().parent / "conf"


@hydra.main(version_base="1.3", config_path="conf", config_name="config")
def main(cfg: DictConfig) -> dict:
    hydra_config = HydraConfig.get()
    choices = {group: choice for group, choice in hydra_config.runtime.choices.items()
               if not group.startswith("hydra/")}
    state = load_checkpoint(cfg.resume) if cfg.resume else None
    if state is not None:  # the run's own settings, but for those this command line names
        check_resumable(state, cfg.resume)
        cfg = settings_for_resume(cfg, state, named_keys(hydra_config.overrides.task, choices), choices, cfg.resume)
        record_resumed_config(cfg, Path(hydra_config.runtime.output_dir), hydra_config.output_subdir)
    validate_config(cfg)  # every setting, before any robot is built or any time is spent
    torch.set_num_threads(1)  # PyBullet robots and small networks: threads only contend on 2 cores
    torch.manual_seed(cfg.seed)  # network initialisation
    run_dir = Path(HydraConfig.get().runtime.output_dir)

    observation_dim, action_dim = probe_dimensions(cfg)
    learner = make_learner(cfg, observation_dim, action_dim)
    if cfg.init_policy and state is None:  # a new run from another run's policy (before collectors copy it)
        learner.start_from_policy(policy_to_start_from(cfg, cfg.init_policy, observation_dim, action_dim))
        print(f"started from the policy in {cfg.init_policy}")
    model_based = cfg.source.kind == "model"
    # (algo.update_every: an off-policy learner steps between chunks of the epoch as they come)
    between_chunks = learner.update_chunk if OmegaConf.select(cfg, "algo.update_every") else None
    real = make_real_collector(cfg, learner.policy, full_state=model_based, between_chunks=between_chunks)
    # From here on, a failure anywhere still shuts the collector's worker processes and the
    # learner's critic process down (else the interpreter waits for them on exit).
    with real, closing(learner), RunLock(run_dir), naming_the_checkpoint_on_stall(run_dir / "checkpoint.pt"), \
            StopAtEpochEnd() as stop:
        world = make_world_model_parts(cfg, action_dim) if model_based else None
        if state is not None:
            restore_training_state(state, learner=learner, collector=real, world=world)
            real.update_policy_weights_()
            print(f"resumed from {cfg.resume} at epoch {state['epoch']}")
        # (imagination.refit_every: MBPO's refits while the epoch is collected, between its chunks)
        refits = make_refits_within_epoch(cfg, learner, world, learning_policy(learner), real.epoch + 1) \
            if world is not None else None
        if refits is not None:
            real.between_chunks = refits
        checkpoints = RunCheckpoints(run_dir, config=OmegaConf.to_container(cfg, resolve=True), choices=choices,
                                     observation_dim=observation_dim, action_dim=action_dim, learner=learner,
                                     collector=real, world=world,
                                     elapsed_before=state.get("elapsed", 0.0) if state else 0.0)
        plan = evaluation_plan(cfg)  # what the reports and evaluations run on, and when
        evaluation = make_evaluation(plan, best=state.get("best_evaluation") if state else None, run_dir=run_dir)
        log = RunLog(instantiate(cfg.logger), run_dir, cfg.epochs, real.epoch, cfg.run_name, cfg.progress_bar)
        tick, tick_cpu = time.perf_counter(), process_tree_cpu_seconds()
        for batch in real:
            epoch = real.epoch
            # ---- Real data (and a policy update on it, unless the world model's data alone train it)
            collected = time.perf_counter()
            metrics = {columns.IMAGINED: 0.0, **episode_metrics(batch, plan)}
            if world is None or world.imagination.train_on_real:
                metrics.update(learner.update(batch))
            # The next updates normalise with statistics that include this epoch's observations.
            metrics.update(learner.refresh_observation_normalizer(batch))
            metrics.update(real.metrics())
            if world is not None:
                # ---- Model training on the replay buffer of real transitions
                # (what the model the policy last trained on gets wrong on the states it now visits)
                fitted_before = len(world.buffer) > 0
                # (with refits within the epoch, the buffer holds its steps up to the last of them)
                new_transitions = world.buffer.extend(batch if refits is None else refits.rest_of_epoch(batch), epoch)
                if refits is not None:
                    metrics.update(refits.metrics())
                if fitted_before:
                    metrics.update(fresh_error(world.model, new_transitions))
                fit = None
                if world.imagination.settings.fits_after(epoch):
                    # (imagination.background_fit: on a second thread, the updates below on the previous fit)
                    fit = PendingFit(world.trainer, world.model, world.buffer.contents(),
                                     reseed(cfg.seed, epoch, MODEL_FIT),
                                     background=world.imagination.settings.background_fit and fitted_before)
                # ---- Policy training on imagined branches, until the stopping rule says stop
                # (stopping.kind=real: each check measures the policy's surrogate on this epoch's real batch)
                real_surrogate = (partial(learner.real_surrogate, batch)
                                  if world.imagination.stopping.kind == "real" else None)
                # (algo.policy_average: the learner's own weights, not the average that acts)
                imagined = world.imagination.epoch(epoch, world.buffer.contents(), learning_policy(learner),
                                                   real_surrogate)
                # (imagination.adaptive_kl: their KL bound shrinks as the model's fresh error rises)
                with imagined_trust_region(world.imagination.settings.adaptive_kl, learner,
                                           metrics.get(columns.FRESH_ERROR)) as bound:
                    for rollout in imagined:
                        started = time.perf_counter()
                        row = {columns.IMAGINED: 1.0, **learner.update(rollout), **imagined_metrics(rollout)}
                        log.row(epoch, {**row, **real.metrics(), columns.COLLECT_TIME: imagined.rollout_seconds,
                                        columns.UPDATE_TIME: time.perf_counter() - started})
                metrics.update(bound)
                metrics.update(imagined.metrics())
                if fit is not None:
                    metrics.update(fit.result().as_metrics())  # the model now holds this epoch's fit
            metrics.update(end_of_epoch(learner))  # algo.policy_average: the acting policy's averaging step
            real.update_policy_weights_()
            # (the learner's steps between chunks, taken while the epoch was collected, count as updates)
            metrics[columns.COLLECT_TIME] = collected - tick - real.between_chunks_seconds
            metrics[columns.UPDATE_TIME] = time.perf_counter() - collected + real.between_chunks_seconds
            metrics[columns.CPU_TIME] = process_tree_cpu_seconds() - tick_cpu
            # ---- Evaluation (deterministic policy, real env, design grid) and checkpoint
            metrics.update(evaluation(epoch, real.real_env_steps, learner.policy))
            if evaluation.improved:
                checkpoints.save_best(evaluation.best)
            log.row(epoch, {**metrics, columns.ELAPSED: checkpoints.elapsed()})
            log.epoch_done()
            if epoch % cfg.checkpoint_every == 0 or stop.requested:
                checkpoints.save(evaluation.best)
            if stop.requested:
                log.close()
                print(f"stopped: saved epoch {epoch} to {checkpoints.path}; continue with resume={checkpoints.path}")
                return {"epoch": epoch, "checkpoint": str(checkpoints.path)}
            tick, tick_cpu = time.perf_counter(), process_tree_cpu_seconds()
        log.close()
        path = checkpoints.save(evaluation.best)

    summary = evaluate_final(plan, path, run_dir, cfg.run_name)
    print(f"saved policy: {path}")
    if "mean_return" in summary:  # env=gym: returns over env.evaluation_episodes episodes
        print(f"{summary['episodes']} episodes: mean return {summary['mean_return']:.1f} (lowest "
              f"{summary['min_return']:.1f}, highest {summary['max_return']:.1f})")
    else:
        print(f"design grid {cfg.evaluation.grid}x{cfg.evaluation.grid}:")
        print(format_summary(summary))
    if "morphologies" in summary:  # robot=grammar: the grid of every evaluated morphology
        print(format_morphology_summary(summary))
    best = evaluation.best
    if best is not None:
        print(f"best periodic evaluation: {describe_best(best)}; its policy: {checkpoints.best_path}")
    return {"epoch": real.epoch, "checkpoint": str(path), "best": best, **summary}


if __name__ == "__main__":
    sys.argv = with_the_runs_groups(sys.argv, CONFIG_DIR)  # resume=<checkpoint>: composed from the run's groups
    main()
