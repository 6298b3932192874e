"""The world model of grammar robots on held-out transitions: seen robots, and robots it never saw.

    python benchmarks/token_model_accuracy.py [--morphologies 8] [--robots 16] [--episodes 3] [--max-steps 600]

The model is the one ``python train.py source=moe robot=grammar`` builds (``world_model=moe`` with
``robot=grammar``: :class:`~unipolicy_rl.world_models.TokenEnsemble`, conf/world_model/robot/grammar.yaml),
fitted once by its yaml's trainer with the step budget raised to ``--max-steps`` (early stopping
may end it first). Data: robots of the first ``--morphologies`` training morphologies of the
default split (``robot=grammar``'s), SE designs, padded to the config's ``max_links``, each slot
driven by :class:`~unipolicy_rl.envs.gait.RandomPhaseGait` (a sine of its own phase plus noise);
``--episodes`` episodes of ``--robots`` robots fit the model, one more episode of them is held out,
and one episode of ``--robots`` robots of the first ``--held-out-morphologies`` held-out
morphologies (larger robots among them) measures the model zero-shot.

Printed per held-out set: the share of the real one-step state change the model's mean
prediction leaves unexplained (``model/fresh_error``'s figure: per output, MSE over the change's
variance, averaged over the outputs that change), the same figure for predicting no change
(about 1), and the unexplained share per group of moving features over real tokens.
"""

from __future__ import annotations

import argparse
import dataclasses
import time
from pathlib import Path

import torch
from hydra import compose, initialize_config_dir
from hydra.utils import instantiate

from unipolicy_rl.collectors import transitions
from unipolicy_rl.env_factories import grammar_morphologies, morphology_env_kwargs
from unipolicy_rl.envs import MorphologyWalkerEnv
from unipolicy_rl.envs.gait import RandomPhaseGait
from unipolicy_rl.envs.link_tokens import MOVING
from unipolicy_rl.envs.tokens import FEATURE_INDEX, real_tokens
from unipolicy_rl.factories import make_dynamics_model
from unipolicy_rl.world_models.disagreement import member_predictions
from unipolicy_rl.world_models.fresh_error import fresh_error, no_change_error

ROOT = Path(__file__).resolve().parent.parent
GROUPS = {
    "position": ("x", "y", "z"),
    "velocity": ("vx", "vy", "vz"),
    "orientation": ("r00", "r10", "r20", "r01", "r11", "r21"),
    "angular velocity": ("wx", "wy", "wz"),
    "joint angle": ("joint_angle",),
    "joint rate": ("joint_rate",),
}


def collect(cfg, morphologies, robots: int, episodes: int, seed: int, layout):
    """``episodes`` episodes of ``robots`` robots of ``morphologies`` as buffer rows (the model's view)."""
    kwargs = {**morphology_env_kwargs(cfg), "morphologies": morphologies, "sampling": "balanced"}
    env = MorphologyWalkerEnv(robots, **kwargs)
    env.set_seed(seed)
    rows = []
    for episode in range(episodes):
        gait = RandomPhaseGait(robots, layout.max_links, env.control_period, seed=seed * 1000 + episode)
        batch = env.rollout(cfg.robot.episode_length, gait, break_when_any_done=False)
        rows.append(transitions(batch, layout.from_full, None, layout.state_key, layout.build_keys))
    env.close()
    return torch.cat(rows)


@torch.no_grad()
def feature_errors(model, rows) -> dict[str, float]:
    """Unexplained share of each feature group's change over real tokens (members' mean prediction)."""
    layout = model.layout
    every = member_predictions(model, rows["state"], rows["action"], rows["design"])  # [voters, n, size]
    predicted = every.mean(0)
    tokens, after = layout.tokens(rows["state"]), layout.tokens(rows["next_state"])
    real = real_tokens(tokens)
    change, error = (after - tokens)[real][:, MOVING], (layout.tokens(predicted) - after)[real][:, MOVING]
    out = {}
    for group, names in GROUPS.items():
        columns = [FEATURE_INDEX[name] for name in names]
        variance = change[:, columns].var(0, correction=0).clamp_min(1e-12)
        out[group] = float((error[:, columns].square().mean(0) / variance).mean())
    return out


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--morphologies", type=int, default=8, help="training morphologies the data come from")
    parser.add_argument("--held-out-morphologies", type=int, default=4)
    parser.add_argument("--robots", type=int, default=16, help="robots per episode")
    parser.add_argument("--episodes", type=int, default=3, help="fitting episodes (one more is held out)")
    parser.add_argument("--max-steps", type=int, default=600, help="gradient steps of the fit, at most")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("overrides", nargs="*", help="Hydra overrides, e.g. world_model.model.embedding=32")
    args = parser.parse_args(argv)
    torch.set_num_threads(args.threads)
    with initialize_config_dir(str(ROOT / "conf"), version_base="1.3"):
        cfg = compose("config", overrides=["robot=grammar", "source=moe", "device=cpu", *args.overrides])
    torch.manual_seed(args.seed)
    model = make_dynamics_model(cfg)
    layout = model.layout
    trainer = dataclasses.replace(instantiate(cfg.world_model.trainer), max_steps=args.max_steps)
    _, seen = grammar_morphologies(cfg, "train")
    _, unseen = grammar_morphologies(cfg, "held_out")
    seen, unseen = seen[: args.morphologies], unseen[: args.held_out_morphologies]

    started = time.perf_counter()
    data = collect(cfg, seen, args.robots, args.episodes + 1, args.seed, layout)
    per_episode = args.robots * cfg.robot.episode_length
    fit_rows, held_rows = data[: args.episodes * per_episode], data[args.episodes * per_episode:]
    zero_shot = collect(cfg, unseen, args.robots, 1, args.seed + 1, layout)
    print(f"collected {len(data) + len(zero_shot)} transitions in {time.perf_counter() - started:.0f} s: "
          f"{len(fit_rows)} to fit ({len(seen)} morphologies), {len(held_rows)} held out, {len(zero_shot)} of "
          f"{len(unseen)} unseen morphologies ({sorted(m.num_links for m in unseen)} links)")
    report = trainer.fit(model, fit_rows, torch.Generator().manual_seed(args.seed))
    print(f"{type(model).__name__}: {model.members} members, {layout.max_links} token slots; fit "
          f"{report.extras['fit_steps']:.0f} steps in {report.seconds:.0f} s, validation MSE "
          f"{report.as_metrics()['model/validation_mse']:.3f} (standardised)")
    results = {}
    for name, rows in (("held-out episodes, seen morphologies", held_rows),
                       ("unseen morphologies (zero-shot)", zero_shot)):
        error = fresh_error(model, rows)["model/fresh_error"]
        baseline = no_change_error(rows, layout.robot_size)
        groups = feature_errors(model, rows)
        results[name] = {"model": error, "no_change": baseline, **groups}
        print(f"{name}: unexplained share of the state change {error:.3f} (no change: {baseline:.3f}); "
              + ", ".join(f"{group} {value:.2f}" for group, value in groups.items()))
    return results


if __name__ == "__main__":
    main()
