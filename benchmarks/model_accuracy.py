"""World-model accuracy on held-out real episodes: one step and 25 steps open loop.

    python benchmarks/model_accuracy.py [--train-episodes 300] [--test-episodes 60] [--horizons 1 8 25]

Data: SE robots walking the open-loop gait plus Gaussian noise (``world_model_setup.py``),
100-step episodes; the first ``--train-episodes`` fit the models, the last ``--test-episodes``
are held out (an episode with a physics fault is dropped from them). Models, each fitted by
its yaml's trainer (the ensembles' ``max_epochs`` raised to ``--max-epochs`` so early
stopping ends the fit), one thread (accuracy does not depend on it):

* ``moe``: the default ``GaussianEnsemble`` predicting the full state (``world_model=moe``);
* ``moe, thesis state``: the same ensemble predicting only the thesis' 18-number observation
  (``world_model=moe world_model.model_state=thesis``);
* ``moe_thesis``: the thesis' ``CellEnsemble`` (6 x 6 cells, position and velocity networks);
* ``pce``: the one-step PCE of ``world_model=pce`` (``PCEDynamics``, fitted by ``ClosedFormTrainer``).

Predictions run open loop from every real state of a held-out episode, feeding the recorded
actions, with a member drawn per trajectory as imagination draws it and the imagined env's
fault rule (:class:`PredictNextState`: a non-finite or exploded prediction keeps the last
state), ``deterministic`` (the members' means) and sampled (with the Gaussian ensembles'
predicted noise, the PCE's residual noise). For each k of ``--horizons`` (1 step; 8, the
longest branch ``world_model=pce`` trains on; 25, the ensemble's), over the held-out episodes:

* NMD, the thesis' normalised mean difference (eq. 5.3): per target time step and per number
  of the policy's 18-number observation, |mean of predictions - mean of data| / |mean of data|
  over the episodes, averaged over the 18 numbers and the time steps (and its median, since
  a number whose mean is near zero makes the average large, as the thesis notes);
* the mean relative error of the base's forward position x (column 0) and velocity x_dot
  (column 3), |pred - true| / max(|true|, floor), floors 1 cm and 1 cm/s (thesis eq. 5.2),
  with the mean absolute errors in cm and cm/s beside them.

The figure (``--figure``, default ``docs/figures/model_accuracy.png``): base x and x_dot over
the held-out episodes from their start, data mean and 95% band (2.5-97.5 percentiles over
episodes) against each model's open-loop rollout over the whole episode from the real start
state (sampled, as imagination runs it), with the longest horizon's step marked.
The last lines are the headline ratios of the longest horizon's relative error of x,
deterministic predictions: ``moe_thesis / moe`` and ``moe (thesis state) / moe``, and the
PCE's relative errors at 8 steps (the PCE's target: at most 0.1 over the horizon training uses).
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import matplotlib
import torch
import world_model_setup as setup
from env_throughput import raw_pybullet

from unipolicy_rl.collectors import transitions
from unipolicy_rl.envs import PhysicsSettings, RobotSettings
from unipolicy_rl.evaluation.accuracy import THESIS_FLOOR, normalised_mean_difference, relative_error
from unipolicy_rl.world_models import StateLayout
from unipolicy_rl.world_models.imagined import PredictNextState

matplotlib.use("Agg")
from matplotlib import pyplot as plt  # noqa: E402 (after choosing the backend)

ROOT = Path(__file__).resolve().parent.parent
X, X_DOT = 0, 3  # base forward position and velocity in the observation
FLOORS = {X: THESIS_FLOOR, X_DOT: THESIS_FLOOR}  # 1 cm, 1 cm/s


def open_loop(model, states: torch.Tensor, actions: torch.Tensor, designs: torch.Tensor, steps: int,
              deterministic: bool, generator: torch.Generator) -> tuple[torch.Tensor, int]:
    """``steps`` predictions from ``states`` ``[B, S]`` fed ``actions`` ``[B, steps, 4]``:
    ``[B, steps, S]`` and the number of faulted predictions (kept at the last state)."""
    predict = PredictNextState(model, deterministic=deterministic)
    member = model.draw_members(designs, generator).unsqueeze(-1)
    state, path, faults = states, [], 0
    for step in range(steps):
        state, _, _, fault = predict(state, actions[:, step], designs, member)
        faults += int(fault.sum())
        path.append(state)
    return torch.stack(path, 1), faults


def predict_ahead(model, states: torch.Tensor, actions: torch.Tensor, designs: torch.Tensor, ahead: int,
                  deterministic: bool, generator: torch.Generator) -> tuple[torch.Tensor, int]:
    """The state ``ahead`` steps after every real state that has ``ahead`` recorded actions
    after it, open loop: ``[E, 101 - ahead, S]`` (targets at times ``ahead``..100), and the faults."""
    episodes, length = actions.shape[:2]
    starts = length + 1 - ahead
    window = torch.arange(ahead)[None] + torch.arange(starts)[:, None]  # [starts, ahead] action indices
    path, faults = open_loop(model, states[:, :starts].reshape(-1, states.shape[-1]),
                             actions[:, window].reshape(-1, ahead, actions.shape[-1]),
                             designs.repeat_interleave(starts, 0), ahead, deterministic, generator)
    return path[:, -1].reshape(episodes, starts, -1), faults


def episodes_of(layout: StateLayout, data) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """(states ``[E, 101, S]`` in the model's layout, actions ``[E, 100, 4]``, designs ``[E, 2]``)."""
    states = torch.cat([data["state"], data["next", "state"][:, -1:]], 1)
    return layout.from_full(states), data["action"].clamp(-1.0, 1.0), data["design"][:, 0]


def metrics(layout: StateLayout, predicted: torch.Tensor, true: torch.Tensor, design: torch.Tensor) -> dict:
    """NMD and relative errors of ``predicted`` against ``true`` (``[E, T, S]`` model states)."""
    design = design[:, None].expand(-1, true.shape[1], -1)
    predicted, true = layout.observation(predicted, design), layout.observation(true, design)
    nmd = normalised_mean_difference(true, predicted)
    out = {"nmd": float(nmd.mean()), "nmd_median": float(nmd.median())}
    for name, column in (("x", X), ("x_dot", X_DOT)):
        error = (predicted[..., column] - true[..., column]).abs()
        # Every step has the same episodes, so the mean of the per-step means is the overall mean.
        out[f"relative_{name}"] = float(relative_error(true[..., [column]], predicted[..., [column]],
                                                       FLOORS[column]).mean())
        out[f"absolute_{name}"] = float(error.mean()) * 100
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--train-episodes", type=int, default=300)
    parser.add_argument("--test-episodes", type=int, default=60)
    parser.add_argument("--horizons", type=int, nargs="+", default=[1, 8, 25], help="open-loop steps ahead")
    parser.add_argument("--max-epochs", type=int, default=200, help="cap on epochs (early stopping ends the fit first)")
    parser.add_argument("--noise", type=float, default=0.3, help="std of the Gaussian noise on the gait's actions")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--figure", default=str(ROOT / "docs" / "figures" / "model_accuracy.png"))
    args = parser.parse_args()
    torch.set_num_threads(1)

    raw, _ = raw_pybullet(2000)
    collection = setup.collect(args.train_episodes + args.test_episodes, args.noise, args.seed)
    train = collection.episodes[: args.train_episodes]
    test = collection.episodes[args.train_episodes:]
    test = test[~test["next", "physics_fault"].any(-2).squeeze(-1)]
    print(f"raw PyBullet loop, one core: {raw:.0f} actions/s")
    cached = " (cached from an earlier run)" if collection.cached else ""
    print(f"collection: {collection.episodes.shape[0]} episodes in {collection.seconds:.1f} s at "
          f"{collection.actions_per_second:.0f} actions/s{cached}; {train.shape[0]} to fit, {test.shape[0]} held out "
          "without a physics fault")

    thesis = StateLayout.for_env(RobotSettings(), "thesis", False, "thesis")
    candidates = {
        "moe": (lambda: setup.make_model("moe"), "moe"),
        "moe, thesis state": (lambda: setup.make_model("moe", model_state="thesis"), "moe"),
        "moe_thesis": (lambda: setup.make_model("moe_thesis"), "moe_thesis"),
        "pce": (lambda: setup.make_model("pce"), "pce"),
    }
    generator = torch.Generator().manual_seed(args.seed)
    horizons = sorted(set(args.horizons))
    k = horizons[-1]
    true_states, _, test_designs = episodes_of(thesis, test)
    plotted = {"data": thesis.observation(true_states, test_designs[:, None].expand(-1, true_states.shape[1], -1))}
    rows, headline = [], {}
    for name, (build, config) in candidates.items():
        torch.manual_seed(args.seed)
        model = build()
        trainer = setup.make_trainer(config, threads=1, max_epochs=args.max_epochs)
        report = trainer.fit(model, transitions(train, model.layout.from_full),
                             torch.Generator().manual_seed(args.seed))
        finite = report.validation_error[torch.isfinite(report.validation_error)]
        print(f"{name}: {model.__class__.__name__}, {model.members} members, {model.layout.size}-number state; fit "
              f"{report.epochs} epochs in {report.seconds:.1f} s, validation MSE (standardised) median "
              f"{finite.median():.4f}")
        states, actions, designs = episodes_of(model.layout, test)
        for deterministic in (True, False):
            if not deterministic and name == "moe_thesis":
                continue  # the thesis' networks are deterministic: sampling changes nothing
            mode = "deterministic" if deterministic else "sampled"
            for ahead in horizons:
                started = time.perf_counter()
                predicted, faults = predict_ahead(model, states, actions, designs, ahead, deterministic, generator)
                result = metrics(model.layout, predicted, states[:, ahead:], designs)
                rows.append((name, mode, ahead, result, faults))
                print(f"  {mode}, {ahead} step(s) ahead: {predicted.shape[0] * predicted.shape[1]} open-loop "
                      f"rollouts in {time.perf_counter() - started:.1f} s, {faults} faulted predictions")
                if deterministic:
                    headline[name, ahead] = result
        whole, _ = open_loop(model, states[:, 0], actions, designs, actions.shape[1], False, generator)
        plotted[name] = model.layout.observation(whole, designs[:, None].expand(-1, whole.shape[1], -1))

    print(f"{'model':20s} {'prediction':14s} {'k':>3s} {'NMD (median)':>14s} {'rel. err x':>11s} "
          f"{'rel. err x_dot':>15s} {'|err| x cm':>11s} {'|err| x_dot cm/s':>17s} {'faults':>7s}")
    for name, mode, ahead, result, faults in rows:
        print(f"{name:20s} {mode:14s} {ahead:3d} {result['nmd']:6.3f} ({result['nmd_median']:.3f}) "
              f"{result['relative_x']:11.3f} {result['relative_x_dot']:15.3f} {result['absolute_x']:11.2f} "
              f"{result['absolute_x_dot']:17.2f} {faults:7d}")
    plot(plotted, k, args.figure)
    print(f"figure: {args.figure} ({Path(args.figure).stat().st_size / 1000:.0f} kB)")
    x = {name: headline[name, k]["relative_x"] for name in candidates}
    print(f"{k}-step relative error of x, deterministic: moe_thesis / moe: "
          f"{x['moe_thesis']:.3f} / {x['moe']:.3f} = {x['moe_thesis'] / x['moe']:.2f}")
    print(f"{k}-step relative error of x, deterministic: moe (thesis state) / moe: "
          f"{x['moe, thesis state']:.3f} / {x['moe']:.3f} = {x['moe, thesis state'] / x['moe']:.2f}")
    print(f"{k}-step relative error of x, deterministic: pce / moe: {x['pce']:.3f} / {x['moe']:.3f} = "
          f"{x['pce'] / x['moe']:.2f}")
    for ahead in (h for h in horizons if h != k):
        pce = headline["pce", ahead]
        print(f"pce, {ahead} steps, deterministic: relative error x {pce['relative_x']:.3f}, "
              f"x_dot {pce['relative_x_dot']:.3f} (target 0.1)")
    print(f"model_accuracy_ratio: {x['moe_thesis'] / x['moe']:.2f}")


def plot(series: dict[str, torch.Tensor], horizon: int, path: str) -> None:
    """Base x and x_dot from the episodes' start: data against each model's open-loop rollout."""
    data = series["data"]
    seconds = torch.arange(data.shape[1]) * PhysicsSettings().control_period
    models = [name for name in series if name != "data"]
    figure, axes = plt.subplots(2, len(models), figsize=(4 * len(models), 5.4), sharex=True, sharey="row",
                                squeeze=False)
    for column, name in enumerate(models):
        # The model's rollout starts at the real start state: put that state in front of it.
        predicted = torch.cat([data[:, :1], series[name]], 1)
        for row, (index, label) in enumerate(((X, "base x (m)"), (X_DOT, "base x_dot (m/s)"))):
            axis = axes[row, column]
            for values, colour, legend in ((data, "0.4", "data"), (predicted, f"C{column}", name)):
                band = torch.quantile(values[..., index], torch.tensor([0.025, 0.975]), dim=0)
                axis.fill_between(seconds, band[0], band[1], color=colour, alpha=0.25, linewidth=0)
                axis.plot(seconds, values[..., index].mean(0), color=colour, label=f"{legend}: mean, 95% band")
            low, high = torch.quantile(data[..., index], torch.tensor([0.025, 0.975]), dim=0)
            span = float(high.max() - low.min())
            axis.set_ylim(float(low.min()) - 0.5 * span, float(high.max()) + 0.5 * span)
            axis.axvline(float(seconds[horizon]), color="k", linestyle=":", linewidth=1)
            axis.set_ylabel(label if column == 0 else "")
            if row == 0:
                axis.set_title(name)
                axis.legend(loc="upper left", fontsize=7)
            else:
                axis.set_xlabel("time from the episode's start (s)")
    figure.suptitle(f"Held-out episodes ({data.shape[0]}): open loop from the real start state, sampled "
                    f"(dotted: {horizon} steps)", fontsize=10)
    figure.tight_layout()
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    figure.savefig(path, dpi=80)
    plt.close(figure)


if __name__ == "__main__":
    main()
