"""The thesis-size model ensemble fitted on real transitions: how long, and what batching buys.

    python benchmarks/model_fit.py [--transitions 500000] [--max-epochs 100] [--loop-members 3]

The model is the thesis' (``world_model=moe_thesis``): a :class:`CellEnsemble` with 6 x 6
cells over the SE design ranges, each cell a position and a velocity network (2 x 200 ReLU,
72 networks), predicting the next 18-number thesis observation from the current one, the
action and (l, rho). The data: ``--transitions`` real steps of SE robots walking the
open-loop gait plus Gaussian noise (``world_model_setup.py``: 2 ``SleepingParallelEnv`` workers of
32 ``BatchedWalkerEnv(full_state=True)`` robots; cached in /tmp, so a rerun skips the
physics and reports the cached collection's rate).

The fit is :class:`ModelTrainer` with ``conf/world_model/moe_thesis.yaml``'s trainer
settings (Adam 1e-3, 256 samples per member per step, 80/20 split, early stopping after
``patience`` epochs without any member improving its validation error by 1%), except that
``max_epochs`` is raised (``--max-epochs``) so early stopping, not the cap, ends the fit.
It runs twice from the same initial weights and split: ``num_threads=2`` (the headline,
what a training run's fit uses) and ``num_threads=1``; each prints its wall time and this
process's CPU time (all threads': CPU well above wall time is threads spinning, not working).

The comparison: the same 72 networks fitted one at a time as separate
``torch.nn.Sequential`` MLPs, each with its own Adam, one network's minibatches after
another's, over each cell's own training samples. One epoch of that loop is timed on
``--loop-members`` cells (both their networks) and extrapolated to all 36 cells by
minibatch steps (time per step x the steps all 72 networks take in an epoch). The batched
side is the whole fit's wall time per epoch (its validation pass, set-up and early stopping
included), the loop's only its training steps, so the ratio flatters the loop.

Also prints the raw PyBullet rate of one core (``env_throughput.raw_pybullet``) at the
start and the end of the run, beside the absolute times. The last line is
``model_fit_ratio: <batched / per-network loop, seconds per epoch, 2 threads>``.
"""

from __future__ import annotations

import argparse
import copy
import math
import time

import torch
import world_model_setup as setup
from env_throughput import raw_pybullet
from torch import nn

from unipolicy_rl.envs import RobotSettings
from unipolicy_rl.world_models import CellEnsemble, StateLayout


def per_network_loop_epoch(model: CellEnsemble, data, members: list[int], batch_size: int, learning_rate: float,
                           generator: torch.Generator) -> tuple[float, int]:
    """One epoch of fitting ``members``' networks one at a time: (seconds, minibatch steps).

    Each network is its own ``nn.Sequential`` with its own Adam, trained on its cell's own
    standardised samples (the model's fitted standardisers), one network after another.
    """
    with torch.no_grad():
        x = model.input_norm(model.inputs(data["state"], data["action"], data["design"]))
        y = model.target_norm(model.targets(data["state"], data["next_state"]))
    cells = model.cell(data["design"])
    jobs = []
    for member in members:
        rows = torch.nonzero(cells == member).squeeze(-1)
        for columns in (model.positions, model.velocities):
            width = x.shape[-1]
            layers: list[nn.Module] = []
            for hidden in (200, 200):
                layers += [nn.Linear(width, hidden), nn.ReLU()]
                width = hidden
            network = nn.Sequential(*layers, nn.Linear(width, len(columns)))
            jobs.append((network, torch.optim.Adam(network.parameters(), lr=learning_rate), x[rows],
                         y[rows][:, columns]))
    steps = 0
    started = time.perf_counter()
    for network, optimizer, inputs, targets in jobs:
        order = torch.randperm(len(inputs), generator=generator)
        for chunk in order.split(batch_size):
            loss = nn.functional.mse_loss(network(inputs[chunk]), targets[chunk])
            optimizer.zero_grad(set_to_none=True)
            loss.backward()
            optimizer.step()
            steps += 1
    return time.perf_counter() - started, steps


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--transitions", type=int, default=500_000, help="real transitions to fit on")
    parser.add_argument("--max-epochs", type=int, default=100, help="cap on epochs (early stopping ends the fit first)")
    parser.add_argument("--loop-members", type=int, default=3, help="cells timed in the per-network loop")
    parser.add_argument("--noise", type=float, default=0.3, help="std of the Gaussian noise on the gait's actions")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    torch.set_num_threads(1)

    raw_start, _ = raw_pybullet(2000)
    collection = setup.collect(math.ceil(args.transitions / setup.EPISODE_LENGTH), args.noise, args.seed)
    layout = StateLayout.for_env(RobotSettings(), "thesis", False, "thesis")
    data = collection.transitions(layout.from_full)[: args.transitions]
    print(f"raw PyBullet loop, one core: {raw_start:.0f} actions/s (start of run)")
    print(f"collection: {collection.episodes.shape[0]} episodes, {data.shape[0]} transitions of {layout.size} numbers, "
          f"{collection.seconds:.1f} s at {collection.actions_per_second:.0f} actions/s "
          f"(2 workers x 32 robots{', cached from an earlier run' if collection.cached else ''})")

    settings = setup.trainer_settings("moe_thesis", max_epochs=args.max_epochs)
    print("trainer: " + ", ".join(f"{k}={v}" for k, v in settings.items() if k != "num_threads"))
    torch.manual_seed(args.seed)
    model = setup.make_model("moe_thesis")
    initial = copy.deepcopy(model.state_dict())
    reports = {}
    for threads in (2, 1):
        model.load_state_dict(initial)
        trainer = setup.make_trainer("moe_thesis", threads=threads, max_epochs=args.max_epochs)
        cpu = time.process_time()
        reports[threads] = report = trainer.fit(model, data, torch.Generator().manual_seed(args.seed))
        cpu = time.process_time() - cpu
        stopped = "early stopping" if report.epochs < args.max_epochs else "the epoch cap"
        finite = report.validation_error[torch.isfinite(report.validation_error)]
        print(f"batched fit, num_threads={threads}: {report.seconds:.1f} s ({cpu:.1f} s of CPU), "
              f"{report.epochs} epochs ({report.seconds / report.epochs:.2f} s/epoch, ended by {stopped}); "
              "validation MSE (standardised) "
              f"median {finite.median():.4f}, max {finite.max():.4f} over {finite.numel()} members; "
              f"{report.members_without_data} members without data")

    cells = model.cell(data["design"])
    train_rows = data[torch.randperm(data.shape[0], generator=torch.Generator().manual_seed(args.seed))
                      [round(settings["validation_fraction"] * data.shape[0]):]]
    train_cells = model.cell(train_rows["design"])
    counts = torch.bincount(train_cells, minlength=model.members)
    batch_size = settings["batch_size"]
    all_steps = 2 * int(sum(math.ceil(int(c) / batch_size) for c in counts))
    batched_steps = math.ceil(int(counts.max()) / batch_size)
    members = sorted({round(i * (model.members - 1) / max(args.loop_members - 1, 1)) for i in range(args.loop_members)})
    loop = {}
    for threads in (2, 1):
        torch.set_num_threads(threads)
        seconds, steps = per_network_loop_epoch(model, train_rows, members, batch_size, settings["learning_rate"],
                                                torch.Generator().manual_seed(args.seed))
        loop[threads] = seconds / steps * all_steps
        print(f"per-network loop, {threads} thread(s): {steps} minibatch steps of cells {members} in {seconds:.2f} s "
              f"-> {loop[threads]:.1f} s per epoch for all 72 networks ({all_steps} steps)")
    torch.set_num_threads(1)
    raw_end, _ = raw_pybullet(2000)
    print(f"raw PyBullet loop, one core: {raw_end:.0f} actions/s (end of run)")
    print(f"training samples per cell: {int(counts.min())}-{int(counts.max())} (cells {len(cells.unique())}); "
          f"a batched epoch is {batched_steps} steps of all 72 networks at once")
    for threads in (2, 1):
        per_epoch = reports[threads].seconds / reports[threads].epochs
        print(f"batched / per-network loop, seconds per epoch, {threads} thread(s): "
              f"{per_epoch:.2f} / {loop[threads]:.1f} = {per_epoch / loop[threads]:.3f}")
    print(f"fit time, num_threads=1 / num_threads=2: {reports[1].seconds:.1f} / {reports[2].seconds:.1f} s = "
          f"{reports[1].seconds / reports[2].seconds:.2f} (per epoch "
          f"{(reports[1].seconds / reports[1].epochs) / (reports[2].seconds / reports[2].epochs):.2f})")
    verdict = "met" if reports[2].seconds <= 60 else "missed"
    print(f"fit_seconds (num_threads=2): {reports[2].seconds:.1f} (target 60: {verdict})")
    per_epoch = reports[2].seconds / reports[2].epochs
    print(f"model_fit_ratio: {per_epoch / loop[2]:.3f}")


if __name__ == "__main__":
    main()
