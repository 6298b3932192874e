"""Every setting a run reads, checked when the run starts, before any robot is built.

A typo should cost a second, not a training run: ``epochs=-1`` would train nothing and save an
untrained policy, ``algo.gamma=1.5`` would train with a discount above one, and a bad
``evaluation.grid`` would only fail at the final evaluation, hours later. Settings that
have their own dataclass (design, robot, physics, reward, trust region, world model parts)
are built here once so their own checks run now; the plain numbers of the run are checked
by the rules below. Every error names the config key and the value.

Each check lives in one place: a setting with a dataclass or constructor checks itself there,
a plain value has its rule in :data:`RULES` (or :data:`JOINT_RULES` when it is checked against
another). The factories rely on :func:`validate_config` having run (train.py calls it first);
the few that are library entry points run the rules of the keys they read through
:func:`check_settings`, the same rules, so a direct call fails as clearly.
"""

from __future__ import annotations

import math
import multiprocessing
from collections.abc import Callable

from hydra.utils import instantiate
from omegaconf import DictConfig, OmegaConf

from unipolicy_rl.collectors.distributed import BACKENDS as COLLECTOR_BACKENDS
from unipolicy_rl.collectors.distributed import require_ray
from unipolicy_rl.env_factories import GRAMMAR_SIDES, ROBOT_KINDS, env_kind, gym_task, robot_kind, steps_per_env_epoch
from unipolicy_rl.envs.gym_task import ENV_KINDS, GYM
from unipolicy_rl.envs.morphology import HINGE_TYPES, SAMPLINGS
from unipolicy_rl.envs.simulation import OBSERVATIONS
from unipolicy_rl.envs.slot_layout import TOKEN_LAYOUTS
from unipolicy_rl.envs.tokens import MORPHOLOGY
from unipolicy_rl.networks import ACTIVATIONS
from unipolicy_rl.objectives.updater import CRITIC_FITS
from unipolicy_rl.observation_statistics import REFRESH_MODES
from unipolicy_rl.policy import FLAT_POLICIES, ON_POLICY_ALGOS, TOKEN_POLICIES, TOKEN_POLICY_ALGOS, token_critic
from unipolicy_rl.registry import LEARNER_NAMES, OFF_POLICY_LEARNERS, SOURCE_KINDS

# The batch keys algo.advantage_groups may name (TRPOLoss's advantage_groups): samples of one value
# have their advantages standardised together.
ADVANTAGE_GROUPS = (MORPHOLOGY,)


def _integer(minimum: int) -> Callable[[object], str | None]:
    def check(value) -> str | None:
        if isinstance(value, bool) or not isinstance(value, int) or value < minimum:
            return f"must be an integer >= {minimum}"
        return None

    return check


def _number(low: float, high: float, low_open: bool = False, high_open: bool = False) -> Callable[[object], str | None]:
    def check(value) -> str | None:
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
            return "must be a finite number"
        if value < low or (low_open and value == low) or value > high or (high_open and value == high):
            return f"must lie in {'(' if low_open else '['}{low:g}, {high:g}{')' if high_open else ']'}"
        return None

    return check


def _flag(value) -> str | None:
    return None if isinstance(value, bool) else "must be true or false"


def _one_of(choices) -> Callable[[object], str | None]:
    return lambda value: None if value in choices else f"must be one of {sorted(choices)}"


def _optional(rule: Callable[[object], str | None]) -> Callable[[object], str | None]:
    def check(value) -> str | None:
        problem = None if value is None else rule(value)
        return None if problem is None else f"{problem} or null"

    return check


def _some_of(choices) -> Callable[[object], str | None]:
    """A non-empty list of values from ``choices``."""

    def check(value) -> str | None:
        if isinstance(value, str) or not hasattr(value, "__iter__") or not list(value) or \
                not set(value) <= set(choices):
            return f"must be a non-empty list of {sorted(choices)}"
        return None

    return check


def _sizes(value) -> str | None:
    if not all(isinstance(size, int) and not isinstance(size, bool) and size >= 1 for size in value):
        return "must be a list of positive integers"
    return None


POSITIVE = _integer(1)
INF = math.inf
# key -> rule, for the plain values a run reads (dataclass-backed settings check themselves).
RULES: dict[str, Callable[[object], str | None]] = {
    "seed": _integer(0),
    "epochs": POSITIVE,
    "episodes_per_epoch": POSITIVE,
    "workers": POSITIVE,
    "collector.backend": _one_of(set(COLLECTOR_BACKENDS)),
    "checkpoint_every": POSITIVE,
    "progress_bar": _flag,
    "source.kind": _one_of(set(SOURCE_KINDS)),
    "algo.name": _one_of(set(LEARNER_NAMES)),
    "algo.actor_hidden": _sizes,
    "algo.critic_hidden": _sizes,
    "algo.activation": _one_of(set(ACTIVATIONS)),
    "evaluation.every_steps": _integer(0),  # 0: no periodic evaluation
    "evaluation.dense_until": _integer(0),
    "evaluation.then_every_steps": POSITIVE,
    "evaluation.grid": POSITIVE,
    "evaluation.episodes": POSITIVE,
    "evaluation.morphologies": _one_of(set(GRAMMAR_SIDES)),  # read by robot=grammar only
    "evaluation.morphology_grid": POSITIVE,
    "policy.name": _one_of(set(FLAT_POLICIES + TOKEN_POLICIES)),
    "robot.episode_length": POSITIVE,
}

# robot kind -> rules of the keys only that robot has (the grammar's split checks itself when built).
ROBOT_RULES: dict[str, dict[str, Callable[[object], str | None]]] = {
    "vertebrate": {
        "robot.observation": _one_of(set(OBSERVATIONS)),
        "robot.append_design": _flag,
    },
    "grammar": {
        "robot.morphologies": _one_of(set(GRAMMAR_SIDES)),
        "robot.sampling": _one_of(set(SAMPLINGS)),
        "robot.max_links": _optional(POSITIVE),
        "robot.driven_joints": _optional(_some_of(HINGE_TYPES)),
        "robot.design_in_tokens": _flag,
        "robot.token_layout": _one_of(set(TOKEN_LAYOUTS)),
        "robot.evaluation_every_steps": POSITIVE,
        "robot.clock_frequency": _optional(_number(0.0, INF, low_open=True, high_open=True)),
    },
}


# The keys every on-policy learner reads (GAE, the critic fit, the normaliser), checked by name.
_ON_POLICY_RULES: dict[str, Callable[[object], str | None]] = {
    "algo.init_log_std": _number(-20.0, 5.0),
    "algo.gamma": _number(0.0, 1.0, low_open=True),
    "algo.lmbda": _number(0.0, 1.0),
    "algo.normalize_advantage": _flag,
    "algo.advantage_groups": _optional(_one_of(set(ADVANTAGE_GROUPS))),
    "algo.entropy_coeff": _number(0.0, INF, high_open=True),
    "algo.critic_lr": _number(0.0, INF, low_open=True, high_open=True),
    "algo.critic_epochs": POSITIVE,
    "algo.critic_minibatch_size": POSITIVE,
    "algo.critic_fit": _one_of(set(CRITIC_FITS)),
    "algo.max_consecutive_skips": POSITIVE,
    "algo.normalizer_refresh": _one_of(set(REFRESH_MODES)),
}
# algo.name -> rules of the keys only that learner reads. TRPO's trust region, PPO's clipped step and
# an off-policy learner's settings are dataclasses that check themselves (settings.learner_settings).
ALGO_RULES: dict[str, dict[str, Callable[[object], str | None]]] = {
    **{name: _ON_POLICY_RULES for name in ON_POLICY_ALGOS},
    # (distillation's own numbers and teachers: DistillationSettings checks them)
    "distill": {"algo.init_log_std": _number(-20.0, 5.0)},
}


def _equal_shares(cfg: DictConfig) -> str | None:
    if cfg.episodes_per_epoch % cfg.workers:
        return (f"episodes_per_epoch ({cfg.episodes_per_epoch}) must be a multiple of workers ({cfg.workers}): "
                f"each worker steps an equal share of the robots")
    return None


def _gym_task_alone(cfg: DictConfig) -> str | None:
    """``env=gym`` runs one gymnasium env in this process: the walker's robots, designs, worker
    processes and teachers have no meaning there, and each is refused by name."""
    if env_kind(cfg) not in ENV_KINDS:
        return f"env.kind must be one of {list(ENV_KINDS)}, got {env_kind(cfg)!r}"
    if env_kind(cfg) != GYM:
        return None
    walker_only = {
        "robot": (robot_kind(cfg) != "vertebrate", f"robot={robot_kind(cfg)}"),
        "design": (list(cfg.design.length_range) != list(cfg.design_space.length_range)
                   or list(cfg.design.density_range) != list(cfg.design_space.density_range),
                   "a design other than the SE range (design=de, source=de)"),
        "workers": (cfg.workers != 1, f"workers={cfg.workers}"),
        "episodes_per_epoch": (cfg.episodes_per_epoch != 1,
                               f"episodes_per_epoch={cfg.episodes_per_epoch} (set env.frames_per_epoch)"),
        "collector.backend": (cfg.collector.backend != "process", f"collector.backend={cfg.collector.backend}"),
        "algo": (cfg.algo.name == "distill", "algo=distill (it teaches grammar robots)"),
    }
    for _, (bad, what) in walker_only.items():
        if bad:
            return f"{what} is the walker's and has no meaning with env=gym (a gymnasium task, env.id={cfg.env.id})"
    return None


def _known_robot(cfg: DictConfig) -> str | None:
    if robot_kind(cfg) not in ROBOT_KINDS:
        return f"robot.kind must be one of {list(ROBOT_KINDS)}, got {robot_kind(cfg)!r}"
    return None


def _policy_reads_the_robot(cfg: DictConfig) -> str | None:
    """A flat policy needs the vertebrate's observation, a token policy the grammar's tokens."""
    name = cfg.policy.name
    if robot_kind(cfg) == "grammar" and name in FLAT_POLICIES:
        return (f"policy={name} reads one robot's flat observation, but robot=grammar observes robots of many "
                f"morphologies as padded link tokens: use a token policy (policy={' or policy='.join(TOKEN_POLICIES)})")
    if robot_kind(cfg) != "grammar" and name in TOKEN_POLICIES:
        return (f"policy={name} reads link tokens, which robot={robot_kind(cfg)} does not write: train it with "
                f"robot=grammar (the vertebrate is one of the grammar's morphologies), or use policy=mlp here")
    return None


def _clock_is_read(cfg: DictConfig) -> str | None:
    """The gait clock is an input of the modular policy only, and no world model predicts it."""
    frequency = OmegaConf.select(cfg, "robot.clock_frequency", default=None)
    if robot_kind(cfg) != "grammar" or frequency is None:
        return None
    if cfg.policy.name != "token_modular":
        return (f"robot.clock_frequency={frequency} adds a gait clock only policy=token_modular reads, and "
                f"policy={cfg.policy.name} would ignore it: use policy=token_modular or robot.clock_frequency=null")
    if cfg.source.kind == "model":
        return (f"robot.clock_frequency={frequency} with source={cfg.source.get('name', cfg.source.kind)}: the world "
                f"model's imagined steps carry no clock; train on the real robots (source=se) or set "
                f"robot.clock_frequency=null")
    return None


def _token_critic_builds(cfg: DictConfig) -> str | None:
    """A token policy's ``policy.critic`` is a known critic, and a transformer critic has sizes."""
    if cfg.policy.name not in TOKEN_POLICIES:
        return None
    try:
        token_critic(cfg)
    except ValueError as error:
        return str(error)
    return None


def _grammar_learns_on_policy(cfg: DictConfig) -> str | None:
    if robot_kind(cfg) == "grammar" and cfg.algo.name not in TOKEN_POLICY_ALGOS:
        return (f"algo={cfg.algo.name} with robot=grammar: the token policies are Gaussians that only "
                f"algo={' or algo='.join(TOKEN_POLICY_ALGOS)} train")
    return None


def _distillation_has_specialists(cfg: DictConfig) -> str | None:
    """Distillation teaches a token policy the specialists of grammar robots, on real steps."""
    if cfg.algo.name != "distill":
        return None
    if robot_kind(cfg) != "grammar":
        return (f"algo=distill teaches a token policy the specialists of robot=grammar's morphologies, and "
                f"robot={robot_kind(cfg)} is one robot: train it with algo=trpo")
    if cfg.source.kind != "real":
        return (f"algo=distill labels the student's real steps with its specialists' actions; "
                f"source={cfg.source.get('name', cfg.source.kind)} trains on a world model's: use source=se")
    return None


def _advantage_groups_exist(cfg: DictConfig) -> str | None:
    """``algo.advantage_groups=morphology`` needs a robot that writes its morphology, and a normalisation."""
    groups = cfg.algo.get("advantage_groups")  # (on-policy algos only)
    if groups is None:
        return None
    if not cfg.algo.normalize_advantage:
        return (f"algo.advantage_groups={groups} standardises the advantages within groups, but "
                f"algo.normalize_advantage=false standardises nothing: drop one of them")
    if groups == MORPHOLOGY and robot_kind(cfg) != "grammar":
        return (f"algo.advantage_groups={groups} groups the batch by the robot's morphology, which only "
                f"robot=grammar writes (robot={robot_kind(cfg)} is one build): use algo.advantage_groups=null")
    return None


def _world_model_reads_the_robot(cfg: DictConfig) -> str | None:
    """A model source's world model must predict the state the robot's env writes: the
    vertebrate's flat state, or a grammar robot's link tokens (world_model.model_state=tokens,
    the TokenEnsemble that world_model=moe selects with robot=grammar)."""
    from unipolicy_rl.world_models.token_layout import TOKEN_STATE  # (here: the world models import torch's stack)

    world_model = cfg.get("world_model")
    if cfg.source.kind != "model" or world_model is None:
        return None  # (a missing group is _model_source_groups' to report)
    state = world_model.get("model_state")
    model = str(OmegaConf.select(world_model, "model._target_")).rsplit(".", 1)[-1]
    source = cfg.source.name
    if robot_kind(cfg) == "grammar" and state != TOKEN_STATE:
        return (f"source={source} with robot=grammar: its world model, {model} (world_model.model_state={state}), "
                f"predicts one robot's flat state, and robot=grammar observes robots of many morphologies as "
                f"link tokens; the model conditioned on the morphology is world_model=moe's with robot=grammar "
                f"(TokenEnsemble, world_model.model_state={TOKEN_STATE}): use source=moe with world_model=moe")
    if robot_kind(cfg) != "grammar" and state == TOKEN_STATE:
        return (f"world_model.model_state={TOKEN_STATE} ({model}) models link tokens, which "
                f"robot={robot_kind(cfg)} does not write: train it with robot=grammar, or use the flat "
                f"world_model=moe here")
    return None


def _model_source_groups(cfg: DictConfig) -> str | None:
    """A model source has a world model and an imagination; a real source reads neither, so one
    chosen with it would be ignored without a word (but for an off-policy learner's own MBPO
    imagination, which it checks itself)."""
    if cfg.source.kind == "model":
        for group in ("world_model", "imagination"):
            if cfg.get(group) is None:
                return (f"a model-based source needs a {group} config (e.g. world_model=moe, which selects its "
                        f"imagination)")
        return None
    source = cfg.source.name
    if cfg.get("world_model") is not None:
        return (f"world_model is read by a model-based source only, and source={source} trains on the real robots: "
                f"drop world_model=..., or choose a model source (source=moe or source=pce, which select their "
                f"world_model)")
    imagination = cfg.get("imagination")
    if imagination is not None and not (cfg.algo.name not in ON_POLICY_ALGOS and _mbpo_shaped(imagination)):
        return (f"imagination is read by a model-based source only, and source={source} trains on the real robots: "
                f"drop imagination=..., or choose a model source (source=moe or source=pce)")
    return None


def _mbpo_shaped(imagination: DictConfig) -> bool:
    """An off-policy learner's own imagination (imagination=mbpo: one imagined batch per fit, the
    real batches training too), which such a learner's config may carry whatever its source."""
    stopping = imagination.get("stopping") or {}
    return bool(imagination.get("train_on_real")) and stopping.get("kind") == "fixed" and \
        stopping.get("max_updates") == 1


def _critic_fit_runs_here(cfg: DictConfig) -> str | None:
    """A lagged critic's pending fit is applied at the epoch's normaliser refresh; a policy update on
    the real batch comes before it and would read the critic half-way (and a resumed run would not).
    The fit's process owns the fit's generator, which PPO's step shares, and is a fork."""
    if cfg.algo.name == "ppo" and cfg.algo.critic_fit == "process":
        return ("algo.critic_fit=process with algo=ppo: PPO's minibatch shuffles draw from the critic fit's generator, "
                "which the fit's process takes over; use algo.critic_fit=inline or lagged")
    if (cfg.algo.name in ON_POLICY_ALGOS and cfg.algo.critic_fit != "inline" and cfg.source.kind == "model"
            and cfg.imagination.train_on_real):
        default = (f" (source={cfg.source.get('name', cfg.source.kind)}'s default)"
                   if cfg.source.get("critic_fit") == cfg.algo.critic_fit else "")
        return (f"algo.critic_fit={cfg.algo.critic_fit}{default} with imagination.train_on_real=true: the update on "
                f"each real batch would read a critic whose last fit is still pending; add algo.critic_fit=inline")
    if (cfg.algo.name in ON_POLICY_ALGOS and cfg.algo.critic_fit == "process"
            and "fork" not in multiprocessing.get_all_start_methods()):
        return ("algo.critic_fit=process forks the critic's fit, and this platform cannot fork; "
                "add algo.critic_fit=lagged (the same learning, in one process)")
    return None


def _policy_average_fits(cfg: DictConfig) -> str | None:
    """``algo.policy_average.decay`` is off or in (0, 1), and there is an on-policy actor to average."""
    from unipolicy_rl.learners.policy_average import averaging  # (here: learners import torch's stack)

    decay = OmegaConf.select(cfg, "algo.policy_average.decay")
    try:
        on = averaging(decay)
    except ValueError as error:
        return str(error)
    if on and cfg.algo.name not in ON_POLICY_ALGOS:
        return (f"algo.policy_average.decay={decay} averages an on-policy learner's actor "
                f"(algo={' or algo='.join(ON_POLICY_ALGOS)}), not algo={cfg.algo.name}'s: drop it")
    return None


def _mean_action_robots_fit(cfg: DictConfig) -> str | None:
    """``collector.mean_action_robots`` (unipolicy_rl.collectors.mean_action): fewer than the epoch's
    robots, the first rows of one collector's batch, and never under an on-policy step on the real
    batch, whose log-probabilities they do not sample."""
    robots = OmegaConf.select(cfg, "collector.mean_action_robots", default=0)
    if isinstance(robots, bool) or not isinstance(robots, int) or robots < 0:
        return f"collector.mean_action_robots must be a non-negative integer (robots per real epoch), got {robots!r}"
    if robots == 0:
        return None
    what = f"collector.mean_action_robots={robots}"
    if env_kind(cfg) == GYM:
        return f"{what} picks robots of the walker's epoch; env=gym runs one env (env.id={cfg.env.id})"
    if robots >= cfg.episodes_per_epoch:
        return (f"{what} leaves no robot of episodes_per_epoch={cfg.episodes_per_epoch} to sample: the policy's "
                "exploration comes from those")
    if cfg.workers != 1 or cfg.collector.backend != "process":
        return (f"{what} acts on the first rows of one collector's batch: set workers=1 "
                f"(got workers={cfg.workers}, collector.backend={cfg.collector.backend})")
    on_policy = cfg.algo.name in ON_POLICY_ALGOS
    if on_policy and cfg.source.kind == "real":
        return (f"{what} with algo={cfg.algo.name} on the real env: its update reads the real batch as samples of "
                "the policy, which the mean-action robots are not (a model source, or an off-policy learner, can)")
    if on_policy and OmegaConf.select(cfg, "imagination.train_on_real", default=False):
        return (f"{what} with imagination.train_on_real=true: that step reads the real batch as samples of the "
                "policy, which the mean-action robots are not")
    return None


def _update_every_fits(cfg: DictConfig) -> str | None:
    """``algo.update_every`` (an off-policy learner's steps between rounds of gradient steps while the
    epoch is collected): a divisor of each env's steps per epoch, with the learner in the process
    that collects."""
    every = OmegaConf.select(cfg, "algo.update_every", default=None)
    if every is None:
        return None
    if isinstance(every, bool) or not isinstance(every, int) or every < 1:
        return (f"algo.update_every must be an integer >= 1 (env steps between rounds of gradient steps) or null, "
                f"got {every!r}")
    if cfg.algo.name not in OFF_POLICY_LEARNERS:
        return (f"algo.update_every={every} steps an off-policy learner (algo={' or algo='.join(OFF_POLICY_LEARNERS)}) "
                f"between chunks of the epoch; algo={cfg.algo.name} learns from whole epochs: drop it")
    steps = steps_per_env_epoch(cfg)
    if steps % every:
        where = "env.frames_per_epoch" if env_kind(cfg) == GYM else "robot.episode_length"
        return (f"algo.update_every={every} must divide each env's steps per epoch ({where}={steps}): the epoch is "
                f"collected in chunks of that many steps")
    if cfg.workers != 1 or cfg.collector.backend != "process":
        return (f"algo.update_every={every} steps the learner between chunks of the epoch as they are collected, "
                f"which needs the policy in this process: set workers=1 (got workers={cfg.workers}, "
                f"collector.backend={cfg.collector.backend})")
    return None


def _refit_every_fits(cfg: DictConfig) -> str | None:
    """``imagination.refit_every`` (MBPO's refits while the epoch is collected): a world model, an
    off-policy learner that learns between the epoch's chunks, refits on the chunks' boundaries
    within the epoch, and the loop's own fit after every epoch, in this thread."""
    every = OmegaConf.select(cfg, "imagination.refit_every", default=None)
    if every is None:
        return None
    if isinstance(every, bool) or not isinstance(every, int) or every < 1:
        return f"imagination.refit_every must be a positive integer (env steps between refits) or null, got {every!r}"
    what = f"imagination.refit_every={every}"
    if cfg.source.kind != "model":
        return (f"{what} refits a world model while the epoch is collected, and source={cfg.source.name} has none: "
                f"drop it, or choose a model source (source=moe or source=pce)")
    if cfg.algo.name not in OFF_POLICY_LEARNERS:
        return (f"{what} fills an off-policy learner's model buffer as the epoch is collected (MBPO: "
                f"algo={' or algo='.join(OFF_POLICY_LEARNERS)}); algo={cfg.algo.name} imagines after each epoch: "
                f"drop it")
    update_every = OmegaConf.select(cfg, "algo.update_every", default=None)
    if update_every is None:
        return (f"{what} needs the learner to learn while the epoch is collected: set algo.update_every (env steps "
                f"between its rounds of gradient steps; MBPO: 1)")
    if isinstance(update_every, int) and every % update_every:
        return (f"{what} must be a multiple of algo.update_every={update_every}: the refits fall between the "
                f"epoch's chunks")
    steps = steps_per_env_epoch(cfg)
    if steps % every:
        where = "env.frames_per_epoch" if env_kind(cfg) == GYM else "robot.episode_length"
        return f"{what} must divide each env's steps per epoch ({where}={steps})"
    imagination = cfg.imagination
    if imagination.get("fit_every", 1) != 1:
        return (f"{what} refits within every epoch, and imagination.fit_every={imagination.fit_every} skips the "
                f"fits after some: set imagination.fit_every=1")
    if imagination.get("background_fit", False):
        return (f"{what} fits in the training thread, between the epoch's chunks: set "
                f"imagination.background_fit=false")
    return None


# keys -> rule, for the plain values checked against each other; run after the keys' own rules,
# it returns the whole message (naming the keys and values) or None.
JOINT_RULES: dict[tuple[str, ...], Callable[[DictConfig], str | None]] = {
    ("episodes_per_epoch", "workers"): _equal_shares,
    ("source", "world_model", "imagination", "algo.name"): _model_source_groups,
    ("robot",): _known_robot,
    ("env", "robot", "design", "design_space", "workers", "episodes_per_epoch", "collector", "algo.name"):
        _gym_task_alone,
    ("robot", "policy.name"): _policy_reads_the_robot,
    ("robot", "policy.name", "source.kind"): _clock_is_read,
    ("policy",): _token_critic_builds,
    ("robot", "algo.name"): _grammar_learns_on_policy,
    ("robot", "algo.name", "source.kind"): _distillation_has_specialists,
    ("robot", "algo"): _advantage_groups_exist,
    ("robot", "source.kind", "world_model"): _world_model_reads_the_robot,
    ("algo", "source"): _critic_fit_runs_here,
    ("algo",): _policy_average_fits,
    ("collector", "env", "episodes_per_epoch", "workers", "algo.name", "source.kind", "imagination"):
        _mean_action_robots_fit,
    ("algo", "env", "robot", "workers", "collector"): _update_every_fits,
    ("imagination", "algo", "env", "robot", "source"): _refit_every_fits,
}


def check_settings(cfg: DictConfig, *keys: str) -> None:
    """Runs the rules of ``keys`` (:data:`RULES`, then each of :data:`JOINT_RULES` whose keys are
    all among them): raises ValueError naming the first bad setting (key and value).

    :func:`validate_config` runs every rule; a library entry point that reads a few plain
    settings runs theirs here, so it fails as clearly without validate_config having run.
    """
    rules = {**RULES, **ROBOT_RULES.get(robot_kind(cfg), {})}
    if "algo.name" in keys:
        rules.update(ALGO_RULES.get(_get(cfg, "algo.name"), {}))
    for key in keys:
        if key in rules:
            value = _get(cfg, key)
            problem = rules[key](value)
            if problem:
                raise ValueError(f"{key} {problem}, got {value!r}")
    for joint, rule in JOINT_RULES.items():
        if set(joint) <= set(keys):
            problem = rule(cfg)
            if problem:
                raise ValueError(problem)


def validate_config(cfg: DictConfig) -> None:
    """Raises ValueError naming the first bad setting of ``cfg`` (key and value)."""
    algo_keys = ALGO_RULES.get(cfg.algo.name, {})
    robot_keys = ROBOT_RULES.get(robot_kind(cfg), {})
    check_settings(cfg, *RULES, *algo_keys, *robot_keys, *(key for joint in JOINT_RULES for key in joint))
    # Imported here: the settings' builders import the whole training stack.
    from unipolicy_rl.collectors.imagination import check_stopping_rule
    from unipolicy_rl.device import resolve_device
    from unipolicy_rl.envs import DesignDistribution
    from unipolicy_rl.learners.off_policy import check_model_based_imagination
    from unipolicy_rl.settings import learner_settings, make_dynamics_model
    from unipolicy_rl.world_models.disagreement import check_members_disagree

    if env_kind(cfg) == GYM:
        _built("env=gym", lambda: gym_task(cfg))
    evaluation = cfg.evaluation
    _built("evaluation", lambda: DesignDistribution(tuple(evaluation.length_range), tuple(evaluation.density_range)))
    _built("design", lambda: instantiate(cfg.design))
    if robot_kind(cfg) == "grammar":
        from unipolicy_rl.env_factories import morphology_env_kwargs

        # The split (drawn once per process), its side and the padding; then the evaluated side.
        _built("robot", lambda: morphology_env_kwargs(cfg))
        _built("evaluation.morphologies", lambda: morphology_env_kwargs(cfg, cfg.evaluation.morphologies))
    else:
        _built("robot.settings", lambda: instantiate(cfg.robot.settings, _convert_="all"))
    _built("robot.physics", lambda: instantiate(cfg.robot.physics))
    _built("robot.reward", lambda: instantiate(cfg.robot.reward))
    _built("algo", lambda: learner_settings(cfg))
    _built("device", lambda: resolve_device(cfg.device))
    if cfg.collector.backend == "ray":
        try:
            require_ray(cfg.collector.ray_address)
        except ImportError as error:
            raise ValueError(f"collector.backend=ray: {error}") from None
    if cfg.source.kind == "model":  # its world_model and imagination groups are there (JOINT_RULES)
        _built("world_model.trainer", lambda: instantiate(cfg.world_model.trainer))
        imagination = _built("imagination", lambda: instantiate(cfg.imagination))
        # On the meta device: the constructor's checks run, no weights are allocated.
        model = _built("world_model.model", lambda: make_dynamics_model(cfg, device="meta"))
        check_stopping_rule(imagination.stopping, model)
        for name in ("disagreement_cut", "disagreement_penalty"):
            if getattr(imagination, name) is not None:
                check_members_disagree(model, f"imagination.{name}")
        if cfg.algo.name not in ON_POLICY_ALGOS:
            check_model_based_imagination(imagination)
        _check_adaptive_kl(cfg, imagination.adaptive_kl)


def _check_adaptive_kl(cfg: DictConfig, rule) -> None:
    """``imagination.adaptive_kl`` (checked itself when built) bounds TRPO's steps, under ``algo.max_kl``."""
    if not rule.on:
        return
    if cfg.algo.name != "trpo":
        raise ValueError(f"imagination.adaptive_kl shrinks TRPO's KL bound (algo.max_kl), and algo={cfg.algo.name} "
                         f"takes no such step: use algo=trpo, or set imagination.adaptive_kl.reference=null")
    if rule.floor > cfg.algo.max_kl:
        raise ValueError(f"imagination.adaptive_kl.floor={rule.floor} exceeds algo.max_kl={cfg.algo.max_kl}: the "
                         f"bound would never shrink; set a floor below max_kl")


def _get(cfg: DictConfig, key: str):
    node = cfg
    for part in key.split("."):
        node = node[part]
    return node


def _built(key: str, build: Callable[[], object]):
    """Builds a setting so its own checks run, prefixing any complaint with its key; returns it."""
    try:
        return build()
    except ValueError as err:
        raise ValueError(f"{key}: {err}") from None
    except Exception as err:  # Hydra wraps a constructor's error in its own
        cause = err.__cause__ or err.__context__ or err
        if isinstance(cause, ValueError):
            raise ValueError(f"{key}: {cause}") from None
        if isinstance(cause, (RuntimeError, OverflowError, MemoryError)):  # sizes no machine could hold
            raise ValueError(f"{key}: cannot be built ({type(cause).__name__}: {cause})") from None
        raise
