"""Imagined steps per second of the default world model against real env steps per second.

    python benchmarks/imagination_throughput.py [--repeats 5] [--batches 500x10,200x25,2000x25,5000x25]
        [--world-model moe] [--disagreement-cut 1.0] [--disagreement-penalty 1.0] [--deterministic]

The model is ``world_model=moe`` as configured (``conf/world_model/moe.yaml``: a
:class:`GaussianEnsemble` of 7 members, 3 x 200 SiLU, predicting the full state), given a
short fit (3 epochs) on 64 real gait-plus-noise episodes (``world_model_setup.py``): prediction
costs the same whatever the accuracy. The policy is the one training runs:
``make_actor(18, 4)`` behind an ``ObservationNorm`` (``make_collecting_policy``), with
observation statistics from the same data.

Imagined: :class:`ImaginedEnv` rolled out as the model-based collector does
(``env.rollout(horizon, policy, break_when_any_done=False)`` under ``torch.no_grad``, start
states drawn from the real transitions, a member per trajectory), timed per rollout, for
each ``TRAJECTORIESxHORIZON`` batch. Training's batches are 5000 steps: 500 x 10 at the
start of the horizon schedule, 200 x 25 at its end; 2000 and 5000 trajectories show what
larger batches give. Real: ``BatchedWalkerEnv(32, full_state=True)`` over SE designs, one
100-step episode per rollout, its reset included (an SE reset rebuilds every robot, as
every training epoch does), with the same policy.

Every variant runs at 1 and 2 torch threads; repeats are interleaved and each imagined
rate is divided by the real rate of the same repeat and thread count, the median over
repeats printed. The raw PyBullet loop of one core (``env_throughput.raw_pybullet``) is
measured in every repeat too, beside the absolute rates. The last line is
``imagination_ratio: <imagined / real steps per second, 1 thread, 500 x 10>``
(training's first batch shape; its loop runs one thread).

``--world-model`` measures another world model's yaml (``pce``, ``pce_sparse``) instead.
``--disagreement-cut T`` adds, per batch, the same imagined env with branches cut where the
members disagree past ``T`` (``imagination.disagreement_cut``; its scale from the same real
transitions), timed in the same repeats; its rows give the cut's steps/s, their paired ratio
to the uncut rate (every member predicts every step, and cut rows restart), and the share of
branches it cut. The last line is then ``cut_cost_ratio: <cut / uncut steps per second, 1
thread, first batch>``. ``--disagreement-penalty W`` adds the same with the imagined reward
lowered by ``W`` times the disagreement (``imagination.disagreement_penalty``: every member
predicts every step, no branch is cut), and ``penalty_cost_ratio`` likewise.
``--deterministic`` imagines with each member's mean, as ``imagination.deterministic`` does
(``world_model=pce``'s default), for every variant.
"""

from __future__ import annotations

import argparse
import statistics
import time

import torch
import world_model_setup
from env_throughput import raw_pybullet

from unipolicy_rl.collectors import imagined_metrics, truncate_last_step
from unipolicy_rl.envs import BatchedWalkerEnv, RewardWeights, RobotSettings
from unipolicy_rl.networks import make_actor
from unipolicy_rl.policy import NORMALIZED_OBSERVATION, make_collecting_policy, make_observation_norm
from unipolicy_rl.world_models import DisagreementCut, DisagreementPenalty, ImaginedEnv, StateLayout, make_world_model
from unipolicy_rl.world_models.disagreement import change_scale

REAL_STEPS = 100


def timed_rollout(env, policy, steps: int, cut_shares: list | None = None) -> tuple[float, float]:
    """(steps/s of wall time, steps per second of this process's CPU time) of one rollout; the
    share of branches the disagreement cut ended (0 where nothing cuts) is appended to
    ``cut_shares`` when given."""
    with torch.no_grad():
        wall, cpu = time.perf_counter(), time.process_time()
        rollout = env.rollout(steps, policy, break_when_any_done=False)
        wall, cpu = time.perf_counter() - wall, time.process_time() - cpu
    if cut_shares is not None:
        cut_shares.append(imagined_metrics(truncate_last_step(rollout)).get("imagined/cut_share", 0.0))
    return rollout.numel() / wall, rollout.numel() / cpu


def setup(world_model: str = "moe"):
    """The fitted model, its fit report, the real transitions, the policy and a start sampler."""
    collection = world_model_setup.collect(64)
    layout = StateLayout.for_env(RobotSettings(), "thesis", False, "full")
    data = collection.transitions(layout.from_full)
    model, trainer = world_model_setup.configured(world_model, max_epochs=3)
    report = trainer.fit(model, data, torch.Generator().manual_seed(0))
    observations = layout.observation(data["state"], data["design"])
    policy = make_collecting_policy(make_observation_norm(18, observations.mean(0), observations.std(0)),
                                    make_actor(18, 4, observation_key=NORMALIZED_OBSERVATION))
    pool = data.select("state", "design")

    def starts(n: int):
        return pool[torch.randint(pool.shape[0], (n,))]

    return model, report, data, policy, starts


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--batches", default="500x10,200x25,2000x25,5000x25",
                        help="imagined batches, TRAJECTORIESxHORIZON, comma-separated")
    parser.add_argument("--threads", default="1,2", help="torch thread counts, comma-separated")
    parser.add_argument("--world-model", default="moe", help="the world model's yaml (conf/world_model/)")
    parser.add_argument("--disagreement-cut", type=float, default=None,
                        help="also time each batch with branches cut where members disagree past this")
    parser.add_argument("--disagreement-penalty", type=float, default=None,
                        help="also time each batch with the reward lowered by this times the members' disagreement")
    parser.add_argument("--deterministic", action="store_true",
                        help="imagine with each member's mean prediction (imagination.deterministic)")
    args = parser.parse_args()
    batches = [tuple(int(v) for v in spec.split("x")) for spec in args.batches.split(",")]
    thread_counts = [int(t) for t in args.threads.split(",")]
    torch.set_num_threads(1)
    torch.manual_seed(0)

    model, report, data, policy, starts = setup(args.world_model)
    real = BatchedWalkerEnv(32, full_state=True)
    real.set_seed(0)
    world_model = make_world_model(model, RewardWeights(), deterministic=args.deterministic)
    imagined = {batch: ImaginedEnv(world_model, real, starts, batch[0]) for batch in batches}
    # The variants that read the members' disagreement: name -> (its headline, its env per batch).
    scale = change_scale(data, model.layout.robot_size)
    variants = {}
    for name, value, headline_name, setting in (
            ("disagreement_cut", args.disagreement_cut, "cut_cost_ratio", lambda v: {"cut": DisagreementCut(v, scale)}),
            ("disagreement_penalty", args.disagreement_penalty, "penalty_cost_ratio",
             lambda v: {"penalty": DisagreementPenalty(v, scale)})):
        if value is not None:
            variant_model = make_world_model(model, RewardWeights(), deterministic=args.deterministic, **setting(value))
            variants[f"{name}={value:g}"] = (headline_name, {batch: ImaginedEnv(variant_model, real, starts, batch[0])
                                                             for batch in batches})
    for threads in thread_counts:  # untimed warm-up: robot builds, first allocations
        torch.set_num_threads(threads)
        timed_rollout(real, policy, REAL_STEPS)
        for (_, horizon), env in [*imagined.items(), *(item for _, envs in variants.values() for item in envs.items())]:
            timed_rollout(env, policy, horizon)

    raw_rates = []
    real_rates = {threads: [] for threads in thread_counts}
    rates = {(threads, batch): [] for threads in thread_counts for batch in batches}
    variant_rates = {(name, threads, batch): [] for name in variants for threads in thread_counts for batch in batches}
    cut_shares = {(name, batch): [] for name in variants for batch in batches}
    for _ in range(args.repeats):  # interleaved, so drift in the machine's load hits every variant
        torch.set_num_threads(1)
        raw_rates.append(raw_pybullet(2000)[0])
        for threads in thread_counts:
            torch.set_num_threads(threads)
            real_rates[threads].append(timed_rollout(real, policy, REAL_STEPS))
            for batch, env in imagined.items():
                rates[threads, batch].append(timed_rollout(env, policy, batch[1]))
                for name, (_, envs) in variants.items():
                    variant_rates[name, threads, batch].append(timed_rollout(envs[batch], policy, batch[1],
                                                                             cut_shares[name, batch]))
    real.close()

    print(f"model: {type(model).__name__} (world_model={args.world_model}), {model.members} members, "
          f"{'deterministic' if args.deterministic else 'sampled'} imagination, "
          f"{model.layout.size}-number state, fitted {report.epochs} "
          f"epochs on {data.shape[0]} transitions ({report.seconds:.1f} s)")
    print(f"raw PyBullet loop, one core: {statistics.median(raw_rates):.0f} actions/s "
          f"(median of {args.repeats}; {min(raw_rates):.0f}-{max(raw_rates):.0f})")
    print(f"{'variant':44s} {'threads':>7s} {'steps/s':>9s} {'x real (paired)':>20s} "
          f"{'steps/CPU-s':>12s} {'x real (CPU)':>13s}")
    headline = {}
    for threads in thread_counts:
        real_wall = [wall for wall, _ in real_rates[threads]]
        real_cpu = [cpu for _, cpu in real_rates[threads]]
        print(f"{'BatchedWalkerEnv(32), 100-step episode':44s} {threads:7d} {statistics.median(real_wall):9.0f} "
              f"{'1':>20s} {statistics.median(real_cpu):12.0f} {'1':>13s}")
        for trajectories, horizon in batches:
            wall = [w for w, _ in rates[threads, (trajectories, horizon)]]
            cpu = [c for _, c in rates[threads, (trajectories, horizon)]]
            ratios = [a / b for a, b in zip(wall, real_wall, strict=True)]
            cpu_ratios = [a / b for a, b in zip(cpu, real_cpu, strict=True)]
            headline[threads, (trajectories, horizon)] = statistics.median(ratios)
            name = f"imagined, {trajectories} trajectories x {horizon} steps"
            spread = f"{statistics.median(ratios):.1f} ({min(ratios):.1f}-{max(ratios):.1f})"
            print(f"{name:44s} {threads:7d} {statistics.median(wall):9.0f} {spread:>20s} "
                  f"{statistics.median(cpu):12.0f} {statistics.median(cpu_ratios):13.1f}")
            for variant in variants:
                variant_wall = [w for w, _ in variant_rates[variant, threads, (trajectories, horizon)]]
                paired = [c / u for c, u in zip(variant_wall, wall, strict=True)]
                headline[variant, threads, (trajectories, horizon)] = statistics.median(paired)
                share = statistics.median(cut_shares[variant, (trajectories, horizon)])
                name = f"  with {variant} ({share:.0%} cut)"
                print(f"{name:44s} {threads:7d} {statistics.median(variant_wall):9.0f} "
                      f"{f'x plain {statistics.median(paired):.2f} ({min(paired):.2f}-{max(paired):.2f})':>20s}")
    print("steps/CPU-s: steps per second of this process's CPU time (both threads' with 2), which load from "
          "other processes moves less than wall time")
    print(f"imagination_ratio: {headline[thread_counts[0], batches[0]]:.1f}")
    for variant, (headline_name, _) in variants.items():
        print(f"{headline_name}: {headline[variant, thread_counts[0], batches[0]]:.2f}")


if __name__ == "__main__":
    main()
