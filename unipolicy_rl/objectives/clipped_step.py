"""PPO's policy step: epochs of Adam on TorchRL's clipped surrogate (``ClipPPOLoss``), in place of
TRPO's one natural-gradient step.

Everything around the step stays the on-policy learner's: GAE and the standardised advantage
(:class:`~unipolicy_rl.objectives.TRPOLoss`), the critic fit, the observation normaliser, the
checkpoint. Why a second step: TRPO's step is sized by the Fisher matrix, and for some networks
(the token transformer, docs/grammar.md) its conjugate-gradient direction gains little surrogate
per unit of KL; PPO, which MetaMorph and ModuMorph train their transformers with, moves by many
small first-order steps instead. TorchRL's ``ClipPPOLoss`` computes the clipped objective, the
entropy bonus and its diagnostics; this module runs the epochs and minibatches over a batch,
stops early past a KL target (as stable-baselines3's ``target_kl``: checked on every minibatch,
so a large batch, such as an imagined one of 5,000 steps, cannot overshoot it by a whole epoch of
steps), and, like the natural
gradient step, leaves the actor and its optimiser as they were when anything turns non-finite.
Log-probabilities, entropy and KL are the actor's distribution's, so a masked token policy's
padding counts for nothing here as it does in TRPO.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import torch
from tensordict import TensorDictBase
from tensordict.nn import ProbabilisticTensorDictSequential
from torchrl.objectives import ClipPPOLoss

from unipolicy_rl.objectives.trpo import TRPOLoss

__all__ = ["ClippedStep", "ClippedStepResult", "ClippedSurrogate"]


@dataclass(frozen=True)
class ClippedSurrogate:
    """PPO's policy-step settings (stable-baselines3's PPO defaults where not said).

    Attributes:
        epochs: passes over the batch per update.
        minibatch_size: samples per Adam step.
        lr: Adam's learning rate for the actor.
        clip_epsilon: the probability ratio's clip range, ``[1 - eps, 1 + eps]``.
        max_grad_norm: the actor gradient's norm is clipped to this before each step.
        target_kl: stop the step at the first minibatch whose mean ``KL(old || new)``, with the
            actor as it stands before that minibatch's Adam step, passes 1.5 times this, as
            stable-baselines3 does (which estimates the KL from the sampled ratios; here it is the
            distributions' exact KL, the one ``kl`` reports); None: always run every epoch. Without
            it PPO's KL per update grows as the policy's spread shrinks (docs/grammar.md).
    """

    epochs: int = 10
    minibatch_size: int = 64
    lr: float = 3e-4
    clip_epsilon: float = 0.2
    max_grad_norm: float = 0.5
    target_kl: float | None = None

    def __post_init__(self) -> None:
        for name in ("epochs", "minibatch_size"):
            value = getattr(self, name)
            if not (isinstance(value, int) and not isinstance(value, bool) and value >= 1):
                raise ValueError(f"{CONFIG_KEYS[name]} must be a positive integer, got {value!r}")
        for name in ("lr", "clip_epsilon", "max_grad_norm"):
            value = getattr(self, name)
            if not (isinstance(value, (int, float)) and not isinstance(value, bool) and 0 < value < math.inf):
                raise ValueError(f"{CONFIG_KEYS[name]} must be a positive finite number, got {value!r}")
        if self.target_kl is not None and not (isinstance(self.target_kl, (int, float))
                                               and not isinstance(self.target_kl, bool) and self.target_kl > 0):
            raise ValueError(f"{CONFIG_KEYS['target_kl']} must be null or a positive number, got {self.target_kl!r}")


# Each ClippedSurrogate field's config key (conf/algo/ppo.yaml), which its errors name.
CONFIG_KEYS = {"epochs": "algo.policy_epochs", "minibatch_size": "algo.policy_minibatch_size", "lr": "algo.policy_lr",
               "clip_epsilon": "algo.clip_epsilon", "max_grad_norm": "algo.max_grad_norm",
               "target_kl": "algo.target_kl"}


@dataclass(frozen=True)
class ClippedStepResult:
    """What one PPO policy step did (the fields a TRPO step reports where they mean the same).

    Attributes:
        accepted: whether the actor changed (False: skipped, see ``skip_reason``).
        skip_reason: None when accepted.
        kl: mean ``KL(old || new)`` over the batch after the step.
        surrogate_improvement: the (unclipped) surrogate advantage gained over the batch.
        entropy: mean policy entropy before the step.
        clip_fraction: share of samples whose ratio was clipped, mean over the minibatch steps.
        policy_epochs: passes over the batch, a pass that ``target_kl`` stopped counted by the
            share of its minibatches stepped (fewer than set when it stopped them).
    """

    accepted: bool
    skip_reason: str | None
    kl: float = 0.0
    surrogate_improvement: float = 0.0
    entropy: float = 0.0
    clip_fraction: float = 0.0
    policy_epochs: float = 0.0

    def as_metrics(self, prefix: str = "train/") -> dict[str, float]:
        values = asdict(self)
        values.pop("skip_reason")
        values["step_accepted"] = float(values.pop("accepted"))
        return {prefix + name: float(value) for name, value in values.items()}


class ClippedStep:
    """``step(batch, advantage)``: PPO's epochs on ``loss``'s actor, ``loss`` the on-policy learner's
    :class:`TRPOLoss` (its keys, its behaviour distribution, its standardised advantage).

    ``actor`` must be the module whose parameters the collecting policy runs (the one ``loss``
    was built on): TorchRL's loss is built on it directly (not functionally), so every step
    moves the policy that collects next.
    """

    def __init__(self, loss: TRPOLoss, actor: ProbabilisticTensorDictSequential,
                 settings: ClippedSurrogate | None = None, generator: torch.Generator | None = None) -> None:
        self.loss = loss
        self.settings = settings or ClippedSurrogate()
        self.generator = generator
        keys = loss.tensor_keys
        entropy_coeff = float(loss.entropy_coeff)
        self.ppo = ClipPPOLoss(actor, None, clip_epsilon=self.settings.clip_epsilon, entropy_bonus=entropy_coeff > 0,
                               entropy_coeff=entropy_coeff if entropy_coeff > 0 else None, critic_coeff=None,
                               normalize_advantage=False, functional=False)
        self.ppo.set_keys(action=keys.action, sample_log_prob=keys.sample_log_prob, advantage=keys.advantage)
        self.parameters = [p for p in actor.parameters() if p.requires_grad]
        self.optimizer = torch.optim.Adam(self.parameters, lr=self.settings.lr)

    def __call__(self, batch: TensorDictBase, advantage: torch.Tensor) -> ClippedStepResult:
        """One policy step on the flat ``batch`` with ``advantage`` (one per sample, standardised)."""
        loss, settings = self.loss, self.settings
        if not bool(torch.isfinite(advantage).all()):
            return ClippedStepResult(False, "non-finite advantage")
        data = batch.select(*self._read_keys()).clone(False)
        data.set(loss.tensor_keys.advantage, advantage.detach().reshape(data.batch_size + (1,)))
        with torch.no_grad():
            before = loss.policy_distribution(data)
            entropy = float(before.entropy().mean())
            surrogate_before = float(loss.surrogate_advantage(before, data, advantage))
        saved = [p.detach().clone() for p in self.parameters]
        saved_optimizer = _copy_state(self.optimizer.state_dict())
        count, clipped, steps = data.batch_size[0], 0.0, 0
        minibatches = math.ceil(count / settings.minibatch_size)
        stop_above = None if settings.target_kl is None else 1.5 * settings.target_kl
        for _ in range(settings.epochs):
            order = torch.randperm(count, generator=self.generator)
            for start in range(0, count, settings.minibatch_size):
                minibatch = data[order[start:start + settings.minibatch_size]]
                if stop_above is not None and self._kl(minibatch) > stop_above:
                    break
                out = self.ppo(minibatch)
                objective = out["loss_objective"] + (out["loss_entropy"] if "loss_entropy" in out.keys() else 0.0)
                self.optimizer.zero_grad(set_to_none=True)
                objective.backward()
                torch.nn.utils.clip_grad_norm_(self.parameters, settings.max_grad_norm)
                self.optimizer.step()
                clipped += float(out["clip_fraction"])
                steps += 1
            else:
                continue
            break  # (the KL target stopped the inner loop)
        with torch.no_grad():
            after = loss.policy_distribution(data)
            kl = float(loss.mean_kl(loss.behaviour_distribution(data), after))
            surrogate_after = float(loss.surrogate_advantage(after, data, advantage))
        if not (math.isfinite(kl) and math.isfinite(surrogate_after)
                and all(bool(torch.isfinite(p).all()) for p in self.parameters)):
            with torch.no_grad():
                for parameter, value in zip(self.parameters, saved, strict=True):
                    parameter.copy_(value)
            self.optimizer.load_state_dict(saved_optimizer)
            return ClippedStepResult(False, "non-finite loss, KL or parameter")
        return ClippedStepResult(True, None, kl, surrogate_after - surrogate_before, entropy, clipped / max(steps, 1),
                                 steps / minibatches)

    def _kl(self, minibatch: TensorDictBase) -> float:
        with torch.no_grad():
            return float(self.loss.mean_kl(self.loss.behaviour_distribution(minibatch),
                                           self.loss.policy_distribution(minibatch)))

    def _read_keys(self) -> list:
        loss = self.loss
        keys = loss.tensor_keys
        actor_keys = [key for key in loss.actor_network.in_keys if key not in loss.actor_network.dist_params_keys]
        return list(dict.fromkeys([*actor_keys, keys.action, keys.sample_log_prob,
                                   *loss.actor_network.dist_params_keys]))

    def state_dict(self) -> dict:
        return {"optimizer": self.optimizer.state_dict()}

    def load_state_dict(self, state: dict) -> None:
        self.optimizer.load_state_dict(state["optimizer"])


def _copy_state(state: dict) -> dict:
    """A deep copy of an optimizer's ``state_dict`` (its tensors cloned), to restore after a failed step."""
    def copy(value):
        if torch.is_tensor(value):
            return value.clone()
        if isinstance(value, dict):
            return {key: copy(item) for key, item in value.items()}
        if isinstance(value, list):
            return [copy(item) for item in value]
        return value
    return copy(state)
