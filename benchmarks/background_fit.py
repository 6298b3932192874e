"""A model-based epoch's fit and imagined updates one after the other, against the fit on a second thread.

    python benchmarks/background_fit.py <checkpoint.pt of a model-based run> [--repeats 3]

``imagination.background_fit`` runs the world model's fit (:class:`~unipolicy_rl.world_models.PendingFit`)
beside the policy's imagined updates instead of before them. This benchmark takes a model-based
run's checkpoint (its replay buffer, model, policy and config), then per repetition, from the same
start each time: the fit and then the epoch's imagined updates in one thread (what a run does by
default), and the same two with the fit in the background. The two alternate, repetition by
repetition, so load from other processes hits both alike. It prints each one's seconds, the
medians and their ratio, the last line ``background_fit_ratio: <background / in turn>``. It pays
only where a core is free: on a machine whose cores are all busy the ratio tends to 1.
"""

from __future__ import annotations

import argparse
import copy
import statistics
import time
from pathlib import Path

import torch
from omegaconf import OmegaConf

from unipolicy_rl.checkpoint import load_checkpoint
from unipolicy_rl.factories import make_learner, make_world_model_parts
from unipolicy_rl.seeding import MODEL_FIT, reseed
from unipolicy_rl.world_models import PendingFit


def one_epoch(learner, world, epoch: int, seed: int, background: bool) -> tuple[float, float, int]:
    """(wall seconds of the fit and the updates together, of the fit alone, updates taken)."""
    started = time.perf_counter()
    data = world.buffer.contents()
    fit = PendingFit(world.trainer, world.model, data, reseed(seed, epoch, MODEL_FIT), background=background)
    updates = 0
    for rollout in world.imagination.epoch(epoch, data, learner.policy):
        learner.update(rollout)
        updates += 1
    report = fit.result()
    return time.perf_counter() - started, report.seconds, updates


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("checkpoint", type=Path, help="checkpoint.pt of a model-based run (source=moe or pce)")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--threads", type=int, default=1, help="torch threads per thread of work (1, as runs use)")
    args = parser.parse_args()
    if args.repeats < 1:
        parser.error(f"--repeats must be at least 1, got {args.repeats}")
    torch.set_num_threads(args.threads)
    state = load_checkpoint(args.checkpoint)
    cfg = OmegaConf.create(state["config"])
    if cfg.source.kind != "model":
        parser.error(f"{args.checkpoint} is a {cfg.source.name} run; this benchmark needs a model-based one")
    learner = make_learner(cfg, state["observation_dim"], state["action_dim"])
    world = make_world_model_parts(cfg, state["action_dim"])
    learner.load_state_dict(state["learner"])
    world.model.load_state_dict(state["world_model"])
    world.buffer.load_state_dict(state["replay_buffer"])
    epoch = int(state["epoch"])
    start_learner, start_model = copy.deepcopy(learner.state_dict()), copy.deepcopy(world.model.state_dict())
    print(f"{args.checkpoint}: epoch {epoch}, {len(world.buffer)} transitions, {cfg.run_name}")
    timings: dict[bool, list[float]] = {False: [], True: []}
    for repeat in range(args.repeats):
        for background in (False, True):
            learner.load_state_dict(start_learner)
            world.model.load_state_dict(start_model)
            total, fit_seconds, updates = one_epoch(learner, world, epoch, cfg.seed, background)
            timings[background].append(total)
            print(f"repeat {repeat}: {'background' if background else 'in turn   '} {total:6.1f} s "
                  f"(fit {fit_seconds:.1f} s, {updates} imagined updates)", flush=True)
    in_turn, background = statistics.median(timings[False]), statistics.median(timings[True])
    print(f"median: in turn {in_turn:.1f} s, fit in the background {background:.1f} s")
    print(f"background_fit_ratio: {background / in_turn:.3f}")


if __name__ == "__main__":
    main()
