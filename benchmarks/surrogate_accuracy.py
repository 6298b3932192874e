"""Surrogate accuracy over the horizon: the one-step PCE and the default ensemble side by side.

    python benchmarks/surrogate_accuracy.py [--episodes 200] [--samples 10] [--max-epochs 10] [--quick]

Data: real SE episodes with uniform random actions (``pce_data.py``, the thesis' section
6.1.2 setting, cached in /tmp), 100 actions each; an episode with a physics fault is dropped,
the first 80% fit the models, the rest are held out. Models as ``conf/world_model/pce.yaml``
and ``moe.yaml`` configure them (model and trainer), both predicting the env's full state,
with one exception: the ensemble's fit is capped at ``--max-epochs`` (10; the yaml allows 30,
early stopping may end it sooner) so the default run stays near 5 minutes on 2 cores; the
PCE's fit is closed form and takes seconds. ``--quick``: 100 episodes, 5 rollouts per
episode, 5 ensemble epochs, about a minute.

Each model is rolled out open loop from every held-out episode's real start state with its
real actions, ``--samples`` times per episode, as imagination runs it (a member drawn per
trajectory, the imagined env's fault rule: a non-finite or exploded prediction keeps the last
state, and the trajectory counts as faulted from there on), with sampled noise (``sampled``)
and without (``deterministic``, the drawn member's mean). At 6 steps (0.4 s, the thesis'
horizon), 10, 25 (the longest imagined branch in training) and 100, for the base's forward
position x and velocity vx (:mod:`unipolicy_rl.evaluation.accuracy`):

* the Jensen-Shannon divergence in bits between the held-out episodes' distribution and the
  surrogate's, with ``--bins`` bins of equal mass under their mixture. The row ``real vs
  real`` compares the fitting episodes with the held-out ones: about the figure a perfect
  surrogate would get at these sample sizes (the histogram estimate's noise floor);
* the mean relative error (median in brackets), |s - s_hat| / max(|s|, floor), floors 1 cm
  and 1 cm/s (thesis eq. 5.2), each sampled trajectory against its own episode;
* the share of rollouts that have faulted by then (imagination would have ended them; here
  their held state stays in the figures above).

The figure (``--figure``, default ``docs/figures/surrogate_accuracy.png``, the one the docs show;
with ``--quick``, ``outputs/benchmarks/surrogate_accuracy_quick.png``, so a quick check never
overwrites the committed figure with a smaller run's): held-out mean and 95% band of x and vx
against each model's sampled rollouts, the 25-step horizon dotted.
The raw PyBullet rate of this run is printed first (machines differ, and a VM's speed drifts:
docs/results.md, "Environment throughput").
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import torch
from env_throughput import raw_pybullet
from pce_data import collect
from world_model_setup import configured

from unipolicy_rl.collectors import transitions
from unipolicy_rl.envs import PhysicsSettings, RobotSettings
from unipolicy_rl.evaluation.accuracy import THESIS_FLOOR, jensen_shannon, plot_bands, relative_error
from unipolicy_rl.training.metrics_file import MODEL_VALIDATION_MSE
from unipolicy_rl.world_models import StateLayout
from unipolicy_rl.world_models.imagined import PredictNextState

ROOT = Path(__file__).resolve().parent.parent
FIGURE = ROOT / "docs" / "figures" / "surrogate_accuracy.png"  # committed, shown by docs/surrogate_accuracy.md
QUICK_FIGURE = ROOT / "outputs" / "benchmarks" / "surrogate_accuracy_quick.png"  # outputs/ is git-ignored
HORIZONS = (6, 10, 25, 100)
TRAINING_HORIZON = 25  # conf/world_model/*.yaml: imagination.horizon.end
COLUMNS = {0: "x", 3: "vx"}  # the base's forward position and velocity in the state
MODELS = {"one-step PCE": "pce", "ensemble": "moe"}


def split(episodes, fraction: float = 0.8):
    """(fit, held out): faulted episodes dropped, the first ``fraction`` to fit."""
    episodes = episodes[~episodes["next", "physics_fault"].squeeze(-1).any(1)]
    cut = int(fraction * episodes.batch_size[0])
    return episodes[:cut], episodes[cut:]


def trajectories(layout: StateLayout, episodes) -> torch.Tensor:
    """``[E, 101, S]``: the real start state then the state after each action."""
    return layout.from_full(torch.cat([episodes["state"][:, :1], episodes["next", "state"]], 1))


def rollouts(model, start: torch.Tensor, actions: torch.Tensor, designs: torch.Tensor, samples: int,
             deterministic: bool, generator: torch.Generator) -> tuple[torch.Tensor, torch.Tensor]:
    """``[E, samples, 101, S]`` open-loop trajectories from the real start states (step 0), and
    ``[E, samples, 101]``: whether each has had a fault by then (its state held since, as the
    imagined env holds it; imagination would have ended the trajectory there)."""
    start, actions, designs = (values.repeat_interleave(samples, 0) for values in (start, actions, designs))
    predict = PredictNextState(model, deterministic=deterministic)
    member = model.draw_members(designs, generator).unsqueeze(-1)
    state, path, faulted = start, [start], [torch.zeros(start.shape[0], dtype=torch.bool)]
    for step in range(actions.shape[1]):
        state, _, _, fault = predict(state, actions[:, step], designs, member)
        path.append(state)
        faulted.append(faulted[-1] | fault.squeeze(-1))
    return torch.stack(path, 1).unflatten(0, (-1, samples)), torch.stack(faulted, 1).unflatten(0, (-1, samples))


def measures(truth: torch.Tensor, surrogate: torch.Tensor, bins: int) -> dict[str, torch.Tensor]:
    """JSD and mean and median relative error of the base's x and vx, each ``[101, 2]``."""
    columns = list(COLUMNS)
    truth, surrogate = truth[..., columns], surrogate[..., columns]
    return {"jsd": jensen_shannon(truth, surrogate, bins),
            "mean": relative_error(truth, surrogate, THESIS_FLOOR),
            "median": relative_error(truth, surrogate, THESIS_FLOOR, statistic="median")}


def table(title: str, rows: dict[str, dict[str, torch.Tensor]], cell) -> None:
    """One markdown table: a row per (model, prediction), x then vx at each horizon."""
    print(f"\n{title}")
    head = " | ".join(f"{name} {h}" for name in COLUMNS.values() for h in HORIZONS)
    print(f"| model, prediction | {head} |")
    print("|---" * (1 + len(COLUMNS) * len(HORIZONS)) + "|")
    for label, figures in rows.items():
        print(f"| {label} | " + " | ".join(cell(figures, h, c) for c in range(len(COLUMNS)) for h in HORIZONS) + " |")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--episodes", type=int, default=200, help="real random-action episodes (80%% fit)")
    parser.add_argument("--samples", type=int, default=10, help="rollouts per held-out episode and model")
    parser.add_argument("--bins", type=int, default=10, help="JSD histogram bins")
    parser.add_argument("--max-epochs", type=int, default=10, help="cap on the ensemble's epochs (yaml: 30)")
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--quick", action="store_true", help="100 episodes, 5 samples, 5 ensemble epochs")
    parser.add_argument("--figure", type=Path,
                        help=f"where to write the figure (default: {FIGURE.relative_to(ROOT)}; "
                             f"with --quick: {QUICK_FIGURE.relative_to(ROOT)})")
    args = parser.parse_args()
    if args.quick:
        args.episodes, args.samples, args.max_epochs = 100, 5, 5
    if args.figure is None:
        args.figure = QUICK_FIGURE if args.quick else FIGURE
    torch.set_num_threads(args.threads)

    rate = raw_pybullet(1000 if args.quick else 3000)[0]
    print(f"raw PyBullet loop: {rate:.0f} actions/s")
    data = collect(args.episodes, "random", args.seed)
    fit_episodes, held_out = split(data["episodes"])
    print(f"real data: {args.episodes} random-action SE episodes, collected at {data['actions_per_second']:.0f} "
          f"actions/s (cached in /tmp after the first run); {fit_episodes.batch_size[0]} to fit, "
          f"{held_out.batch_size[0]} held out without a physics fault")

    layout = StateLayout.for_env(RobotSettings(), "thesis", False, "full")
    truth = trajectories(layout, held_out)
    actions, designs = held_out["action"].clamp(-1.0, 1.0), held_out["design"][:, 0]
    # The JSD's floor: real fitting episodes, regrouped as "samples" of the held-out ones.
    group = min(args.samples, fit_episodes.batch_size[0] // truth.shape[0])
    real = trajectories(layout, fit_episodes[: group * truth.shape[0]]).unflatten(0, (group, -1)).transpose(0, 1)
    rows = {f"real vs real ({group} x {truth.shape[0]} fit episodes)": measures(truth, real, args.bins)}
    plotted, faults = {}, {}
    for name, world_model in MODELS.items():
        torch.manual_seed(args.seed)
        model, trainer = configured(world_model, args.threads, args.max_epochs)
        report = trainer.fit(model, transitions(fit_episodes, layout.from_full),
                             torch.Generator().manual_seed(args.seed))
        print(f"{name} (world_model={world_model}): {model.__class__.__name__}, {model.members} members; fit "
              f"{report.epochs} epoch(s) in {report.seconds:.1f} s, validation MSE (standardised) of the elites "
              f"{report.as_metrics()[MODEL_VALIDATION_MSE]:.3f}")
        generator = torch.Generator().manual_seed(args.seed)
        for mode in ("sampled", "deterministic"):
            started = time.perf_counter()
            rolled, faulted = rollouts(model, truth[:, 0], actions, designs, args.samples, mode == "deterministic",
                                       generator)
            print(f"  {mode}: {rolled.shape[0] * rolled.shape[1]} open-loop rollouts of {actions.shape[1]} steps "
                  f"in {time.perf_counter() - started:.1f} s")
            rows[f"{name}, {mode}"] = measures(truth, rolled, args.bins)
            faults[f"{name}, {mode}"] = faulted.flatten(0, 1).float().mean(0)
            if mode == "sampled":
                plotted[f"{name} ({world_model}), sampled"] = rolled[..., list(COLUMNS)]

    print(f"\n{truth.shape[0]} held-out episodes x {args.samples} rollouts per model; figures at step k of the "
          f"open-loop rollout ({PhysicsSettings().control_period:.4f} s per step)")
    table(f"Jensen-Shannon divergence (bits, {args.bins} bins of equal mixture mass)", rows,
          lambda f, h, c: f"{float(f['jsd'][h, c]):.3f}")
    models = {label: figures for label, figures in rows.items() if not label.startswith("real")}
    table("Mean relative error (median), floors 1 cm and 1 cm/s", models,
          lambda f, h, c: f"{float(f['mean'][h, c]):.2f} ({float(f['median'][h, c]):.2f})")
    print("\nShare of rollouts with a fault (a prediction non-finite or past the explosion limit) by step k")
    print("| model, prediction | " + " | ".join(map(str, HORIZONS)) + " |\n" + "|---" * (1 + len(HORIZONS)) + "|")
    for label, share in faults.items():
        print(f"| {label} | " + " | ".join(f"{float(share[h]):.2f}" for h in HORIZONS) + " |")
    path = plot_bands(truth[..., list(COLUMNS)], plotted, {0: "base x (m)", 1: "base vx (m/s)"}, args.figure,
                      seconds_per_step=PhysicsSettings().control_period, marks=[TRAINING_HORIZON],
                      title=f"{truth.shape[0]} held-out random-action episodes, open loop from the real start state\n"
                            f"{args.samples} sampled rollouts each (dotted: {TRAINING_HORIZON} steps)")
    print(f"\nfigure: {path} ({path.stat().st_size / 1000:.0f} kB)")
    pce, moe = (rows[f"{name}, sampled"]["mean"][TRAINING_HORIZON, 0] for name in MODELS)
    print(f"mean relative error of x at {TRAINING_HORIZON} steps, sampled: one-step PCE / ensemble = "
          f"{float(pce):.2f} / {float(moe):.2f} = {float(pce / moe):.2f}")


if __name__ == "__main__":
    main()
