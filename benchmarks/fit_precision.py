"""The world model's fit in float32 against bfloat16 autocast (``world_model.trainer.precision``), and Adam's
fused kernel against its default one (``unipolicy_rl/cpu_speed/fused_adam.py``), on a run's own data.

    python benchmarks/fit_precision.py <checkpoint.pt of a source=moe run> [--repeats 3] [--fresh 1000]

Takes a model-based run's checkpoint (its replay buffer and its world model's and trainer's
settings), holds out the newest ``--fresh`` transitions (the states the policy visited last, as
``model/fresh_error`` does in training), and fits a freshly initialised model (the same initial
weights for both) on the rest with the run's own trainer for ``--steps`` gradient steps (its
``max_steps``; the checkpoint's own weights have already fitted these data, and a fit from them
stops at once), once per arm -- float32 with Adam's default (for-loop) kernel, as fits ran
before the fused one, float32 and bfloat16 with the fused kernel the trainer now uses -- the arms
alternating repetition by repetition so that load from other processes hits all alike. Per fit it
prints the wall time,
the gradient steps (early stopping may take a different number), the seconds per step, the
median member's validation error and the error on the held-out newest transitions. Then the
medians, ``fit_fused_adam_ratio: <fused / default kernel, float32 seconds per gradient step>`` and
the last line ``fit_precision_ratio: <bfloat16 / float32 seconds per gradient step>`` (both fused).

bfloat16 pays only where the CPU has bfloat16 instructions (``avx512_bf16``, ``amx_bf16`` in
``/proc/cpuinfo``) or on a GPU; elsewhere autocast emulates it and is slower. The raw PyBullet rate
is not printed: nothing here steps the physics.
"""

from __future__ import annotations

import argparse
import contextlib
import copy
import statistics
from pathlib import Path
from unittest import mock

import torch
from hydra.utils import instantiate
from omegaconf import OmegaConf

from unipolicy_rl.checkpoint import load_checkpoint
from unipolicy_rl.factories import make_world_model_parts
from unipolicy_rl.seeding import MODEL_FIT, reseed
from unipolicy_rl.world_models import trainer as trainer_module
from unipolicy_rl.world_models.fresh_error import fresh_error

# name: (precision, Adam's kernel: fused or torch's default)
ARMS = {"float32-default-adam": ("float32", False), "float32": ("float32", True), "bfloat16": ("bfloat16", True)}


def default_adam(params, **settings) -> torch.optim.Adam:
    return torch.optim.Adam(params, **settings)


def adam_kernel(fused: bool):
    """The trainer's optimiser as it is (fused), or patched to torch's default kernel."""
    return contextlib.nullcontext() if fused else mock.patch.object(trainer_module, "adam", default_adam)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("checkpoint", type=Path, help="checkpoint.pt of a source=moe run")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--fresh", type=int, default=1000, help="newest transitions held out of the fit (1,000)")
    parser.add_argument("--steps", type=int, default=500, help="gradient steps per fit, at most (500)")
    parser.add_argument("--threads", type=int, default=1, help="torch threads (1, as runs use)")
    args = parser.parse_args()
    if args.repeats < 1:
        parser.error(f"--repeats must be at least 1, got {args.repeats}")
    if args.steps < 1:
        parser.error(f"--steps must be at least 1, got {args.steps}")
    torch.set_num_threads(args.threads)
    state = load_checkpoint(args.checkpoint)
    cfg = OmegaConf.create(state["config"])
    if cfg.source.name != "moe":
        parser.error(f"{args.checkpoint} is a source={cfg.source.name} run; this benchmark fits a neural world model")
    torch.manual_seed(cfg.seed)
    world = make_world_model_parts(cfg, state["action_dim"])  # a fresh model: weights as a run starts
    world.buffer.load_state_dict(state["replay_buffer"])
    data = world.buffer.contents()
    if not 2 <= args.fresh < len(data) // 2:
        parser.error(f"--fresh must lie in [2, {len(data) // 2}) for a buffer of {len(data)}, got {args.fresh}")
    fit_rows, fresh_rows = data[: len(data) - args.fresh], data[len(data) - args.fresh:]
    start = copy.deepcopy(world.model.state_dict())
    epoch = int(state["epoch"])
    print(f"{args.checkpoint}: epoch {epoch}, fitting on {len(fit_rows)} transitions, the newest {args.fresh} held out")
    results: dict[str, list[tuple[float, int, float, float]]] = {arm: [] for arm in ARMS}
    for repeat in range(args.repeats):
        for arm, (precision, fused) in ARMS.items():
            world.model.load_state_dict(start)
            trainer = instantiate(cfg.world_model.trainer, precision=precision, max_steps=args.steps)
            with adam_kernel(fused):
                report = trainer.fit(world.model, fit_rows, reseed(cfg.seed, epoch, MODEL_FIT))
            steps = int(report.extras["fit_steps"])
            error = float(report.validation_error.median())
            fresh = fresh_error(world.model, fresh_rows)["model/fresh_error"]
            results[arm].append((report.seconds, steps, error, fresh))
            print(f"repeat {repeat}: {arm:20s} {report.seconds:6.1f} s, {steps:4d} steps "
                  f"({1e3 * report.seconds / steps:5.1f} ms each), validation error {error:.4f}, "
                  f"newest transitions {fresh:.4f}", flush=True)
    per_step = {}
    for arm, rows in results.items():
        per_step[arm] = statistics.median(seconds / steps for seconds, steps, _, _ in rows)
        seconds, error, fresh = (statistics.median(r[k] for r in rows) for k in (0, 2, 3))
        print(f"median {arm:20s}: {seconds:6.1f} s, {1e3 * per_step[arm]:5.1f} ms per step, "
              f"validation error {error:.4f}, newest transitions {fresh:.4f}")
    print(f"fit_fused_adam_ratio: {per_step['float32'] / per_step['float32-default-adam']:.3f}")
    print(f"fit_precision_ratio: {per_step['bfloat16'] / per_step['float32']:.3f}")


if __name__ == "__main__":
    main()
