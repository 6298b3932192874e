"""How much a TRPO step gains under other trust-region settings, on a run's own policy and data.

TRPO moves the policy by ``sqrt(2 max_kl / s'Fs) s`` along ``s ~= F^-1 g`` (conjugate gradient,
``cg_iters`` Fisher-vector products, ``damping`` added to F). Where CG stops short of ``F^-1 g``
or the damping swamps F's small eigenvalues, the step spends its KL budget on a poorer direction
and gains less surrogate advantage per unit of KL. This loads a checkpoint, collects
``--batches`` real batches with its policy (the run's own collector and settings), and on each
applies one policy step under every setting of ``--settings`` (each from the same starting
weights, undone after), printing per setting the medians of: the surrogate gained, the KL
moved, the step's predicted gain, the line-search tries and the step's seconds, with the gain
as a ratio to the first setting's. One thread.

    python study/scripts/trpo_step_settings.py runs/specialist-transformer-train0/seed0/checkpoint.pt \\
        --settings 10:0.1 30:0.1 10:0.01 30:0.01
"""

from __future__ import annotations

import argparse
import dataclasses
import statistics
import time
from pathlib import Path

import torch
from omegaconf import OmegaConf

from unipolicy_rl.checkpoint import load_checkpoint
from unipolicy_rl.factories import make_learner, make_real_collector, make_trust_region
from unipolicy_rl.objectives import natural_gradient_step


def setting(text: str) -> tuple[int, float]:
    """``cg_iters:damping``, e.g. ``30:0.01``."""
    try:
        iterations, damping = text.split(":")
        parsed = int(iterations), float(damping)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected cg_iters:damping (e.g. 30:0.01), got {text!r}") from None
    if parsed[0] < 1 or not parsed[1] > 0:
        raise argparse.ArgumentTypeError(f"cg_iters must be >= 1 and damping > 0, got {text!r}")
    return parsed


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("checkpoint", type=Path, help="a TRPO run's checkpoint.pt")
    parser.add_argument("--settings", nargs="+", type=setting, default=[(10, 0.1), (30, 0.1), (10, 0.01)],
                        help="cg_iters:damping pairs, the first the reference (10:0.1 30:0.1 10:0.01)")
    parser.add_argument("--batches", type=int, default=3, help="real batches to step on (3)")
    args = parser.parse_args(argv)
    if args.batches < 1:  # (else the collector's loop below would never stop)
        parser.error(f"--batches must be >= 1, got {args.batches}")
    torch.set_num_threads(1)
    state = load_checkpoint(args.checkpoint)
    cfg = OmegaConf.create(state["config"])
    if cfg.algo.name != "trpo":
        parser.error(f"{args.checkpoint} is a run of algo={cfg.algo.name}; this compares TRPO steps")
    learner = make_learner(cfg, state["observation_dim"], state["action_dim"])
    learner.load_state_dict(state["learner"])
    loss = learner.loss
    reference = make_trust_region(cfg)
    start = {name: value.detach().clone() for name, value in loss.actor_network_params.items(True, True)}
    results: dict[tuple[int, float], list[tuple[float, float, float, int, float]]] = {key: [] for key in args.settings}
    with make_real_collector(cfg, learner.policy, full_state=False) as collector:
        for number, batch in enumerate(collector, start=1):
            learner.normalizer(batch["next"])  # as TRPOLearner.update: the critic's next-state input
            loss.compute_advantage(batch)
            flat = batch.reshape(-1)
            advantage = loss.advantage(flat)
            for cg_iters, damping in args.settings:
                region = dataclasses.replace(reference, cg_iters=cg_iters, damping=damping)
                began = time.perf_counter()
                step = natural_gradient_step(loss, flat, advantage=advantage, trust_region=region)
                seconds = time.perf_counter() - began
                results[(cg_iters, damping)].append((step.surrogate_improvement, step.kl, step.expected_improvement,
                                                     step.line_search_tries, seconds))
                with torch.no_grad():  # undo: every setting steps from the same weights
                    for name, value in loss.actor_network_params.items(True, True):
                        value.copy_(start[name])
            if number == args.batches:
                break
    print(f"{args.checkpoint} (epoch {state['epoch']}), {args.batches} batches, max_kl {reference.max_kl}, "
          f"fisher_fraction {reference.fisher_fraction}; medians:")
    first = statistics.median(row[0] for row in results[args.settings[0]])
    for (cg_iters, damping), rows in results.items():
        gain, kl, expected, tries, seconds = (statistics.median(column) for column in zip(*rows, strict=True))
        print(f"  cg_iters {cg_iters:3d} damping {damping:<6g} surrogate gain {gain:.4f} ({gain / first:.2f}x)  "
              f"KL {kl:.4f}  predicted {expected:.4f}  line-search tries {tries:.0f}  step {seconds:.2f} s")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
