"""Evaluate one policy on a grid of robot designs, in metres as well as reward.

A universal policy is judged by how it walks across the whole (l, rho) range, not on
the design it happened to train on most. Every (design, episode) pair runs through one
``BatchedWalkerEnv``: each batch resets its robots with explicit designs and rolls out
exactly one episode, so the robots of a batch walk side by side at physics speed.
"""

from __future__ import annotations

import csv
import math
from collections.abc import Iterator, Sequence
from dataclasses import asdict, dataclass, fields
from pathlib import Path

import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.envs import EnvBase
from torchrl.envs.utils import ExplorationType, set_exploration_type

from unipolicy_rl.envs import BatchedWalkerEnv, Design
from unipolicy_rl.envs.reward import forward_displacement, mean_forward_speed
from unipolicy_rl.envs.tokens import MORPHOLOGY, walking_observation

# A design "walks" when its base gets at least this far forward in one episode (m).
WALKING_DISPLACEMENT = 1.0
# A policy "walks the grid" when the grid's mean displacement reaches this (m) and every
# design walks: the level at which sources are compared (real env steps and wall time to it).
GRID_WALKING_MEAN = 3.0


def walks_the_grid(mean_displacement: float, min_displacement: float) -> bool:
    """Grid mean >= :data:`GRID_WALKING_MEAN` m with every design >= :data:`WALKING_DISPLACEMENT` m."""
    return mean_displacement >= GRID_WALKING_MEAN and min_displacement >= WALKING_DISPLACEMENT
def grid_score(mean_displacement: float, min_displacement: float) -> tuple[bool, float]:
    """How a grid evaluation ranks against another (larger is better): a grid that walks
    (:func:`walks_the_grid`) beats any that does not, then the higher grid mean wins."""
    return walks_the_grid(mean_displacement, min_displacement), mean_displacement


DEFAULT_MAX_ROBOTS = 32


@dataclass(frozen=True)
class DesignResult:
    """Episode statistics of one design; std is the population std (0 for one episode)."""

    length: float
    density: float
    episodes: int
    mean_episode_reward: float
    std_episode_reward: float
    mean_forward_displacement: float  # m, base x at the episode's last step
    std_forward_displacement: float  # m
    mean_forward_speed: float  # m/s, displacement / episode duration
    physics_faults: int  # episodes cut short because the simulation blew up

    @property
    def design(self) -> Design:
        return Design(self.length, self.density)


def rollout_designs(env: EnvBase, policy, designs: Sequence[Design],
                    morphologies: Sequence[int] | None = None) -> TensorDictBase:
    """Resets every robot of ``env`` to its own design (and, in a ``MorphologyWalkerEnv``, to its
    own morphology: an index into the env's set) and rolls out exactly one episode.

    Returns the rollout, shape [num_robots, steps]. A robot that finishes early (a physics
    fault) has its later entries frozen at its last step by TorchRL's partial-step logic;
    :func:`episode_outcomes` reads each robot up to its own first ``done`` either way.
    """
    num_robots = env.batch_size[0]
    if len(designs) != num_robots:
        raise ValueError(f"need one design per robot: got {len(designs)} designs for {num_robots} robots")
    # float64, not the spec's float32: the env builds the robot from these numbers, and
    # 0.15 should stay 0.15 rather than become 0.15000000596.
    requested = torch.tensor([(d.length, d.density) for d in designs], dtype=torch.float64, device=env.device)
    reset_request = TensorDict({"design": requested}, batch_size=env.batch_size, device=env.device)
    if morphologies is not None:
        if len(morphologies) != num_robots:
            raise ValueError(f"need one morphology per robot: got {len(morphologies)} for {num_robots} robots")
        reset_request[MORPHOLOGY] = torch.tensor(list(morphologies), dtype=torch.int64, device=env.device)[:, None]
    start = env.reset(reset_request)
    return env.rollout(
        env.episode_length,
        policy,
        auto_reset=False,
        tensordict=start,
        break_when_any_done=False,  # one robot's fault must not cut the others' episodes short
        break_when_all_done=True,
    )


def episode_outcomes(rollout: TensorDictBase, control_period: float) -> dict[str, torch.Tensor]:
    """Per-robot episode reward, forward displacement (m), mean speed (m/s), steps and fault flag."""
    done = rollout["next", "done"].squeeze(-1)  # [robots, steps]
    if not bool(done.any(-1).all()):
        raise RuntimeError("every robot's episode must end within the rollout; was it cut short?")
    steps_taken = torch.arange(done.shape[-1], device=done.device)
    # Index of each robot's first done: later entries belong to no episode.
    last = torch.where(done, steps_taken, done.shape[-1]).min(-1).values
    in_episode = steps_taken <= last.unsqueeze(-1)
    rows = torch.arange(done.shape[0], device=done.device)
    reward = (rollout["next", "reward"].squeeze(-1) * in_episode).sum(-1)
    displacement = forward_displacement(walking_observation(rollout["next"])[rows, last])
    steps = last + 1
    return {
        "episode_reward": reward.double().cpu(),
        "forward_displacement": displacement.double().cpu(),
        "forward_speed": mean_forward_speed(displacement.double(), steps.double(), control_period).cpu(),
        "steps": steps.cpu(),
        "physics_fault": rollout["next", "physics_fault"].squeeze(-1)[rows, last].cpu(),
    }


def _check_designs_were_used(rollout: TensorDictBase, designs: Sequence[Design],
                             morphologies: Sequence[int] | None = None) -> None:
    # A wrapper that drops the reset's "design" (or "morphology") key would silently evaluate
    # random robots under the requested labels; this guard makes that loud.
    requested = torch.tensor([(d.length, d.density) for d in designs], dtype=torch.float32)
    used = rollout["design"][:, 0].cpu()
    if not torch.allclose(used, requested):
        raise RuntimeError(
            f"the env did not use the requested designs: asked {requested.tolist()}, got {used.tolist()}"
        )
    if morphologies is not None and rollout[MORPHOLOGY][:, 0, 0].tolist() != list(morphologies):
        raise RuntimeError(f"the env did not use the requested morphologies: asked {list(morphologies)}, got "
                           f"{rollout[MORPHOLOGY][:, 0, 0].tolist()}")


def design_rollouts(policy, env_kwargs: dict, designs: Sequence[Design], num_robots: int | None = None, seed: int = 0,
                    deterministic: bool = True, progress: str | None = None, *,
                    env_class: type[EnvBase] = BatchedWalkerEnv,
                    morphologies: Sequence[int] | None = None) -> Iterator[tuple[list[Design], TensorDictBase, float]]:
    """One episode of ``policy`` per design, ``num_robots`` at a time: yields each batch's designs,
    its rollout (``[num_robots, steps]``; a short last batch is padded with copies of its last
    design, whose rows follow the batch's) and the env's control period.

    ``progress``: a progress bar with this label, or None for none. ``env_class`` is built with
    ``env_kwargs``; for a ``MorphologyWalkerEnv``, ``morphologies`` gives each design's robot
    (an index into the env's set, one per design).
    """
    if "num_robots" in env_kwargs:
        raise ValueError("env_kwargs must not set num_robots: pass it as num_robots=...")
    designs = list(designs)
    num_robots = num_robots or min(len(designs), DEFAULT_MAX_ROBOTS)
    if not (isinstance(num_robots, int) and num_robots >= 1):
        raise ValueError(f"num_robots must be a positive integer, got {num_robots!r}")
    if morphologies is not None and len(morphologies) != len(designs):
        raise ValueError(f"need one morphology per design: got {len(morphologies)} for {len(designs)} designs")
    env = env_class(num_robots=num_robots, **env_kwargs)
    env.set_seed(seed)
    batches = range(0, len(designs), num_robots)
    if progress is not None:
        from tqdm.auto import tqdm

        batches = tqdm(batches, desc=progress, unit="batch")
    exploration = ExplorationType.DETERMINISTIC if deterministic else ExplorationType.RANDOM
    try:
        with torch.random.fork_rng(), torch.no_grad(), set_exploration_type(exploration):
            torch.manual_seed(seed)
            for start in batches:
                batch = designs[start : start + num_robots]
                padded = batch + [batch[-1]] * (num_robots - len(batch))
                robots = None
                if morphologies is not None:
                    robots = list(morphologies[start : start + num_robots])
                    robots += [robots[-1]] * (num_robots - len(robots))
                rollout = rollout_designs(env, policy, padded, robots)
                _check_designs_were_used(rollout, padded, robots)
                yield batch, rollout, env.control_period
    finally:
        env.close()


def evaluate_on_designs(
    policy,
    env_kwargs: dict,
    designs: Sequence[Design],
    episodes_per_design: int = 4,
    num_robots: int | None = None,
    seed: int = 0,
    deterministic: bool = True,
    progress: bool = False,
) -> list[DesignResult]:
    """Runs ``episodes_per_design`` episodes of ``policy`` on each design; one result per design, in order.

    ``policy`` reads "observation" and writes "action" (a TensorDict module). Actions are
    the policy's deterministic ones unless ``deterministic=False``; with deterministic
    actions the physics is deterministic too, so repeated episodes of a design coincide
    and more than one episode only matters for stochastic actions.
    """
    if not (isinstance(episodes_per_design, int) and episodes_per_design >= 1):
        raise ValueError(f"episodes_per_design must be a positive integer, got {episodes_per_design!r}")
    if not designs:
        raise ValueError("designs is empty: nothing to evaluate")
    pairs = [design for design in designs for _ in range(episodes_per_design)]
    outcomes = [
        {key: value[: len(batch)] for key, value in episode_outcomes(rollout, control_period).items()}
        for batch, rollout, control_period in design_rollouts(policy, env_kwargs, pairs, num_robots, seed,
                                                              deterministic, "evaluating designs" if progress else None)
    ]
    merged = {key: torch.cat([outcome[key] for outcome in outcomes]) for key in outcomes[0]}
    return [
        _summarise_design(design, {key: value[i * episodes_per_design : (i + 1) * episodes_per_design]
                                   for key, value in merged.items()})
        for i, design in enumerate(designs)
    ]


def _summarise_design(design: Design, episodes: dict[str, torch.Tensor]) -> DesignResult:
    reward, displacement = episodes["episode_reward"], episodes["forward_displacement"]
    return DesignResult(
        length=float(design.length),
        density=float(design.density),
        episodes=len(reward),
        mean_episode_reward=reward.mean().item(),
        std_episode_reward=reward.std(correction=0).item(),
        mean_forward_displacement=displacement.mean().item(),
        std_forward_displacement=displacement.std(correction=0).item(),
        mean_forward_speed=episodes["forward_speed"].mean().item(),
        physics_faults=int(episodes["physics_fault"].sum()),
    )


# -- CSV -------------------------------------------------------------------------------
CSV_COLUMNS = tuple(field.name for field in fields(DesignResult))


def write_csv(results: Sequence[DesignResult], path: str | Path) -> Path:
    """One row per design, columns :data:`CSV_COLUMNS`, full float precision."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with path.open("w", newline="") as handle:
        writer = csv.DictWriter(handle, fieldnames=CSV_COLUMNS)
        writer.writeheader()
        for result in results:
            writer.writerow({key: repr(value) if isinstance(value, float) else value
                             for key, value in asdict(result).items()})
    return path


def read_csv(path: str | Path) -> list[DesignResult]:
    """Reads what :func:`write_csv` wrote (to re-plot or compare runs without re-evaluating)."""
    types = {field.name: (int if field.type in ("int", int) else float) for field in fields(DesignResult)}
    with Path(path).open(newline="") as handle:
        return [DesignResult(**{key: types[key](row[key]) for key in CSV_COLUMNS}) for row in csv.DictReader(handle)]


# -- summary ---------------------------------------------------------------------------
def summarise(results: Sequence[DesignResult], walking_displacement: float = WALKING_DISPLACEMENT) -> dict:
    """Grid-level numbers for a log line or a sweep table: how well, and how evenly, the policy walks."""
    if not results:
        raise ValueError("results is empty: nothing to summarise")
    displacement = [r.mean_forward_displacement for r in results]
    reward = [r.mean_episode_reward for r in results]
    worst = min(results, key=lambda r: r.mean_forward_displacement)
    best = max(results, key=lambda r: r.mean_forward_displacement)
    walking = sum(d >= walking_displacement for d in displacement)
    return {
        "designs": len(results),
        "episodes": sum(r.episodes for r in results),
        "mean_forward_displacement": _mean(displacement),
        "min_forward_displacement": min(displacement),
        "max_forward_displacement": max(displacement),
        "mean_forward_speed": _mean([r.mean_forward_speed for r in results]),
        "mean_episode_reward": _mean(reward),
        "min_episode_reward": min(reward),
        "walking_designs": walking,  # cells with mean displacement >= walking_displacement
        "walking_fraction": walking / len(results),
        "walking_displacement": walking_displacement,
        "physics_faults": sum(r.physics_faults for r in results),
        "worst_design": (worst.length, worst.density),
        "best_design": (best.length, best.density),
    }


def _mean(values: Sequence[float]) -> float:
    return math.fsum(values) / len(values)


# -- text ------------------------------------------------------------------------------
def format_table(results: Sequence[DesignResult]) -> str:
    """One line per design: the numbers a person reads first."""
    lines = [f"{'l (m)':>7} {'rho':>6} {'reward':>10} {'disp (m)':>10} {'+-':>6} {'speed (m/s)':>11} {'faults':>6}"]
    for r in results:
        lines.append(
            f"{r.length:7.3f} {r.density:6.3f} {r.mean_episode_reward:10.2f} {r.mean_forward_displacement:10.3f} "
            f"{r.std_forward_displacement:6.3f} {r.mean_forward_speed:11.3f} {r.physics_faults:6d}"
        )
    return "\n".join(lines)


def format_summary(summary: dict) -> str:
    """What a finished training run and ``python -m unipolicy_rl.evaluate`` print about a grid."""
    return "\n".join(
        [
            f"designs {summary['designs']}, episodes {summary['episodes']}, physics faults {summary['physics_faults']}",
            f"forward displacement (m): mean {summary['mean_forward_displacement']:.3f}, "
            f"min {summary['min_forward_displacement']:.3f}, max {summary['max_forward_displacement']:.3f}; "
            f"mean speed {summary['mean_forward_speed']:.3f} m/s",
            f"episode reward: mean {summary['mean_episode_reward']:.2f}, min {summary['min_episode_reward']:.2f}",
            f"designs walking >= {summary['walking_displacement']:g} m: "
            f"{summary['walking_designs']}/{summary['designs']}; "
            f"worst design (l, rho) = {_pair(summary['worst_design'])}, best = {_pair(summary['best_design'])}",
        ]
    )


def _pair(design: tuple[float, float]) -> str:
    return f"({design[0]:.3f}, {design[1]:.3f})"
