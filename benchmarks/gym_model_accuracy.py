"""One-step accuracy of the world models on a gymnasium task: the ensemble against the PCE.

    python benchmarks/gym_model_accuracy.py [--env Pendulum-v1] [--steps 5000] [--seeds 0,1,2] [--quick]

Data: real steps of ``make_gym_env(<env>)`` (the transforms a training run uses: actions in
[-1, 1], scaled to the task's range) under uniform random actions, ``--steps`` to fit on and a
quarter as many from another seed held out, per seed. Models, each fitted by its yaml's trainer
on the fitting steps, as ``python train.py env=gym env.id=<env> source=moe|pce`` builds them
(Hydra's ``compose`` and training's :func:`~unipolicy_rl.settings.make_dynamics_model`):

* ``ensemble``: the default ``GaussianEnsemble`` (``world_model=moe``), predicting the state's change;
* ``ensemble, next-state target``: the same predicting the next state itself
  (``world_model.model.target=next_state``);
* ``pce``: the one-step PCE with the task's basis (``world_model=pce``; ``pce_env/gym.yaml``:
  every term up to order 3, state-state interactions included);
* ``pce, the walker's basis``: the same PCE with the walker's basis (hyperbolic q = 0.75,
  interactions only through an action: ``world_model.model.interactions=controls`` ...).

The error is the one-step standardised MSE on the held-out steps: per output, the mean squared
error of the voting members' mean next state, divided by the variance of that output's real
change over the held-out steps, averaged over outputs (``model/validation_mse``'s scale: 1 is
as good as predicting no change's mean). The last lines are the medians over seeds and the
ratio ``pce / ensemble`` (issue target: at most 1 on a smooth, contact-free task). The raw
env rate of the collection is printed first (machines differ; fit seconds only beside it).
"""

from __future__ import annotations

import argparse
import statistics
import time
from pathlib import Path

import torch
from hydra import compose, initialize_config_dir
from hydra.utils import instantiate
from omegaconf import DictConfig

from unipolicy_rl.collectors import TransitionBuffer
from unipolicy_rl.envs.gym_task import make_gym_env
from unipolicy_rl.settings import make_dynamics_model
from unipolicy_rl.world_models.disagreement import member_predictions

CONF = Path(__file__).resolve().parent.parent / "conf"
WALKER_BASIS = ("world_model.model.truncation=hyperbolic", "world_model.model.interactions=controls",
                "world_model.model.max_interaction=2")
WALKERS_PCE = "pce, the walker's basis"
MODELS = {"ensemble": ("source=moe",),
          "ensemble, next-state target": ("source=moe", "world_model.model.target=next_state"),
          "pce": ("source=pce",), WALKERS_PCE: ("source=pce", *WALKER_BASIS)}


def config(env_id: str, overrides: tuple[str, ...]) -> DictConfig:
    """The config of ``python train.py env=gym env.id=<env_id> <overrides>`` (on the CPU)."""
    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        return compose(config_name="config", overrides=["env=gym", f"env.id={env_id}", "device=cpu", *overrides])


def random_steps(env_id: str, steps: int, seed: int) -> tuple[object, float]:
    """``steps`` real steps under uniform random actions, episodes reset as they end, and the rate
    (steps per second) they were collected at."""
    env = make_gym_env(env_id=env_id)
    env.set_seed(seed)
    torch.manual_seed(seed)
    started = time.perf_counter()
    batch = env.rollout(steps, break_when_any_done=False)
    rate = steps / (time.perf_counter() - started)
    env.close()
    return batch, rate


def transitions(model, batch):
    """``batch``'s transitions as the model's buffer holds them (state, action, design, next state)."""
    buffer = TransitionBuffer.for_model(batch.numel(), model)
    buffer.extend(batch, 1)
    return buffer.contents()


def one_step_error(model, held_out) -> float:
    """The standardised one-step MSE of the voting members' mean next state (module docstring)."""
    state, action, design, next_state = (held_out[key] for key in ("state", "action", "design", "next_state"))
    predicted = member_predictions(model, state, action, design).mean(0)
    change_variance = (next_state - state).var(0, correction=0).clamp_min(1e-12)
    return float(((predicted - next_state).pow(2).mean(0) / change_variance).mean())


def measure(env_id: str, steps: int, seed: int, quick: bool) -> tuple[dict[str, tuple[float, float]], float]:
    """``{model: (held-out error, fit seconds)}`` for one seed, and the collection's env rate."""
    fitting, rate = random_steps(env_id, steps, seed)
    held_out_steps, _ = random_steps(env_id, max(steps // 4, 200), seed + 10_000)
    results = {}
    for name, overrides in MODELS.items():
        quick_fit = ("world_model.trainer.max_epochs=2",) if quick and name.startswith("ensemble") else ()
        cfg = config(env_id, (*overrides, *quick_fit))
        torch.manual_seed(seed)
        model = make_dynamics_model(cfg)
        trainer = instantiate(cfg.world_model.trainer)
        started = time.perf_counter()
        trainer.fit(model, transitions(model, fitting), torch.Generator().manual_seed(seed))
        seconds = time.perf_counter() - started
        results[name] = (one_step_error(model, transitions(model, held_out_steps)), seconds)
    return results, rate


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--env", default="Pendulum-v1", help="a gymnasium id with a flat continuous observation")
    parser.add_argument("--steps", type=int, default=5000, help="real steps to fit on, per seed")
    parser.add_argument("--seeds", default="0,1,2", help="comma-separated seeds")
    parser.add_argument("--quick", action="store_true", help="1,000 steps, one seed, a 2-epoch ensemble fit")
    args = parser.parse_args()
    torch.set_num_threads(1)
    seeds = [0] if args.quick else [int(s) for s in args.seeds.split(",")]
    steps = 1000 if args.quick else args.steps
    errors: dict[str, list[float]] = {name: [] for name in MODELS}
    for seed in seeds:
        results, rate = measure(args.env, steps, seed, args.quick)
        print(f"seed {seed}: {args.env}, {steps} random steps collected at {rate:,.0f} env steps/s")
        for name, (error, seconds) in results.items():
            errors[name].append(error)
            print(f"  {name:28s} one-step standardised MSE {error:.2e}   fit {seconds:5.1f} s")
    medians = {name: statistics.median(values) for name, values in errors.items()}
    print(f"median over seeds {seeds}:")
    for name, value in medians.items():
        print(f"  {name:28s} {value:.2e}")
    print(f"pce / ensemble: {medians['pce'] / medians['ensemble']:.2f}   "
          f"the walker's basis / ensemble: {medians[WALKERS_PCE] / medians['ensemble']:.1f}")


if __name__ == "__main__":
    main()
