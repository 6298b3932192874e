"""A surrogate as a TorchRL world model, and the env that rolls a policy through it.

:func:`make_world_model` composes a :class:`Dynamics` into TorchRL's
:class:`~torchrl.modules.WorldModel`: the latent is the robot's state itself (``state``),
the dynamics head predicts the next state, the reward head is the real env's
:func:`~unipolicy_rl.envs.walking_reward` of it (no learned reward), the done head ends a
trajectory whose prediction blew up (and, with a
:class:`~unipolicy_rl.world_models.disagreement.DisagreementCut`, one whose members disagree
about the next state past its threshold), and the decoder derives what the policy reads (the
layout's ``observation_key``). :class:`ImaginedWalkerEnv` is TorchRL's
:class:`~torchrl.envs.model_based.ModelBasedEnvBase` around it, presenting the keys and specs of
the real env: :class:`~unipolicy_rl.envs.BatchedWalkerEnv`'s (``observation``, ``design``,
``physics_fault``, reward, done/terminated/truncated) for a :class:`StateLayout`, or for grammar
robots (a :class:`~unipolicy_rl.world_models.token_layout.TokenLayout`)
:class:`~unipolicy_rl.envs.MorphologyWalkerEnv`'s (``tokens`` and the build keys ``token_mask``,
``token_parent``, ``action_mask``, ``morphology``, carried unchanged from each branch's real
start), beside the model's ``state`` and ``member``, so the same policy, value estimator and
:class:`~unipolicy_rl.objectives.TRPOUpdater` work on imagined data as on real data.
"""

from __future__ import annotations

from collections.abc import Callable

import torch
from tensordict import TensorDict, TensorDictBase
from tensordict.nn import TensorDictModule, TensorDictSequential
from torch import nn
from torchrl.data import Categorical, Composite, Unbounded
from torchrl.envs import EnvBase
from torchrl.envs.model_based import ModelBasedEnvBase
from torchrl.modules import WorldModel

from unipolicy_rl.envs.reward import RewardWeights, walking_reward
from unipolicy_rl.envs.simulation import healthy_rows
from unipolicy_rl.world_models.disagreement import (
    DISAGREEMENT,
    DISAGREEMENT_CUT,
    CutDoneHead,
    DisagreementCut,
    MemberDisagreement,
    member_predictions,
)
from unipolicy_rl.world_models.dynamics import Dynamics

# A start state: the robot's state and design (and, once assigned, the member that predicts it).
StartSampler = Callable[[int], TensorDictBase]


class PredictNextState(nn.Module):
    """The dynamics head: ``(state, action, design, member) -> (next state, design, member, fault)``.

    A prediction that is not finite or leaves the real env's explosion limit is a fault:
    the state stays where it was (as the real env repeats its last good observation) and
    the done head ends the trajectory, so a diverging model never poisons a batch.
    ``member_per_step`` redraws the predicting member at every step instead of keeping the
    trajectory's.
    """

    def __init__(self, model: Dynamics, member_per_step: bool = False, deterministic: bool = False) -> None:
        super().__init__()
        self.model = model
        self.member_per_step = member_per_step
        self.deterministic = deterministic

    def forward(self, state, action, design, member):
        if self.member_per_step:
            member = draw_members(self.model, design).unsqueeze(-1)
        device = self.model.device
        predicted = self.model.predict(state.to(device), action.to(device), design.to(device),
                                       member.squeeze(-1).to(device), deterministic=self.deterministic).to(state.device)
        return self.settled(state, predicted, design, member)

    def settled(self, state, predicted, design, member):
        """The head's outputs for a ``predicted`` next state: a fault keeps ``state`` and says so."""
        # The robot's part only: a model's memory (a step count) is not physics.
        healthy = healthy_rows(predicted[..., :self.model.layout.robot_size]).unsqueeze(-1)
        next_state = torch.where(healthy, predicted, state)
        return next_state, design, member, ~healthy


class PredictAndMeasureDisagreement(nn.Module):
    """The dynamics head of deterministic imagination with the cut: one all-member prediction
    serves the step and the disagreement.

    Without noise the row's own next state is its member's mean prediction, one of the voting
    members' mean predictions the disagreement needs anyway (:func:`member_predictions`), so
    the step is read from them instead of predicted again: ``(state, action, design, member)
    -> (next state, design, member, fault, disagreement)``. A row whose member does not vote
    is predicted on its own, as :class:`PredictNextState` would.
    """

    def __init__(self, model: Dynamics, scale: torch.Tensor, member_per_step: bool = False) -> None:
        super().__init__()
        self.step = PredictNextState(model, member_per_step, deterministic=True)
        self.disagreement = MemberDisagreement(model, scale)
        self.model = model
        voters = model.voting_members.cpu()
        voter_of = torch.full((model.members,), -1, dtype=torch.long)
        voter_of[voters] = torch.arange(len(voters))
        self.register_buffer("voter_of", voter_of)  # each member's row in member_predictions (-1: none)

    @torch.no_grad()
    def forward(self, state, action, design, member):
        if self.step.member_per_step:
            member = draw_members(self.model, design).unsqueeze(-1)
        device = self.model.device
        state_, action_, design_ = state.to(device), action.to(device), design.to(device)
        every = member_predictions(self.model, state_, action_, design_)  # [voters, N, size]
        voter = self.voter_of.to(device)[member.reshape(-1).to(device)]
        if (voter >= 0).all():
            predicted = every[voter, torch.arange(every.shape[1], device=device)]
        else:
            predicted = self.model.predict(state_, action_, design_, member.reshape(-1).to(device), deterministic=True)
        outputs = self.step.settled(state, predicted.reshape(state.shape).to(state.device), design, member)
        return *outputs, self.disagreement.of_predictions(every).to(state.device)


def draw_members(model: Dynamics, design: torch.Tensor) -> torch.Tensor:
    """``model.draw_members`` for designs on any device, answered on theirs."""
    return model.draw_members(design.to(model.device)).to(design.device)


class RewardHead(nn.Module):
    """The real env's reward of the predicted state (the base leads every layout)."""

    def __init__(self, weights: RewardWeights) -> None:
        super().__init__()
        self.weights = weights

    def forward(self, state):
        return walking_reward(state, self.weights).unsqueeze(-1)


class DoneHead(nn.Module):
    """A model fault ends the trajectory as truncated, never terminated: the real robot would
    have walked on, so the value estimator bootstraps from the critic there."""

    def forward(self, fault):
        return fault.clone(), torch.zeros_like(fault), fault.clone()


class ObservationDecoder(nn.Module):
    """What the policy reads of the predicted state (the layout's ``observation``: the flat
    observation, or the tokens)."""

    def __init__(self, model: Dynamics) -> None:
        super().__init__()
        self.layout = model.layout

    def forward(self, state, design):
        return self.layout.observation(state, design)


def make_world_model(model: Dynamics, reward_weights: RewardWeights, member_per_step: bool = False,
                     deterministic: bool = False, cut: DisagreementCut | None = None) -> WorldModel:
    """Composes ``model`` into TorchRL's ``WorldModel`` (latent = ``state``).

    With ``cut`` the done head also measures the members' disagreement about each step's next
    state (``("next", "disagreement")``) and ends the branch where it passes ``cut.threshold``
    (``("next", "disagreement_cut")``); without it the model is exactly what it was before the
    cut existed (same keys, same random draws). With ``cut`` and ``deterministic`` the step and
    the disagreement share one all-member prediction (:class:`PredictAndMeasureDisagreement`):
    the cut then costs little more than the step itself."""
    nxt = "next"
    # The encoder is the identity: the real env reports the model's state itself.
    encoder = TensorDictModule(nn.Identity(), in_keys=["state"], out_keys=["state"])
    dynamics = TensorDictModule(
        PredictNextState(model, member_per_step, deterministic),
        in_keys=["state", "action", "design", "member"],
        out_keys=[(nxt, "state"), (nxt, "design"), (nxt, "member"), (nxt, "physics_fault")],
    )
    reward = TensorDictModule(RewardHead(reward_weights), in_keys=[(nxt, "state")], out_keys=[(nxt, "reward")])
    flags = [(nxt, "done"), (nxt, "terminated"), (nxt, "truncated")]
    if cut is None:
        done = TensorDictModule(DoneHead(), in_keys=[(nxt, "physics_fault")], out_keys=flags)
    elif deterministic:
        dynamics = TensorDictModule(
            PredictAndMeasureDisagreement(model, cut.scale, member_per_step),
            in_keys=["state", "action", "design", "member"],
            out_keys=[(nxt, "state"), (nxt, "design"), (nxt, "member"), (nxt, "physics_fault"), (nxt, DISAGREEMENT)],
        )
        done = TensorDictModule(CutDoneHead(cut.threshold), in_keys=[(nxt, "physics_fault"), (nxt, DISAGREEMENT)],
                                out_keys=[*flags, (nxt, DISAGREEMENT_CUT)])
    else:
        done = TensorDictSequential(
            TensorDictModule(MemberDisagreement(model, cut.scale), in_keys=["state", "action", "design"],
                             out_keys=[(nxt, DISAGREEMENT)]),
            TensorDictModule(CutDoneHead(cut.threshold), in_keys=[(nxt, "physics_fault"), (nxt, DISAGREEMENT)],
                             out_keys=[*flags, (nxt, DISAGREEMENT_CUT)]),
        )
    decoder = TensorDictModule(ObservationDecoder(model), in_keys=[(nxt, "state"), (nxt, "design")],
                               out_keys=[(nxt, model.layout.observation_key)])
    return WorldModel(encoder, dynamics, reward, done_head=done, decoder=decoder)


class ImaginedWalkerEnv(ModelBasedEnvBase):
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
    The keys of the robot's build (the layout's ``build_keys``: a grammar robot's masks, parents
    and morphology) come with each start state and stay as they are for the whole branch.

    Args:
        world_model: from :func:`make_world_model`.
        reference_env: the real env (a ``BatchedWalkerEnv``, or a ``MorphologyWalkerEnv`` for a
            token model; or a ``TransformedEnv`` of one) whose action, reward and done specs, and
            the specs of the design, fault and build keys, this env copies; it is not stepped.
        start_states: ``n -> TensorDict(state, design, *build keys)`` of real start states.
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

        fault = reference_env.observation_spec["physics_fault"][one]
        self.observation_spec = Composite(
            {layout.observation_key: Unbounded((*shape, *layout.observation_shape), dtype=torch.float32),
             "design": copied("design"),
             "physics_fault": fault.expand(*shape, *fault.shape).clone(),
             "state": Unbounded((*shape, layout.size), dtype=torch.float32),
             "member": Categorical(model.members, (*shape, 1), dtype=torch.long),
             **{key: copied(key) for key in layout.build_keys}},
            shape=shape,
        )
        self.build_keys = layout.build_keys
        # A world model with the disagreement cut reports it at every step (zero at a reset).
        self.cuts = ("next", DISAGREEMENT_CUT) in world_model.out_keys
        if self.cuts:
            self.observation_spec[DISAGREEMENT] = Unbounded((*shape, 1), dtype=torch.float32)
            self.observation_spec[DISAGREEMENT_CUT] = fault.expand(*shape, *fault.shape).clone()
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
        starting = ("state", "design", *self.build_keys)
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
                    start["member"][mask] = draw_members(self.model, fresh["design"]).unsqueeze(-1)
        state, design = start.get("state").float(), start.get("design").float()
        member = start.get("member", None)
        if self.members is not None:
            member = self.members.clone()
        elif member is None:
            member = draw_members(self.model, design).unsqueeze(-1)
        layout = self.model.layout
        out = TensorDict(
            {
                "state": state,
                "design": design,
                "member": member,
                layout.observation_key: layout.observation(state, design),
                "physics_fault": torch.zeros(n, 1, dtype=torch.bool),
                **{key: start.get(key) for key in self.build_keys},
            },
            batch_size=self.batch_size,
        )
        if self.cuts:
            out.set(DISAGREEMENT, torch.zeros(n, 1))
            out.set(DISAGREEMENT_CUT, torch.zeros(n, 1, dtype=torch.bool))
        zero_done = self.full_done_spec.zero()
        out.update(zero_done)
        return out


def member_returns(world_model: WorldModel, reference_env: EnvBase, policy: TensorDictModule,
                   starts: TensorDictBase, horizon: int) -> torch.Tensor:
    """Mean return of ``policy`` over ``horizon`` imagined steps from ``starts``, one figure per voting member.

    Every start is rolled out under every member of ``model.voting_members`` (ME-TRPO's check
    of a policy on each model), all of them in one batched rollout: ``[voters]``. A trajectory
    that faults restarts from its own start under its own member, so each figure is one
    member's alone.
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
    env = ImaginedWalkerEnv(world_model, reference_env, lambda k: starts[torch.arange(k) % n],
                            batch_size=batch.batch_size[0], members=members)
    rollout = env.rollout(horizon, policy, tensordict=env.reset(batch), auto_reset=False,
                          break_when_any_done=False)
    returns = rollout.get(("next", "reward")).sum(dim=(1, 2))
    return returns.reshape(len(voters), n).mean(1)
