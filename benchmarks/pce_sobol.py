"""Which inputs drive which outputs of the one-step PCE world model: Sobol' indices from its coefficients.

    python benchmarks/pce_sobol.py [--episodes 64] [--world-model pce] [--top 3] [--outputs base,joints]

Fits ``world_model=<world-model>`` (``pce``: the default one-step PCE; ``pce_sparse``: the
adaptive sparse one) as its yaml and trainer say, on ``--episodes`` real gait-plus-noise SE
episodes (``world_model_setup.collect``: cached, the same data the other world-model
benchmarks fit on), then reads first-order (S) and total (ST) Sobol' indices of each
output's one-step change from member 0's coefficients
(:meth:`~unipolicy_rl.world_models.PCEDynamics.sobol_indices`): no sampling, free once fitted.

Inputs: the translation-invariant state features (``rel.`` where the base's x, y is subtracted),
the actions (named by the joint they drive) and the design (l, rho). The indices are the fitted
expansion's under its input measure, every input independent and uniform on its training range,
not the correlated law of a walking robot's states: they say what the fitted function responds
to over the box of its data.

Per output (``--outputs``: ``base`` the base's six numbers, ``joints`` the actuated joints'
angles and rates, ``all`` every state column) it prints the standard deviation of the
predicted change under that measure, the ``--top`` inputs by total index with their
first-order index, and the variance split: the first-order shares of the state features, the
actions and the design, and the interactions' share (the four sum to 1). The last line is
``design_total_max: <largest total index of l or rho over the printed outputs>``.
One thread.
"""

from __future__ import annotations

import argparse
import time

import torch
import world_model_setup as setup

from unipolicy_rl.envs import RobotSettings
from unipolicy_rl.envs.simulation import Design
from unipolicy_rl.world_models import StateLayout


def names_of(robot: RobotSettings, layout: StateLayout, model) -> tuple[list[str], list[str]]:
    """(output names, input names) with the robot's link and joint names in place of indices."""
    links = [link.name for link in robot.describe(Design(0.175, 0.5)).links]
    bodies = ("base", *links[1:]) if len(links) == layout.num_bodies else None

    def named(name: str) -> str:
        for j, joint in enumerate(robot.actuated):
            name = name.replace(f"joint{j}.", f"{joint}.").replace(f"action{j}", f"action.{joint}")
        return name

    return ([named(n) for n in layout.state_names(bodies)],
            [named(n) for n in model.input_names(bodies)])


def chosen_outputs(which: str, layout: StateLayout) -> list[int]:
    base = list(range(6))
    joints = list(range(layout.robot_size - layout.num_joint_values, layout.robot_size))
    return {"base": base, "joints": joints, "base,joints": base + joints,
            "all": list(range(layout.robot_size))}[which]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--episodes", type=int, default=64, help="real gait-plus-noise SE episodes (100 steps each)")
    parser.add_argument("--world-model", default="pce", choices=("pce", "pce_sparse"))
    parser.add_argument("--top", type=int, default=3, help="inputs listed per output, by total index")
    parser.add_argument("--outputs", default="base,joints", choices=("base", "joints", "base,joints", "all"))
    parser.add_argument("--member", type=int, default=0)
    args = parser.parse_args()
    torch.set_num_threads(1)
    torch.manual_seed(0)

    collection = setup.collect(args.episodes)
    model, trainer = setup.configured(args.world_model)
    data = collection.transitions(model.layout.from_full)
    report = trainer.fit(model, data, torch.Generator().manual_seed(0))
    started = time.perf_counter()
    indices = model.sobol_indices(args.member)
    seconds = time.perf_counter() - started
    outputs, inputs = names_of(RobotSettings(), model.layout, model)
    features = model.layout.feature_size
    actions = len(inputs) - features - 2
    groups = {"state": slice(0, features), "actions": slice(features, features + actions),
              "design": slice(features + actions, None)}

    print(f"world_model={args.world_model}: {type(model).__name__}, {len(inputs)} inputs, "
          f"{int(model.fitted_terms)} of {model.terms} terms fitted, on {data.shape[0]} real transitions "
          f"({args.episodes} episodes{', cached' if collection.cached else ''}); fit {report.seconds:.1f} s, "
          f"validation error {float(report.validation_error.mean()):.3f} (standardised MSE); "
          f"indices of member {args.member} in {seconds * 1e3:.1f} ms")
    header = (f"{'output (change of)':24s} {'std':>9s}  {f'top {args.top} inputs: ST (S)':60s} "
              f"{'S state':>8s} {'S act':>6s} {'S l,rho':>8s} {'inter':>6s}")
    print(header)
    design_total = []
    for o in chosen_outputs(args.outputs, model.layout):
        total, first = indices.total[o], indices.first[o]
        top = torch.argsort(total, descending=True)[: args.top]
        listed = ", ".join(f"{inputs[i]} {float(total[i]):.2f} ({float(first[i]):.2f})" for i in top)
        shares = [float(first[part].sum()) for part in groups.values()]
        design_total.append(float(total[groups["design"]].max()))
        print(f"{outputs[o]:24s} {float(indices.variance[o]) ** 0.5:9.2e}  {listed:60s} "
              f"{shares[0]:8.2f} {shares[1]:6.2f} {shares[2]:8.2f} {float(indices.interaction[o]):6.2f}")
    print("ST: total Sobol' index (every term with the input), S: first-order (the input alone); "
          "S state/act/l,rho: first-order shares of each group; inter: the interactions' share")
    print(f"design_total_max: {max(design_total):.3f}")


if __name__ == "__main__":
    main()
