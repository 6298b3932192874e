"""A surrogate as a TorchRL world model, and the env that rolls a policy through it.

:func:`make_world_model` composes a :class:`Dynamics` into TorchRL's
:class:`~torchrl.modules.WorldModel`: the latent is the model's state itself (``state``), the
dynamics head predicts the next state (and whatever the model learns beside it), the decoder
derives what the policy reads (the layout's ``observation_key``), the reward head is either a
known reward or the model's learned one, and the done head ends a trajectory that terminated
(by a known termination function or the model's learned one; none by default) and truncates
one whose prediction blew up (and, with a
:class:`~unipolicy_rl.world_models.disagreement.DisagreementCut`, one whose members disagree
about the next state past its threshold; with a
:class:`~unipolicy_rl.world_models.disagreement.DisagreementPenalty`, the reward is lowered where
they disagree). :class:`ImaginedEnv` is TorchRL's
:class:`~torchrl.envs.model_based.ModelBasedEnvBase` around it, presenting the keys and specs of
the real env: the policy's observation, the design where the layout has one, ``physics_fault``
(the model's own blow-ups; copied from the env where it has the key), reward,
done/terminated/truncated, and for grammar robots (a
:class:`~unipolicy_rl.world_models.token_layout.TokenLayout`) the build keys ``token_mask``,
``token_parent``, ``action_mask``, ``morphology``, carried unchanged from each branch's real
start, beside the model's ``state`` and ``member``, so the same policy, value estimator and
learner work on imagined data as on real data.

A known reward or termination is a TensorDict module of the real env's keys: it reads any of
``observation``, ``action`` and ``("next", "observation")`` (the layout's observation key) and
writes ``("next", "reward")`` (a float ``[..., 1]``) or ``("next", "terminated")`` (a bool
``[..., 1]``), as the real env computes them (e.g. :mod:`unipolicy_rl.envs.gym_functions`). The
walker's reward is given by its :class:`~unipolicy_rl.envs.RewardWeights`: ``walking_reward`` of
the next state, whose first numbers are the base's in every walker layout.
"""

from __future__ import annotations

from collections.abc import Callable

import torch
from tensordict import TensorDict, TensorDictBase
from tensordict.nn import TensorDictModule, TensorDictModuleBase, TensorDictSequential
from torch import nn
from torchrl.data import Categorical, Composite, Unbounded
from torchrl.envs import EnvBase
from torchrl.envs.model_based import ModelBasedEnvBase
from torchrl.modules import WorldModel

from unipolicy_rl.envs.limits import EXPLOSION_LIMIT, healthy_rows
from unipolicy_rl.envs.reward import RewardWeights, walking_reward
from unipolicy_rl.world_models.disagreement import (
    DISAGREEMENT,
    DISAGREEMENT_CUT,
    DISAGREEMENT_PENALTY,
    CutDoneHead,
    DisagreementCut,
    DisagreementPenalty,
    MemberDisagreement,
    PenalizedReward,
    member_predictions,
)
from unipolicy_rl.world_models.dynamics import REWARD, TERMINATED, Dynamics, learned_outputs

# A start state: the model's state (and design, build keys; once assigned, the member that predicts it).
StartSampler = Callable[[int], TensorDictBase]
# ``reward=`` / ``termination=``: the model's learned output, not a known function.
LEARNED = "learned"
# Under "next": what the dynamics head predicts of each learned output (before the heads read it).
LEARNED_KEYS = {REWARD: "learned_reward", TERMINATED: "learned_terminated"}
# A learned termination ends the branch where the predicted probability passes this.
TERMINATION_THRESHOLD = 0.5

Reward = RewardWeights | TensorDictModuleBase | str
Termination = TensorDictModuleBase | str | None


def context_keys(model: Dynamics) -> list[str]:
    """The keys beside the state that every prediction reads: ``design`` where the layout has one."""
    return ["design"] if model.layout.design_size else []


def no_design(state: torch.Tensor) -> torch.Tensor:
    """The design input of a model of an env without one: no numbers, one row per state."""
    return state.new_zeros(*state.shape[:-1], 0)


class PredictNextState(nn.Module):
    """The dynamics head: ``(state, action, member[, design]) -> (next state, member, fault[, design],
    *learned)``, the learned outputs (:data:`LEARNED_KEYS`) for a model that learns any.

    A prediction that is not finite or leaves ``blowup_limit`` (the real walker's explosion
    limit by default) is a fault: the state stays where it was (as the real walker repeats its
    last good observation) and the done head truncates the trajectory, so a diverging model
    never poisons a batch. ``member_per_step`` redraws the predicting member at every step
    instead of keeping the trajectory's.
    """

    def __init__(self, model: Dynamics, member_per_step: bool = False, deterministic: bool = False,
                 blowup_limit: float = EXPLOSION_LIMIT) -> None:
        super().__init__()
        if not blowup_limit > 0:
            raise ValueError(f"blowup_limit must be positive (a state's largest magnitude), got {blowup_limit!r}")
        self.model = model
        self.member_per_step = member_per_step
        self.deterministic = deterministic
        self.blowup_limit = blowup_limit
        self.learned = learned_outputs(model)

    def forward(self, state, action, member, *design):
        context = design[0] if design else no_design(state)
        if self.member_per_step:
            member = draw_members(self.model, context).unsqueeze(-1)
        device = self.model.device
        inputs = state.to(device), action.to(device), context.to(device), member.squeeze(-1).to(device)
        if self.learned:
            predicted, learned = self.model.predict_outputs(*inputs, deterministic=self.deterministic)
            learned = learned.to(state.device).unbind(-1)
        else:
            predicted, learned = self.model.predict(*inputs, deterministic=self.deterministic), ()
        next_state, member, fault = self.settled(state, predicted.to(state.device), member)
        return next_state, member, fault, *design, *(value.unsqueeze(-1) for value in learned)

    def settled(self, state, predicted, member):
        """The head's outputs for a ``predicted`` next state: a fault keeps ``state`` and says so."""
        # The env's part only: a model's memory (a step count) is not physics.
        healthy = healthy_rows(predicted[..., :self.model.layout.robot_size], self.blowup_limit).unsqueeze(-1)
        next_state = torch.where(healthy, predicted, state)
        return next_state, member, ~healthy


class PredictAndMeasureDisagreement(nn.Module):
    """The dynamics head of deterministic imagination with the cut: one all-member prediction
    serves the step and the disagreement.

    Without noise the row's own next state is its member's mean prediction, one of the voting
    members' mean predictions the disagreement needs anyway (:func:`member_predictions`), so
    the step is read from them instead of predicted again: ``(state, action, member[, design])
    -> (next state, member, fault[, design], disagreement)``. A row whose member does not vote
    is predicted on its own, as :class:`PredictNextState` would. (A model that learns outputs
    beside the state takes :class:`PredictNextState` and the disagreement apart.)
    """

    def __init__(self, model: Dynamics, scale: torch.Tensor, member_per_step: bool = False,
                 blowup_limit: float = EXPLOSION_LIMIT) -> None:
        super().__init__()
        self.step = PredictNextState(model, member_per_step, deterministic=True, blowup_limit=blowup_limit)
        self.disagreement = MemberDisagreement(model, scale)
        self.model = model
        voters = model.voting_members.cpu()
        voter_of = torch.full((model.members,), -1, dtype=torch.long)
        voter_of[voters] = torch.arange(len(voters))
        self.register_buffer("voter_of", voter_of)  # each member's row in member_predictions (-1: none)

    @torch.no_grad()
    def forward(self, state, action, member, *design):
        context = design[0] if design else no_design(state)
        if self.step.member_per_step:
            member = draw_members(self.model, context).unsqueeze(-1)
        device = self.model.device
        state_, action_, design_ = state.to(device), action.to(device), context.to(device)
        every = member_predictions(self.model, state_, action_, design_)  # [voters, N, size]
        voter = self.voter_of.to(device)[member.reshape(-1).to(device)]
        if (voter >= 0).all():
            predicted = every[voter, torch.arange(every.shape[1], device=device)]
        else:
            predicted = self.model.predict(state_, action_, design_, member.reshape(-1).to(device), deterministic=True)
        outputs = self.step.settled(state, predicted.reshape(state.shape).to(state.device), member)
        return *outputs, *design, self.disagreement.of_predictions(every).to(state.device)


def draw_members(model: Dynamics, design: torch.Tensor) -> torch.Tensor:
    """``model.draw_members`` for designs on any device, answered on theirs."""
    return model.draw_members(design.to(model.device)).to(design.device)


class RewardHead(nn.Module):
    """The walker's reward of the predicted state (the base leads every walker layout)."""

    def __init__(self, weights: RewardWeights) -> None:
        super().__init__()
        self.weights = weights

    def forward(self, state):
        return walking_reward(state, self.weights).unsqueeze(-1)


class DoneHead(nn.Module):
    """A model fault ends the trajectory as truncated, never terminated: the real env would have
    gone on, so the value estimator bootstraps from the critic there. With a termination (known
    or learned: ``terminated``), a step that ended the task (and did not fault) is terminated."""

    def forward(self, fault, terminated=None):
        if terminated is None:
            return fault.clone(), torch.zeros_like(fault), fault.clone()
        terminated = terminated.bool() & ~fault
        return terminated | fault, terminated, fault.clone()


class Threshold(nn.Module):
    """A learned termination's decision: the predicted probability above :data:`TERMINATION_THRESHOLD`."""

    def forward(self, probability):
        return probability > TERMINATION_THRESHOLD


class ObservationDecoder(nn.Module):
    """What the policy reads of the predicted state (the layout's ``observation``: the flat
    observation, or the tokens)."""

    def __init__(self, model: Dynamics) -> None:
        super().__init__()
        self.layout = model.layout

    def forward(self, state, *design):
        return self.layout.observation(state, *design)


def reward_head(reward: Reward, model: Dynamics, decoder: TensorDictModule) -> TensorDictModuleBase:
    """The world model's reward head for ``reward`` (see :func:`make_world_model`)."""
    nxt = "next"
    if isinstance(reward, RewardWeights):
        return TensorDictModule(RewardHead(reward), in_keys=[(nxt, "state")], out_keys=[(nxt, "reward")])
    if isinstance(reward, str) and reward == LEARNED:
        if REWARD not in learned_outputs(model):
            raise ValueError(f"reward={LEARNED!r} needs a model that learns it, but {type(model).__name__} learns "
                             f"{list(learned_outputs(model))}: build it with learn=['reward'] or give a known reward")
        return TensorDictModule(nn.Identity(), in_keys=[(nxt, LEARNED_KEYS[REWARD])], out_keys=[(nxt, "reward")])
    if isinstance(reward, TensorDictModuleBase):
        if (nxt, "reward") not in reward.out_keys:
            raise ValueError(f"a known reward must write ('next', 'reward'); this one writes {reward.out_keys}")
        return TensorDictSequential(decoder, reward)
    raise TypeError(f"reward must be RewardWeights (the walker's), a TensorDict module writing ('next', 'reward'), "
                    f"or {LEARNED!r}; got {reward!r}")


def termination_module(termination: Termination, model: Dynamics,
                       decoder: TensorDictModule) -> TensorDictModuleBase | None:
    """What writes ``("next", "terminated")`` before the done head, for ``termination``; None for none."""
    nxt = "next"
    if termination is None:
        return None
    if isinstance(termination, str) and termination == LEARNED:
        if TERMINATED not in learned_outputs(model):
            raise ValueError(f"termination={LEARNED!r} needs a model that learns it, but {type(model).__name__} "
                             f"learns {list(learned_outputs(model))}: build it with learn=['terminated'], give a "
                             f"known termination, or none")
        return TensorDictModule(Threshold(), in_keys=[(nxt, LEARNED_KEYS[TERMINATED])], out_keys=[(nxt, "terminated")])
    if isinstance(termination, TensorDictModuleBase):
        if (nxt, "terminated") not in termination.out_keys:
            raise ValueError(f"a known termination must write ('next', 'terminated'); this one writes "
                             f"{termination.out_keys}")
        return TensorDictSequential(decoder, termination)
    raise TypeError(f"termination must be a TensorDict module writing ('next', 'terminated'), {LEARNED!r} or None; "
                    f"got {termination!r}")


def make_world_model(model: Dynamics, reward: Reward, member_per_step: bool = False,
                     deterministic: bool = False, cut: DisagreementCut | None = None,
                     termination: Termination = None, blowup_limit: float = EXPLOSION_LIMIT,
                     penalty: DisagreementPenalty | None = None) -> WorldModel:
    """Composes ``model`` into TorchRL's ``WorldModel`` (latent = ``state``).

    ``reward``: the walker's :class:`~unipolicy_rl.envs.RewardWeights`, a known reward (a
    TensorDict module of the real env's keys, see the module docstring), or ``"learned"``: the
    model's reward head (``learn=['reward']``). ``termination``: None (a branch ends only where
    the model faults, truncated), a known termination function, or ``"learned"``.
    ``blowup_limit``: a predicted state with a magnitude at or past it is a fault.

    With ``cut`` or ``penalty`` the world model also measures the members' disagreement about
    each step's next state (``("next", "disagreement")``). ``cut`` ends the branch where it passes
    ``cut.threshold`` (``("next", "disagreement_cut")``); ``penalty`` takes ``penalty.weight``
    times it off the step's reward (``("next", "disagreement_penalty")``: what it took). Without
    either the model is exactly what it was before they existed (same keys, same random draws).
    With ``deterministic`` the step and the disagreement share one all-member prediction
    (:class:`PredictAndMeasureDisagreement`): the measure then costs little more than the step
    itself."""
    nxt = "next"
    context = context_keys(model)
    learned = [(nxt, LEARNED_KEYS[name]) for name in learned_outputs(model)]
    # The encoder is the identity: the real env reports the model's state itself.
    encoder = TensorDictModule(nn.Identity(), in_keys=["state"], out_keys=["state"])
    step_in = ["state", "action", "member", *context]
    step_out = [(nxt, "state"), (nxt, "member"), (nxt, "physics_fault"), *((nxt, key) for key in context)]
    dynamics = TensorDictModule(PredictNextState(model, member_per_step, deterministic, blowup_limit),
                                in_keys=step_in, out_keys=[*step_out, *learned])
    decoder = TensorDictModule(ObservationDecoder(model), in_keys=[(nxt, "state"), *((nxt, key) for key in context)],
                               out_keys=[(nxt, model.layout.observation_key)])
    rewards = reward_head(reward, model, decoder)
    scale = disagreement_scale(cut, penalty)
    if scale is not None and deterministic and not learned:
        dynamics = TensorDictModule(PredictAndMeasureDisagreement(model, scale, member_per_step, blowup_limit),
                                    in_keys=step_in, out_keys=[*step_out, (nxt, DISAGREEMENT)])
    elif scale is not None:  # measured first in the reward's stage (it follows the dynamics; the done head reads it)
        rewards = TensorDictSequential(
            TensorDictModule(MemberDisagreement(model, scale), in_keys=["state", "action", *context],
                             out_keys=[(nxt, DISAGREEMENT)]), rewards)
    if penalty is not None:
        rewards = TensorDictSequential(rewards, TensorDictModule(
            PenalizedReward(penalty.weight), in_keys=[(nxt, "reward"), (nxt, DISAGREEMENT)],
            out_keys=[(nxt, "reward"), (nxt, DISAGREEMENT_PENALTY)]))
    terminates = termination_module(termination, model, decoder)
    done_in = [(nxt, "physics_fault")]
    flags = [(nxt, "done"), (nxt, "terminated"), (nxt, "truncated")]
    terminated_in = [] if terminates is None else [(nxt, "terminated")]
    if cut is None:
        done = TensorDictModule(DoneHead(), in_keys=[*done_in, *terminated_in], out_keys=flags)
    else:
        done = TensorDictModule(CutDoneHead(cut.threshold), in_keys=[*done_in, (nxt, DISAGREEMENT), *terminated_in],
                                out_keys=[*flags, (nxt, DISAGREEMENT_CUT)])
    if terminates is not None:
        done = TensorDictSequential(terminates, done)
    return WorldModel(encoder, dynamics, rewards, done_head=done, decoder=decoder)


def disagreement_scale(cut: DisagreementCut | None, penalty: DisagreementPenalty | None) -> torch.Tensor | None:
    """The units of the one disagreement the cut and the penalty read (None: neither is on)."""
    if cut is not None and penalty is not None and not torch.equal(cut.scale, penalty.scale):
        raise ValueError("the disagreement cut and penalty read one measure, so they need the same scale (both "
                         "from the same transitions: change_scale)")
    return cut.scale if cut is not None else None if penalty is None else penalty.scale


class ImaginedEnv(ModelBasedEnvBase):
    """Rolls policies through a world model, ``batch_size`` trajectories at a time.

    A :class:`~torchrl.envs.model_based.ModelBasedEnvBase`, written as TorchRL's
    ``WorldModelEnv`` is (the world model's ``step`` writes ``("next", ...)``; the env hands
    those entries to TorchRL's step machinery), with two differences that keep
    ``WorldModelEnv`` itself from fitting: it copies a reference env's specs by
    ``spec.expand(batch_size)``, which fails for specs with a feature dimension such as our
    ``action`` of shape ``[4]``; and its reset needs a start state in the reset tensordict,
    while a collector or ``check_env_specs`` resets without one and TorchRL's rollout resets
    only the trajectories that ended (``_reset`` mask). Here a reset draws start states from
    ``start_states`` (real states from the replay buffer) for every trajectory it resets that
    brings none, and assigns each its member: drawn from the model's elites, or the row's own
    member of ``members`` where given (a comparison across members must keep each row's member
    when TorchRL restarts a row that faulted, since its reset brings only the ``_reset`` mask).
    The design (where the layout has one) and the keys of the robot's build (the layout's
    ``build_keys``: a grammar robot's masks, parents and morphology) come with each start state
    and stay as they are for the whole branch.

    Args:
        world_model: from :func:`make_world_model`.
        reference_env: the real env (any TorchRL env the layout was read off, e.g. a ``GymEnv``;
            the walker's ``BatchedWalkerEnv``, or a ``MorphologyWalkerEnv`` for a token model; or
            a ``TransformedEnv`` of one) whose action, reward and done specs, and the specs of
            the design, fault and build keys where it has them, this env copies; it is not stepped.
        start_states: ``n -> TensorDict(state[, design], *build keys)`` of real start states.
        batch_size: number of trajectories.
        members: ``[batch_size]`` the member of every row, for good (None: drawn at every reset).
    """

    def __init__(self, world_model: WorldModel, reference_env: EnvBase, start_states: StartSampler,
                 batch_size: int, members: torch.Tensor | None = None) -> None:
        shape = torch.Size([batch_size])
        super().__init__(world_model.step_module, device="cpu", batch_size=shape, allow_done_after_reset=True)
        model = world_model.dynamics.module.model
        one = (0,) * len(reference_env.batch_size)
        layout = model.layout

        def copied(key):
            spec = reference_env.observation_spec[key][one]
            return spec.expand(*shape, *spec.shape).clone()

        # The model's own blow-ups: the walker reports its physics faults under the same key.
        specs = reference_env.observation_spec
        own = Categorical(2, (1,), dtype=torch.bool)
        fault = specs["physics_fault"][one] if "physics_fault" in specs.keys() else own
        self.context_keys = context_keys(model)
        self.observation_spec = Composite(
            {layout.observation_key: Unbounded((*shape, *layout.observation_shape), dtype=torch.float32),
             **{key: copied(key) for key in self.context_keys},
             "physics_fault": fault.expand(*shape, *fault.shape).clone(),
             "state": Unbounded((*shape, layout.size), dtype=torch.float32),
             "member": Categorical(model.members, (*shape, 1), dtype=torch.long),
             **{key: copied(key) for key in layout.build_keys}},
            shape=shape,
        )
        self.build_keys = layout.build_keys
        # A world model with the disagreement cut or penalty reports them at every step (zero at a reset).
        measured = {DISAGREEMENT: Unbounded((*shape, 1), dtype=torch.float32),
                    DISAGREEMENT_CUT: fault.expand(*shape, *fault.shape).clone(),
                    DISAGREEMENT_PENALTY: Unbounded((*shape, 1), dtype=torch.float32)}
        self.measured = [key for key in measured if ("next", key) in world_model.out_keys]
        for key in self.measured:
            self.observation_spec[key] = measured[key]
        for name in ("action_spec", "reward_spec", "done_spec"):
            spec = getattr(reference_env, name)[one]
            setattr(self, name, spec.expand(*shape, *spec.shape).clone())
        self.full_world_model = world_model
        self.model = model
        self.start_states = start_states
        if members is not None and members.shape != shape:
            raise ValueError(f"members must be one per trajectory, shape {tuple(shape)}, got {tuple(members.shape)}")
        self.members = None if members is None else members.reshape(batch_size, 1).long()

    def _step(self, tensordict: TensorDictBase) -> TensorDictBase:
        out = self.world_model(tensordict.copy()).get("next")
        for key in self.build_keys:  # the robot's build: no step changes it
            out.set(key, tensordict.get(key))
        keys = [*self.observation_spec.keys(), *self.full_reward_spec.keys(), *self.full_done_spec.keys()]
        return out.select(*keys)

    def _reset(self, tensordict: TensorDictBase | None = None, **kwargs) -> TensorDictBase:
        n = self.batch_size[0]
        mask = torch.ones(n, dtype=torch.bool)
        if tensordict is not None and "_reset" in tensordict.keys():
            mask = tensordict.get("_reset").reshape(n)
        starting = ("state", *self.context_keys, *self.build_keys)
        if tensordict is None or "state" not in tensordict.keys():
            start = self.start_states(n)
        else:
            start = tensordict.select(*starting, *(["member"] if "member" in tensordict.keys() else []))
            if mask.any() and "_reset" in tensordict.keys():
                fresh = self.start_states(int(mask.sum()))
                start = start.clone()
                for key in starting:
                    start[key][mask] = fresh[key]
                if "member" in start.keys():
                    start["member"][mask] = draw_members(self.model, self._design(fresh)).unsqueeze(-1)
        state, design = start.get("state").float(), self._design(start).float()
        member = start.get("member", None)
        if self.members is not None:
            member = self.members.clone()
        elif member is None:
            member = draw_members(self.model, design).unsqueeze(-1)
        layout = self.model.layout
        out = TensorDict(
            {
                "state": state,
                **({"design": design} if self.context_keys else {}),
                "member": member,
                layout.observation_key: layout.observation(state, design),
                "physics_fault": torch.zeros(n, 1, dtype=torch.bool),
                **{key: start.get(key) for key in self.build_keys},
            },
            batch_size=self.batch_size,
        )
        for key in self.measured:
            out.set(key, self.observation_spec[key].zero())
        zero_done = self.full_done_spec.zero()
        out.update(zero_done)
        return out

    def _design(self, start: TensorDictBase) -> torch.Tensor:
        """The start states' design, or no numbers for a model of an env without one."""
        return start.get("design") if self.context_keys else no_design(start.get("state"))


def member_returns(world_model: WorldModel, reference_env: EnvBase, policy: TensorDictModule,
                   starts: TensorDictBase, horizon: int) -> torch.Tensor:
    """Mean return of ``policy`` over ``horizon`` imagined steps from ``starts``, one figure per voting member.

    Every start is rolled out under every member of ``model.voting_members`` (ME-TRPO's check
    of a policy on each model), all of them in one batched rollout: ``[voters]``. A trajectory
    that faults restarts from its own start under its own member, so each figure is one
    member's alone; one that terminates earns nothing after its termination.
    """
    model = world_model.dynamics.module.model
    voters = model.voting_members
    if voters is None:
        raise ValueError(f"{type(model).__name__}'s members model different designs, not alternatives of one "
                         f"robot: ME-TRPO's comparison across members does not apply (use stopping.kind=fixed)")
    voters = voters.cpu()
    n = starts.batch_size[0]
    members = voters.repeat_interleave(n)
    batch = starts.expand(len(voters), n).reshape(-1).clone()
    batch.set("member", members.unsqueeze(-1))
    # Row i holds start i % n: a restart asks for all rows and keeps those it resets.
    env = ImaginedEnv(world_model, reference_env, lambda k: starts[torch.arange(k) % n],
                            batch_size=batch.batch_size[0], members=members)
    rollout = env.rollout(horizon, policy, tensordict=env.reset(batch), auto_reset=False,
                          break_when_any_done=False)
    reward = rollout.get(("next", "reward"))
    # A trajectory that terminated earns nothing after it (its row restarted): only its own steps count.
    terminated = rollout.get(("next", "terminated")).long()
    returns = reward.masked_fill((terminated.cumsum(1) - terminated) > 0, 0.0).sum(dim=(1, 2))
    return returns.reshape(len(voters), n).mean(1)
