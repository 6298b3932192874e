"""World-model accuracy where training uses it: short branches from a run's own real states.

    python benchmarks/branch_accuracy.py <run dir or checkpoint.pt of a model-based run>
        [--fit-transitions 30000] [--test-transitions 10000] [--horizons 1 3 8 25] [--starts 2000]
        [--models pce moe]
    python benchmarks/branch_accuracy.py --episodes 64 --fit-transitions 4800 --test-transitions 1600 ...

``model_accuracy.py`` and ``surrogate_accuracy.py`` measure surrogates on episodes of a
scripted gait and of random actions, from the episode start. Training meets a surrogate
elsewhere: imagined branches of a few steps (``world_model=pce``: 3 growing to 8) start from
any real state in the replay buffer, and the actions are the policy's. This benchmark takes
that buffer from a model-based run's checkpoint (a walking policy's data: the robot is
metres from x = 0), fits the ``--models`` (world_model yamls: by default the one-step PCE and the
default ensemble; ``pce_sparse`` the adaptive sparse PCE) as their yamls say on the
``--fit-transitions`` real steps before the last ``--test-transitions`` (what a fit at that
point of the run saw), and rolls each out open loop from ``--starts`` held-out real states
with the recorded actions, ``k`` steps for each horizon (starts whose episode lasts ``k``
more steps), deterministic (each member's mean) and sampled (with the model's noise), a
member drawn per branch as imagination draws it.

Per horizon, over the branches: the mean relative error of the base's x and x_dot with the
thesis' floors (1 cm, 1 cm/s; eq. 5.2), the same for the branch's displacement x_k - x_0
(what the reward sums; the position itself flatters a robot far from the origin), the mean
absolute errors, and the share of predictions that faulted (non-finite or past the
explosion limit: the imagined env ends the branch there). For the deterministic branches also
whether the members' disagreement tells where the model is wrong: every voting member rolls
each branch out with its mean prediction, and Spearman's rank correlation is taken between the
members' spread (standard deviation) of the predicted displacement and the error of their mean
(``spread_rank_correlation``; 0: the spread says nothing, 1: it orders the branches by error).
One thread (accuracy does not depend on it).

A model in ``--models`` is a world_model yaml with settings of its ``world_model.model``:
``NAME[:key=value,...]`` (``pce:lags=1``, ``pce_sparse:order=4,tolerance=0.05``). A model with
memory columns (``lags``: PC-NARX) gets them from the buffer's own chain of steps
(:func:`in_model_view`), so its branches start with their real past. ``--episodes N`` takes the
N cached gait-plus-noise episodes of the other world-model benchmarks (``world_model_setup.py``)
instead of a run's buffer: cheap, but not a policy's data. A summary table closes the output:
per model, the one-step validation error, the fit time and the deterministic displacement error
at each horizon (and its ratio to ``moe``'s at 8 steps where ``moe`` is among the models).
``pce_selection.py`` ranks candidate settings with the same machinery.
"""

from __future__ import annotations

import argparse
import statistics
import time
from pathlib import Path

import torch
import world_model_setup as setup
from model_accuracy import open_loop
from tensordict import TensorDict

from unipolicy_rl.checkpoint import load_checkpoint
from unipolicy_rl.envs import RobotSettings
from unipolicy_rl.evaluation.accuracy import THESIS_FLOOR, relative_error
from unipolicy_rl.world_models import StateLayout
from unipolicy_rl.world_models.imagined import PredictNextState
from unipolicy_rl.world_models.trainer import EPISODE_START

X, X_DOT = 0, 3  # base forward position and velocity in the state


def buffer_of(path: Path) -> TensorDict:
    """The real transitions a model-based run's checkpoint carries, oldest first."""
    checkpoint = load_checkpoint(path / "checkpoint.pt" if path.is_dir() else path)
    # Today's checkpoints keep the buffer at the top; older ones kept it in the collector's state.
    buffer = checkpoint.get("replay_buffer") or (checkpoint.get("collector") or {}).get("buffer")
    if buffer is None:
        raise ValueError(f"{path} is not a model-based run's checkpoint (no replay buffer in it)")
    # The replay buffer's own state dict (TorchRL's ReplayBuffer.state_dict), read here rather
    # than loaded into a ReplayBuffer: the rows are wanted in the order they were written, which
    # only the writer's cursor gives, and TorchRL has no public accessor for it.
    storage = buffer["_storage"]
    rows, length = storage["_storage"], int(storage["_len"])
    writes = int(buffer["_writer"]["_write_count"])
    data = TensorDict({key: value[:length] for key, value in rows.items()}, batch_size=[length])
    if writes > length:  # the FIFO wrapped: the oldest row sits at the write cursor
        cursor = int(buffer["_writer"]["_cursor"])
        data = torch.cat([data[cursor:], data[:cursor]])
    return data


def in_model_view(model, rows: TensorDict) -> TensorDict:
    """``rows`` (real transitions, oldest first, the robot's state only) with ``model``'s memory
    columns appended to ``state`` and ``next_state`` (``model.memory_of`` on the rows as one long
    row whose episodes end where the chain of steps breaks; see :func:`branch_starts`); the rows
    themselves for a model without memory."""
    if model.layout.memory_size == 0:
        return rows
    broken = (rows["state"][1:] != rows["next_state"][:-1]).any(-1)
    if EPISODE_START in rows.keys():
        broken |= rows[EPISODE_START][1:].reshape(-1).bool()
    done = torch.cat([broken, torch.ones(1, dtype=torch.bool)]).reshape(1, -1, 1)
    chain = TensorDict({"state": rows["state"][None], "action": rows["action"][None],
                        ("next", "state"): rows["next_state"][None], ("next", "done"): done}, [1, len(rows)])
    before, after = model.memory_of(chain)
    viewed = rows.clone()
    viewed["state"] = torch.cat([rows["state"], before[0]], -1)
    viewed["next_state"] = torch.cat([rows["next_state"], after[0]], -1)
    return viewed


def real_data(run: Path | None, episodes: int | None) -> TensorDict:
    """A run's buffer, or ``episodes`` cached gait-plus-noise episodes as rows (oldest first)."""
    if (run is None) == (episodes is None):
        raise ValueError("give a run directory (or checkpoint) or --episodes, not both or neither")
    layout = StateLayout.for_env(RobotSettings(), "thesis", False, "full")
    data = buffer_of(run) if run is not None else setup.collect(episodes).transitions(layout.from_full)
    if data["state"].shape[-1] != layout.size:
        raise ValueError(f"the buffer's states have {data['state'].shape[-1]} numbers; this benchmark reads the "
                         f"full state ({layout.size}), the default world_model.model_state")
    return data


def add_data_arguments(parser: argparse.ArgumentParser) -> None:
    """The data and split arguments this benchmark and ``pce_selection.py`` share (:func:`real_data`,
    :func:`split`)."""
    parser.add_argument("run", type=Path, nargs="?", help="a model-based run's directory or its checkpoint.pt")
    parser.add_argument("--episodes", type=int, default=None,
                        help="instead of a run: this many cached gait-plus-noise episodes (world_model_setup.py)")
    parser.add_argument("--fit-transitions", type=int, default=30_000)
    parser.add_argument("--test-transitions", type=int, default=10_000)


def checked_data(args: argparse.Namespace, specs: list[str]) -> tuple[TensorDict, TensorDict, TensorDict]:
    """(all the rows, the fit part, the held-out part) the data arguments name, after every model
    spec is checked: a bad spec fails before the data load and any fit."""
    for spec in specs:
        setup.parse_model(spec)
    data = real_data(args.run, args.episodes)
    return data, *split(data, args.fit_transitions, args.test_transitions)


def split(data: TensorDict, fit_transitions: int, test_transitions: int) -> tuple[TensorDict, TensorDict]:
    """(the ``fit_transitions`` rows before the last ``test_transitions``, those last rows)."""
    if len(data) <= test_transitions:
        raise ValueError(f"the data hold {len(data)} transitions, not more than --test-transitions {test_transitions}")
    return data[max(0, len(data) - test_transitions - fit_transitions): len(data) - test_transitions], \
        data[-test_transitions:]


def fit_and_measure(spec: str, data: TensorDict, fit_transitions: int, test_transitions: int, horizons: list[int],
                    starts: int, seed: int, sampled: bool = True) -> tuple[object, dict]:
    """Fits model ``spec`` on ``data``'s fit part and measures it on the held-out part: (the fit
    report, ``{(deterministic, horizon): measure(...)}``)."""
    torch.manual_seed(seed)
    model, trainer = setup.configured_spec(spec, threads=1)
    fit, test = split(in_model_view(model, data), fit_transitions, test_transitions)
    report = trainer.fit(model, fit, torch.Generator().manual_seed(seed))
    print(f"{spec}: {model.__class__.__name__}, fit {report.epochs} epoch(s) in {report.seconds:.1f} s, "
          f"validation MSE (standardised) median {report.validation_error.median():.3f}, per member "
          f"{', '.join(f'{error:.3f}' for error in report.validation_error.tolist())}")
    results = {}
    for deterministic in (True, False) if sampled else (True,):
        for horizon in horizons:
            started = time.perf_counter()
            generator = torch.Generator().manual_seed(seed)
            results[deterministic, horizon] = measure(model, test, horizon, deterministic, starts, generator)
            print(f"  {'deterministic' if deterministic else 'sampled'}, {horizon} steps: "
                  f"{results[deterministic, horizon]['branches']} branches in {time.perf_counter() - started:.1f} s")
    return report, results


def summary_rows(reports: dict, results: dict, horizons: list[int], reference: str | None = "moe") -> list[str]:
    """The summary table's markdown lines: per model the one-step validation error (median of its
    members), the fit time and the deterministic displacement error per horizon (and the ratio
    to ``reference``'s at the longest horizon where ``reference`` is among the models)."""
    last = horizons[-1]
    ratio = reference in reports
    lines = ["| model | one-step validation error | fit s | "
             + " | ".join(f"rel. err. displacement, {k} steps" for k in horizons)
             + (f" | / {reference} at {last} |" if ratio else " |"),
             "|---|---|---|" + "---|" * len(horizons) + ("---|" if ratio else "")]
    for name, report in reports.items():
        errors = [results[name, True, k]["relative_displacement"] for k in horizons]
        line = (f"| {name} | {statistics.median(report.validation_error.tolist()):.3f} | {report.seconds:.1f} | "
                + " | ".join(f"{e:.3f}" for e in errors) + " |")
        if ratio:
            line += f" {errors[-1] / results[reference, True, last]['relative_displacement']:.2f} |"
        lines.append(line)
    return lines


def branch_starts(data: TensorDict, steps: int, count: int, generator: torch.Generator) -> torch.Tensor:
    """Up to ``count`` rows from which the buffer holds ``steps`` consecutive real steps: each
    row's next state is the following row's state (a new episode, or a faulted step the buffer
    left out, breaks the chain)."""
    broken = (data["state"][1:] != data["next_state"][:-1]).any(-1)
    breaks = torch.cat([torch.zeros(1, dtype=torch.long), torch.cumsum(broken.long(), 0)])
    rows = torch.arange(len(data) - steps + 1)
    valid = rows[breaks[rows + steps - 1] == breaks[rows]]
    return valid[torch.randperm(len(valid), generator=generator)[:count]]


def measure(model, test: TensorDict, horizon: int, deterministic: bool, starts: int, generator) -> dict[str, float]:
    rows = branch_starts(test, horizon, starts, generator)
    window = rows[:, None] + torch.arange(horizon)[None]
    start = test["state"][rows]
    path, faults = open_loop(model, start, test["action"][window], test["design"][rows], horizon, deterministic,
                             generator)
    predicted, true = path[:, -1], test["next_state"][rows + horizon - 1]
    columns = [X, X_DOT]
    # relative_error averages over its first axis (here the branches) per step (one: the branch's last).
    relative = relative_error(true[:, None, columns], predicted[:, None, columns], THESIS_FLOOR)[0]
    displacement = relative_error((true[:, X] - start[:, X])[:, None, None],
                                  (predicted[:, X] - start[:, X])[:, None, None], THESIS_FLOOR)[0, 0]
    return {"relative_x": float(relative[0]), "relative_x_dot": float(relative[1]),
            "relative_displacement": float(displacement),
            "absolute_x_cm": float((predicted[:, X] - true[:, X]).abs().mean()) * 100,
            "absolute_x_dot_cm": float((predicted[:, X_DOT] - true[:, X_DOT]).abs().mean()) * 100,
            "faulted": faults / (len(rows) * horizon), "branches": len(rows),
            "spread_rank_correlation": spread_rank_correlation(model, start, test["action"][window],
                                                               test["design"][rows], true[:, X] - start[:, X])
            if deterministic else float("nan")}


def spread_rank_correlation(model, start: torch.Tensor, actions: torch.Tensor, designs: torch.Tensor,
                            displacement: torch.Tensor) -> float:
    """Spearman's correlation between the voting members' spread of the predicted displacement
    and the error of their mean, over branches (each member's mean prediction, open loop)."""
    members = model.voting_members
    if members is None or len(members) < 2:
        return float("nan")
    predict = PredictNextState(model, deterministic=True)
    finals = []
    for member in members.tolist():
        state = start
        chosen = torch.full((len(start), 1), member, dtype=torch.long)
        for step in range(actions.shape[1]):
            state, _, _, _ = predict(state, actions[:, step], designs, chosen)
        finals.append(state[:, X] - start[:, X])
    predicted = torch.stack(finals)  # [members, branches]
    spread, error = predicted.std(0), (predicted.mean(0) - displacement).abs()

    def ranks(values: torch.Tensor) -> torch.Tensor:
        return values.argsort().argsort().double()

    return float(torch.corrcoef(torch.stack([ranks(spread), ranks(error)]))[0, 1])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_data_arguments(parser)
    parser.add_argument("--horizons", type=int, nargs="+", default=[1, 3, 8, 25])
    parser.add_argument("--starts", type=int, default=2000, help="branches per horizon")
    parser.add_argument("--models", nargs="+", default=["pce", "moe"],
                        help="models to fit and compare, NAME[:key=value,...] (a world_model yaml and settings of "
                             "its model, e.g. pce:lags=1); ratios are against moe when it is among them")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    torch.set_num_threads(1)

    data, fit, test = checked_data(args, args.models)
    print(f"{args.run or f'{args.episodes} cached episodes'}: {len(data)} real transitions; {len(fit)} fit the "
          f"models, the last {len(test)} are held out")
    horizons = sorted(set(args.horizons))
    results, reports = {}, {}
    for name in args.models:
        reports[name], measured = fit_and_measure(name, data, args.fit_transitions, args.test_transitions, horizons,
                                                  args.starts, args.seed)
        results.update({(name, *key): value for key, value in measured.items()})
    print("| model | prediction | k | rel. err. x | rel. err. x_dot | rel. err. displacement | abs. err. x (cm) "
          "| abs. err. x_dot (cm/s) | predictions faulted | spread-error rank correlation |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for (name, deterministic, horizon), r in results.items():
        print(f"| {name} | {'deterministic' if deterministic else 'sampled'} | {horizon} | {r['relative_x']:.3f} | "
              f"{r['relative_x_dot']:.3f} | {r['relative_displacement']:.3f} | {r['absolute_x_cm']:.2f} | "
              f"{r['absolute_x_dot_cm']:.2f} | {r['faulted']:.2f} | {r['spread_rank_correlation']:.2f} |")
    # The ensemble to compare with: the first model of the moe yaml, whatever its settings.
    moe = next((m for m in args.models if setup.parse_model(m)[0] == "moe"), None)
    print("\n".join(summary_rows(reports, results, horizons, moe)))
    k = 8 if 8 in horizons else horizons[-1]
    for name in (m for m in args.models if m != moe):
        pce = results[name, True, k]
        error = pce["relative_displacement"]
        line = (f"{k}-step branches, deterministic: {name} relative error of x {pce['relative_x']:.3f} (target 0.1), "
                f"of the displacement {error:.3f}")
        if moe is not None:
            reference = results[moe, True, k]["relative_displacement"]
            line += f"; {name} / {moe} displacement error: {error:.3f} / {reference:.3f} = {error / reference:.2f}"
        print(line)


if __name__ == "__main__":
    main()
