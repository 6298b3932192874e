"""PCE fit time at the thesis' size, against chaospy, and PCE accuracy over the horizon.

    python benchmarks/pce_fit.py [--episodes 3000] [--ensemble-epochs 10]

1. Fit time of the thesis-faithful ME-PCE (order 3, 7 x 7 elements, T = 3 actions of 4:
   14 inputs, 680 terms) for all 100 steps of an episode, 18 outputs (the thesis
   observation), at 1,020 episodes per element (1.5 x the terms; 49,980 episodes): a sample
   of that size would take hours of physics here, so this timing uses uniform designs and
   actions with random targets (the cost does not depend on the values). chaospy's
   regression (``fit_regression``) is timed on one (element, step) problem of the same size
   and scaled by the 4,900 problems.
2. Accuracy on real SE episodes with uniform random actions (benchmarks/pce_data.py, cached
   in /tmp): held-out episodes, base forward position x and velocity vx, mean relative error
   with the thesis' floors (1 cm, 1 cm/s), at 0.4 s (6 steps), 10, 25 and 100 steps:
   the thesis' ME-PCE (what the real sample can determine: order 3 in one element; order 2
   in 2 x 2) next to the one-step PCE (world_model=pce) and the default ensemble
   (world_model=moe, its fit capped at ``--ensemble-epochs``), both rolled out open loop from
   the real start state with the real actions, with each one's mean prediction (member 0 of
   the PCE, the best elite of the ensemble).
3. The thesis' figure 6.5 as a heatmap (``--sweep``): the thesis' ME-PCE over (order,
   divisions per design axis) on the same real data, mean relative error of vx and x at 0.4 s
   (6 steps); a cell is blank where an element gets fewer episodes than terms (the fit would
   be underdetermined). Written to ``docs/figures/pce_order_divisions.png``.
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
from unipolicy_rl.envs import RobotSettings
from unipolicy_rl.envs.design import SE_DENSITY_RANGE, SE_LENGTH_RANGE
from unipolicy_rl.evaluation.accuracy import THESIS_FLOOR, relative_error
from unipolicy_rl.polynomial_chaos import ThesisMEPCE
from unipolicy_rl.world_models import StateLayout

RANGES = (SE_LENGTH_RANGE, SE_DENSITY_RANGE)
STEPS = (6, 10, 25, 100)


def timing(threads: int) -> None:
    torch.set_num_threads(threads)
    per_element, elements, horizon = 1020, 49, 100
    n = per_element * elements
    g = torch.Generator().manual_seed(0)
    cell = torch.arange(elements).repeat_interleave(per_element)
    u = (torch.stack([cell // 7, cell % 7], -1) + torch.rand(n, 2, generator=g)) / 7
    low, high = torch.tensor([r[0] for r in RANGES]), torch.tensor([r[1] for r in RANGES])
    design = low + (high - low) * u
    actions = torch.rand(n, horizon, 4, generator=g) * 2 - 1
    states = torch.randn(n, horizon, 18, generator=g)
    pce = ThesisMEPCE(*RANGES, order=3, divisions=7, window=3)
    report = pce.fit(design, actions, states)
    print(f"thesis ME-PCE fit, 680 terms x 49 elements x 100 steps x 18 outputs, {n} episodes, {threads} threads: "
          f"{report['seconds']:.1f} s (target 60 s), max condition estimate {report['max_condition']:.1f}")
    try:
        import chaospy
        import numpy as np
    except ImportError:
        print("chaospy not installed (pip install -e .[bench]): no comparison")
        return
    joint = chaospy.J(*[chaospy.Uniform(-1, 1) for _ in range(14)])  # 14 independent variables
    started = time.perf_counter()
    expansion = chaospy.generate_expansion(3, joint, normed=True)
    built = time.perf_counter() - started
    x = np.random.default_rng(0).uniform(-1, 1, (14, per_element))
    y = np.random.default_rng(1).normal(size=(per_element, 18))
    started = time.perf_counter()
    chaospy.fit_regression(expansion, x, y)
    one = time.perf_counter() - started
    print(f"chaospy fit_regression, one (element, step) of the same size: {one:.2f} s (+{built:.1f} s to build the "
          f"expansion once); x 4,900 problems = {one * 4900:.0f} s, {one * 4900 / report['seconds']:.0f}x ours")


def open_loop(model, state: torch.Tensor, actions: torch.Tensor, designs: torch.Tensor, member: int) -> torch.Tensor:
    """``[E, H, S]``: ``model``'s mean prediction stepped from ``state`` with the real actions."""
    members = torch.full((state.shape[0],), member, dtype=torch.long)
    rolled = []
    for k in range(actions.shape[1]):
        state = model.predict(state, actions[:, k], designs[:, k], members, deterministic=True)
        rolled.append(state)
    return torch.stack(rolled, 1)


def accuracy(episodes: int, ensemble_epochs: int) -> None:
    torch.set_num_threads(2)
    data = collect(episodes, "random")
    print(f"real data: {episodes} random-action SE episodes, collected at {data['actions_per_second']:.0f} actions/s")
    ep = data["episodes"]
    ep = ep[~ep["next", "physics_fault"].squeeze(-1).any(1)]
    split = int(0.8 * ep.batch_size[0])
    train, test = ep[:split], ep[split:]
    thesis = StateLayout.for_env(RobotSettings(), "thesis", False, "thesis")
    full = StateLayout.for_env(RobotSettings(), "thesis", False, "full")
    truth = test["next", "state"]
    results = {}
    for label, kw in (("ME-PCE order 3, 1x1, T=3 (680 terms)", dict(order=3, divisions=1)),
                      ("ME-PCE order 2, 2x2, T=3 (120 terms)", dict(order=2, divisions=2))):
        pce = ThesisMEPCE(*RANGES, window=3, **kw)
        try:
            report = pce.fit(train["design"][:, 0], train["action"], thesis.from_full(train["next", "state"]))
        except ValueError as error:  # underdetermined: fewer episodes per element than terms
            print(f"{label}: {str(error).split(';')[0]}")
            continue
        predicted = pce.predict(test["design"][:, 0], test["action"])
        results[label] = (predicted[..., 0], predicted[..., 3], report["seconds"])
    start = full.from_full(test["state"][:, 0])
    for label, world_model in (("one-step PCE", "pce"), ("ensemble", "moe")):
        model, trainer = configured(world_model, threads=2, max_epochs=ensemble_epochs)
        fit = trainer.fit(model, transitions(train, full.from_full), torch.Generator().manual_seed(0))
        best = int(fit.elites[int(torch.argmin(fit.validation_error[fit.elites]))])
        rolled = open_loop(model, start, test["action"], test["design"], best)
        size = f"{model.terms} terms" if world_model == "pce" else f"{model.members} members, {fit.epochs} epochs"
        results[f"{label} ({size}), open loop"] = (rolled[..., 0], rolled[..., 3], fit.seconds)
    print(f"{len(test)} held-out episodes; mean relative error at step " + ", ".join(map(str, STEPS)))
    print("| model | fit s | x: " + " | ".join(f"{s}" for s in STEPS) + " | vx: " +
          " | ".join(f"{s}" for s in STEPS) + " |")
    for label, (x, vx, seconds) in results.items():
        ex, ev = relative_error(truth[..., [0, 3]], torch.stack([x, vx], -1), THESIS_FLOOR).unbind(-1)
        print(f"| {label} | {seconds:.1f} | " + " | ".join(f"{float(ex[s - 1]):.2f}" for s in STEPS) + " | " +
              " | ".join(f"{float(ev[s - 1]):.2f}" for s in STEPS) + " |")


SWEEP_ORDERS = (1, 2, 3)
SWEEP_DIVISIONS = (1, 2, 3, 4, 5, 7)
SWEEP_STEP = 6  # 0.4 s, the thesis' figure


def order_divisions_sweep(episodes: int, out: Path) -> None:
    """Thesis fig. 6.5: error at 0.4 s of the thesis' ME-PCE over (order, divisions), as a heatmap."""
    import math

    import numpy as np
    from matplotlib.figure import Figure

    data = collect(episodes, "random")
    ep = data["episodes"]
    ep = ep[~ep["next", "physics_fault"].squeeze(-1).any(1)]
    split = int(0.8 * ep.batch_size[0])
    train, test = ep[:split], ep[split:]
    thesis = StateLayout.for_env(RobotSettings(), "thesis", False, "thesis")
    truth = test["next", "state"][:, :SWEEP_STEP][..., [0, 3]]
    errors = np.full((2, len(SWEEP_ORDERS), len(SWEEP_DIVISIONS)), math.nan)
    print(f"order x divisions: mean relative error of (x, vx) at step {SWEEP_STEP}, {len(test)} held-out episodes")
    for i, order in enumerate(SWEEP_ORDERS):
        for j, divisions in enumerate(SWEEP_DIVISIONS):
            pce = ThesisMEPCE(*RANGES, order=order, divisions=divisions, window=3)
            try:
                pce.fit(train["design"][:, 0], train["action"], thesis.from_full(train["next", "state"]))
            except ValueError as error:  # underdetermined: fewer episodes per element than terms
                print(f"order {order}, {divisions}x{divisions}: {str(error).split(';')[0]}")
                continue
            predicted = pce.predict(test["design"][:, 0], test["action"])[:, :SWEEP_STEP][..., [0, 3]]
            errors[:, i, j] = relative_error(truth, predicted, THESIS_FLOOR)[SWEEP_STEP - 1].numpy()
            print(f"order {order}, {divisions}x{divisions} ({pce.terms} terms): x {errors[0, i, j]:.3f}, "
                  f"vx {errors[1, i, j]:.3f}")
    figure = Figure(figsize=(9, 3.4), layout="constrained")
    for axis, values, name in zip(figure.subplots(1, 2), errors, ("base x", "base vx"), strict=True):
        image = axis.imshow(values, cmap="viridis_r", aspect="auto")
        axis.set_xticks(range(len(SWEEP_DIVISIONS)), [f"{d}x{d}" for d in SWEEP_DIVISIONS])
        axis.set_yticks(range(len(SWEEP_ORDERS)), [str(o) for o in SWEEP_ORDERS])
        axis.set_xlabel("elements (divisions per design axis)")
        axis.set_ylabel("order")
        axis.set_title(f"{name}: relative error at {SWEEP_STEP} steps (0.4 s)")
        for (row, col), value in np.ndenumerate(values):
            axis.text(col, row, "n/a" if math.isnan(value) else f"{value:.2f}", ha="center", va="center",
                      color="white" if value > np.nanmean(values) else "black", fontsize=8)
        figure.colorbar(image, ax=axis)
    figure.savefig(out, dpi=110)
    print(f"wrote {out} (n/a: fewer episodes per element than terms)")


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--episodes", type=int, default=3000)
    parser.add_argument("--skip-timing", action="store_true")
    parser.add_argument("--skip-accuracy", action="store_true")
    parser.add_argument("--ensemble-epochs", type=int, default=10,
                        help="cap on the ensemble's fit in the accuracy table (its yaml allows 30)")
    parser.add_argument("--sweep", action="store_true", help="also the order x divisions heatmap (thesis fig. 6.5)")
    parser.add_argument("--sweep-out", type=Path,
                        default=Path(__file__).resolve().parents[1] / "docs" / "figures" / "pce_order_divisions.png")
    args = parser.parse_args()
    rate = raw_pybullet(3000)[0]
    print(f"raw PyBullet loop: {rate:.0f} actions/s")
    if not args.skip_timing:
        timing(2)
    if not args.skip_accuracy:
        accuracy(args.episodes, args.ensemble_epochs)
    if args.sweep:
        order_divisions_sweep(args.episodes, args.sweep_out)


if __name__ == "__main__":
    main()
