"""Time one TRPO update of the token policies: the transformer (full and body-graph attention)
against the padded-MLP baseline, on the same batch of padded link tokens.

A batch of ``--samples`` synthetic steps (episodes of 100) of robots of two morphologies padded
to ``--tokens`` tokens of ``--features`` features (no env: the cost is the networks'); the
settings of ``conf/algo/trpo.yaml`` and ``conf/policy/``: 10 CG iterations, max KL 0.01, critic
Adam for 10 epochs of minibatches of 128. Per architecture and ``fisher_fraction`` (the share of
the batch the Fisher-vector products use, ``--fractions``), one warm-up update, then
``--repeats`` timed ones, the variants alternating so load from other processes hits each
alike. Printed: the median wall time of the policy step (``natural_gradient_step``: surrogate
gradient, CG with Fisher-vector products, line search) and of the whole update (GAE, policy
step, critic fit), each fraction's step time as a ratio of the whole batch's, and whether every
step kept the trust region: accepted steps, and the largest whole-batch KL over ``max_kl``. One
thread.

    python benchmarks/token_policy_update.py                 # 1,000 steps, 12 tokens, 3 repeats
    python benchmarks/token_policy_update.py --architectures token_transformer --fractions 1.0 0.2

``--critics`` compares the critics a token transformer policy can train with (``policy.critic``,
:data:`CRITIC_VARIANTS`) instead, on real data: ``robot=grammar``'s env (the 32 training
morphologies, padded to its 29 token slots; ``--overrides`` changes the config, e.g.
``robot.training_morphologies=8``) collects ``--batches`` + 1 batches of ``--samples``
steps (one 100-step episode per robot) with the untrained token transformer policy, its
normaliser refreshed after every batch as in training. Each critic, built by the run's own
factory (``make_learner``, the same seed, so each beside the same actor), is fitted once per
batch with ``algo``'s settings (Adam, 10 epochs of minibatches of 128) on the discounted
reward-to-go of the batch's episodes (``algo.gamma``, no bootstrap: a target no critic's own
values enter, the same for all), its normaliser refreshed after each fit as in training. A
seeded ``--held-out-share`` of each batch's samples (the same for every critic) is kept out of
its fit; after each fit the critic's explained variance is taken on those held-out samples
(steps of the episodes it was fitted on, between fitted ones) and on the whole next batch (new
episodes: at 10 episodes a batch, no critic generalises to them yet, so this column says only
that none is worse). Then the whole TRPO update (``learner.update``:
GAE, the policy step at ``--fractions``' first value, the critic fit on the whole batch) is timed on
the last fitted batch, the critics alternating over ``--repeats`` (after a warm-up), each update
undone before the next. Printed per critic: the median critic fit and whole update, each as the
first critic's time over its own (how many times cheaper), and the explained variances, as
ratios to (differences from) the first critic's.

    python benchmarks/token_policy_update.py --critics transformer transformer_small pooled padded_mlp \\
        --fractions 0.2 --batches 6 --repeats 2
"""

from __future__ import annotations

import argparse
import copy
import statistics
import time
from pathlib import Path

import torch
from hydra import compose, initialize_config_dir
from tensordict import TensorDict, TensorDictBase
from torchrl.envs.utils import ExplorationType, set_exploration_type
from torchrl.objectives.value.functional import reward2go

from unipolicy_rl.envs.tokens import ACTION_MASK, TOKEN_MASK, TOKEN_PARENT, TOKENS
from unipolicy_rl.objectives import (
    TRPOLoss,
    TRPOStepResult,
    TRPOUpdater,
    TrustRegion,
    explained_variance,
    fit_critic,
    natural_gradient_step,
)
from unipolicy_rl.token_networks import (
    TokenTransformerSettings,
    make_padded_mlp_actor,
    make_padded_mlp_critic,
    make_token_transformer_actor,
    make_token_transformer_critic,
)

EPISODE_LENGTH = 100
CONF = Path(__file__).resolve().parents[1] / "conf"
# --critics: name -> the config overrides (beside robot=grammar policy=token_transformer) that build it.
SMALL_TRANSFORMER = "{_target_:unipolicy_rl.token_networks.TokenTransformerSettings,d_model:32,layers:1,feedforward:64}"
CRITIC_VARIANTS = {
    "transformer": ["policy.critic=transformer", "policy.critic_network=null"],  # today's: policy.network's sizes
    "transformer_small": ["policy.critic=transformer", f"policy.critic_network={SMALL_TRANSFORMER}"],
    "pooled": ["policy.critic=pooled"],
    "padded_mlp": ["policy.critic=padded_mlp"],
}
# Two morphologies: parents per real link (-1 the root); a 7-link quadruped and an 11-link hexapod.
ROBOTS = ([-1, 0, 0, 0, 0, 1, 2], [-1, 0, 0, 0, 0, 0, 0, 1, 2, 3, 4])


def token_batch(samples: int, tokens: int, features: int) -> TensorDict:
    """``[samples // 100, 100]`` steps, robots alternating by episode, with random features."""
    envs = samples // EPISODE_LENGTH
    parent = torch.full((envs, EPISODE_LENGTH, tokens), -1, dtype=torch.int64)
    for env in range(envs):
        parents = ROBOTS[env % len(ROBOTS)]
        parent[env, :, : len(parents)] = torch.tensor(parents)
    mask = torch.zeros(envs, EPISODE_LENGTH, tokens, dtype=torch.bool)
    for env in range(envs):
        mask[env, :, : len(ROBOTS[env % len(ROBOTS)])] = True
    done = torch.zeros(envs, EPISODE_LENGTH, 1, dtype=torch.bool)
    done[:, -1] = True

    def observation():
        return {TOKENS: torch.randn(envs, EPISODE_LENGTH, tokens, features), TOKEN_MASK: mask, TOKEN_PARENT: parent}

    return TensorDict({**observation(), ACTION_MASK: mask & (parent >= 0),
                       "next": TensorDict({**observation(), "reward": torch.randn(envs, EPISODE_LENGTH, 1),
                                           "done": done, "terminated": done.clone()}, [envs, EPISODE_LENGTH])},
                      [envs, EPISODE_LENGTH])


def architectures(tokens: int, features: int) -> dict[str, tuple]:
    transformer = TokenTransformerSettings()
    graph = TokenTransformerSettings(graph_attention=True)
    return {
        "token_transformer": (make_token_transformer_actor(features, transformer, -0.5),
                              make_token_transformer_critic(features, transformer)),
        "token_transformer graph": (make_token_transformer_actor(features, graph, -0.5),
                                    make_token_transformer_critic(features, graph)),
        "token_mlp": (make_padded_mlp_actor(features, tokens, (64, 64), "tanh", -0.5),
                      make_padded_mlp_critic(features, tokens, (64, 64), "tanh")),
    }


def timed_update(updater: TRPOUpdater, batch: TensorDict) -> tuple[float, float, TRPOStepResult]:
    """(policy step seconds, whole update seconds, the step's result) on fresh copies of ``batch``."""
    loss = updater.loss_module
    with torch.no_grad(), set_exploration_type(ExplorationType.RANDOM):
        batch = loss.actor_network(batch.clone())  # actions and behaviour loc/scale of this policy
    step_batch = batch.clone()
    loss.compute_advantage(step_batch)
    flat = step_batch.reshape(-1)
    advantage = loss.advantage(flat)
    state = {name: param.detach().clone() for name, param in loss.actor_network_params.items(True, True)}
    start = time.perf_counter()
    result = natural_gradient_step(loss, flat, advantage=advantage, trust_region=updater.trust_region)
    step_seconds = time.perf_counter() - start
    with torch.no_grad():  # back to the behaviour policy before the whole update
        for name, param in loss.actor_network_params.items(True, True):
            param.copy_(state[name])
    start = time.perf_counter()
    updater.update(batch)
    return step_seconds, time.perf_counter() - start, result


def critic_config(name: str, fisher_fraction: float, overrides: list[str]):
    with initialize_config_dir(str(CONF), version_base=None):
        return compose("config", overrides=["robot=grammar", "policy=token_transformer",
                                             f"algo.fisher_fraction={fisher_fraction}", *CRITIC_VARIANTS[name],
                                             *overrides])


def reward_to_go(batch: TensorDictBase, gamma: float) -> torch.Tensor:
    """``[envs, time, 1]`` discounted reward-to-go of each episode, no bootstrap at its end."""
    return reward2go(batch["next", "reward"], batch["next", "done"], gamma, time_dim=-2)


def collect_batches(env, learner, count: int, episode_length: int) -> list[TensorDictBase]:
    """``count`` batches of one episode per robot by ``learner``'s policy (never updated), its
    normaliser refreshed after each batch as train.py does; the batches hold the raw tokens."""
    batches = []
    for _ in range(count):
        with torch.no_grad(), set_exploration_type(ExplorationType.RANDOM):
            batch = env.rollout(episode_length, learner.policy, break_when_any_done=False)
        learner.refresh_observation_normalizer(batch)
        batches.append(batch.exclude(*learner.normalizer.out_keys, ("next", *learner.normalizer.out_keys)))
    return batches


def batch_explained_variance(learner, batch: TensorDictBase, target: torch.Tensor) -> float:
    """The critic's explained variance on ``batch`` (raw tokens, normalised here) against ``target``."""
    with torch.no_grad():
        value = learner.critic(learner.normalizer(batch.clone()))["state_value"]
    return explained_variance(value, target)


def compare_critics(args) -> None:
    from unipolicy_rl.env_factories import make_morphology_env
    from unipolicy_rl.factories import make_learner

    unknown = sorted(set(args.critics) - set(CRITIC_VARIANTS))
    if unknown:
        raise SystemExit(f"unknown critics {unknown}; --critics takes {list(CRITIC_VARIANTS)}")
    configs = {name: critic_config(name, args.fractions[0], args.overrides) for name in args.critics}
    cfg = next(iter(configs.values()))
    algo, episode_length = cfg.algo, cfg.robot.episode_length
    env = make_morphology_env(cfg, args.samples // episode_length)
    env.set_seed(args.seed)
    max_tokens, features = env.observation_spec[TOKENS].shape[-2:]

    def learner_for(config):
        torch.manual_seed(args.seed)  # the same actor beside every critic (built first, from the same seed)
        return make_learner(config, features, max_tokens)

    start = time.perf_counter()
    batches = collect_batches(env, learner_for(cfg), args.batches + 1, episode_length)
    env.close()
    print(f"collected {len(batches)} batches of {args.samples} steps in {time.perf_counter() - start:.0f} s")
    # Per batch: its flat samples, their reward-to-go, and one split (the same for every critic).
    flats = [batch.reshape(-1) for batch in batches]
    targets = [reward_to_go(batch, algo.gamma).reshape(-1, 1) for batch in batches]
    order = [torch.randperm(flat.numel(), generator=torch.Generator().manual_seed(args.seed * 1000 + index))
             for index, flat in enumerate(flats)]
    held = [permutation[: int(args.held_out_share * permutation.numel())] for permutation in order]
    fitted = [permutation[held_out.numel():] for permutation, held_out in zip(order, held, strict=True)]
    learners = {name: learner_for(config) for name, config in configs.items()}
    fits: dict[str, list[float]] = {name: [] for name in learners}
    same: dict[str, list[float]] = {name: [] for name in learners}
    following: dict[str, list[float]] = {name: [] for name in learners}
    for name, learner in learners.items():
        for index in range(args.batches):
            flat, target = flats[index], targets[index]
            data = learner.normalizer(flat[fitted[index]].clone())
            data.set(learner.loss.tensor_keys.value_target, target[fitted[index]])
            start = time.perf_counter()
            result = fit_critic(learner.loss, data, learner.updater.critic_optimizer, algo.critic_epochs,
                                algo.critic_minibatch_size, learner.updater.generator)
            fits[name].append(time.perf_counter() - start)
            assert result.fitted, result.skip_reason
            learner.refresh_observation_normalizer(batches[index])
            same[name].append(batch_explained_variance(learner, flat[held[index]], target[held[index]]))
            following[name].append(batch_explained_variance(learner, flats[index + 1], targets[index + 1]))
    updates: dict[str, list[float]] = {name: [] for name in learners}
    last = batches[args.batches - 1]
    for repeat in range(args.repeats + 1):
        for name, learner in learners.items():
            state = copy.deepcopy(learner.state_dict())
            batch = learner.normalizer(last.clone())
            start = time.perf_counter()
            learner.update(batch)
            if repeat:  # the first is a warm-up
                updates[name].append(time.perf_counter() - start)
            learner.load_state_dict(state)
    fitted_samples = fitted[0].numel()
    print(f"{args.batches} batches of {args.samples} steps ({fitted_samples} fitted, {held[0].numel()} held out), "
          f"{max_tokens} token slots of {features} features, fisher_fraction {args.fractions[0]:g}, seed {args.seed}; "
          f"medians (fits "
          f"over the {args.batches} batches, updates over {args.repeats} repeats); explained variance: the last "
          f"fit's and the mean over fits; ratios against the first critic")
    reference = next(iter(learners))
    fit_ref, update_ref = statistics.median(fits[reference]), statistics.median(updates[reference])
    print(f"| critic | parameters | critic fit ({fitted_samples} samples) | cheaper | whole update | cheaper | "
          "EV held out, last | / first | EV held out, mean | / first | EV next batch, mean | - first |")
    print("|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|")
    for name, learner in learners.items():
        parameters = sum(p.numel() for p in learner.critic.parameters())
        fit, update = statistics.median(fits[name]), statistics.median(updates[name])
        last_ev, mean_ev = same[name][-1], statistics.mean(same[name])
        next_ev = statistics.mean(following[name])
        print(f"| {name} | {parameters} | {fit:.2f} s | {fit_ref / fit:.1f} | {update:.2f} s | "
              f"{update_ref / update:.1f} | {last_ev:.3f} | {last_ev / same[reference][-1]:.2f} | {mean_ev:.3f} | "
              f"{mean_ev / statistics.mean(same[reference]):.2f} | {next_ev:.3f} | "
              f"{next_ev - statistics.mean(following[reference]):+.3f} |")
    for label, variances in (("held-out samples of the fitted batch", same), ("the next batch", following)):
        print(f"explained variance after each fit, {label}:")
        for name, values in variances.items():
            print(f"  {name:18s} " + " ".join(f"{value:6.3f}" for value in values))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--samples", type=int, default=1000)
    parser.add_argument("--tokens", type=int, default=12)
    parser.add_argument("--features", type=int, default=24)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--fractions", type=float, nargs="+", default=[1.0],
                        help="fisher_fraction values to time (default 1.0: the whole batch)")
    parser.add_argument("--architectures", nargs="+", default=None, help="a subset of the architectures")
    parser.add_argument("--critics", nargs="+", default=None,
                        help=f"compare these critics on the grammar env's data instead ({list(CRITIC_VARIANTS)})")
    parser.add_argument("--batches", type=int, default=6, help="--critics: batches, one fit each")
    parser.add_argument("--held-out-share", type=float, default=0.2,
                        help="--critics: the share of each batch's samples held out of its fit")
    parser.add_argument("--seed", type=int, default=0, help="--critics: seeds the robots, the networks and the splits")
    parser.add_argument("--overrides", nargs="*", default=[],
                        help="--critics: more config overrides, e.g. robot.training_morphologies=8")
    args = parser.parse_args()
    torch.set_num_threads(1)
    torch.manual_seed(0)
    if args.critics:
        compare_critics(args)
        return
    chosen = architectures(args.tokens, args.features)
    names = args.architectures or list(chosen)
    updaters = {}
    for name in names:
        for fraction in args.fractions:
            actor, critic = copy.deepcopy(chosen[name])  # every fraction starts from the same networks
            updaters[name, fraction] = TRPOUpdater(TRPOLoss(actor, critic), trust_region=TrustRegion(
                fisher_fraction=fraction), generator=torch.Generator().manual_seed(0))
    times: dict[tuple[str, float], list[tuple[float, float, TRPOStepResult]]] = {key: [] for key in updaters}
    for repeat in range(args.repeats + 1):
        batch = token_batch(args.samples, args.tokens, args.features)
        for key, updater in updaters.items():
            result = timed_update(updater, batch)
            if repeat:  # the first is a warm-up
                times[key].append(result)
    print(f"{args.samples} steps, {args.tokens} tokens of {args.features} features, median of {args.repeats}:")
    max_kl = TrustRegion().max_kl
    for (name, fraction), results in times.items():
        parameters = sum(p.numel() for p in updaters[name, fraction].loss_module.actor_parameters())
        step = statistics.median(result[0] for result in results)
        update = statistics.median(result[1] for result in results)
        whole = statistics.median(result[0] for result in times[name, args.fractions[0]])
        accepted = sum(result[2].accepted for result in results)
        worst_kl = max(result[2].kl for result in results)
        tries = statistics.mean(result[2].line_search_tries for result in results)
        print(f"  {name:24s} fisher_fraction {fraction:4.2f}  actor parameters {parameters:6d}  policy step "
              f"{step:6.2f} s ({step / whole:4.2f} of fraction {args.fractions[0]:g})  whole update {update:6.2f} s  "
              f"accepted {accepted}/{len(results)}, max KL {worst_kl / max_kl:4.2f} x max_kl, "
              f"line-search tries {tries:.1f}")


if __name__ == "__main__":
    main()
