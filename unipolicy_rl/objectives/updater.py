"""The full on-policy update: advantage, one policy step (TRPO's natural gradient, or PPO's clipped
epochs), then the critic fit."""

from __future__ import annotations

import torch
from tensordict import TensorDictBase

from unipolicy_rl.cpu_speed.critic_process import CriticFitProcess
from unipolicy_rl.objectives.clipped_step import ClippedStep, ClippedStepResult
from unipolicy_rl.objectives.critic_fit import CriticFitResult, explained_variance, fit_critic, make_critic_optimizer
from unipolicy_rl.objectives.natural_gradient import TRPOStepResult, TrustRegion, natural_gradient_step
from unipolicy_rl.objectives.trpo import TRPOLoss

__all__ = ["CRITIC_FITS", "TRPOUpdater"]

CRITIC_FITS = ("inline", "lagged", "process")


class TRPOUpdater:
    """One full TRPO update per call: advantage, natural-gradient policy step, critic fit.

    Keeps the critic's Adam state across updates. ``update(batch)`` takes a collected batch
    shaped ``[*envs, time]`` (time last, as TorchRL's GAE expects) and returns flat float
    metrics named ``train/...`` (the same names on every call, so they can be rows of a
    table); the last :class:`TRPOStepResult` and :class:`CriticFitResult`, with their skip
    reasons, are kept in ``last_step`` and ``last_critic_fit``.

    ``consecutive_skips`` (also the metric ``train/consecutive_skips``) counts the updates in
    a row, up to and including the last, in which the policy step was not accepted (any
    ``skip_reason``, a failed line search included) or the critic fit was skipped; an update
    with both an accepted step and a fitted critic resets it to 0. Each skip leaves the
    parameters untouched, so a run whose count keeps growing has stopped learning (e.g. its
    returns went non-finite): a training loop can stop it past a limit, with
    :attr:`skip_reasons` for the message.

    The policy step takes its settings from ``trust_region`` (default :class:`TrustRegion`); the critic defaults (Adam
    ``lr=1e-3``, 10 epochs of minibatches of 128) follow stable-baselines3-contrib. With
    ``clipped_step`` (a :class:`ClippedStep` on the same loss) the policy moves by PPO's clipped
    epochs instead (``algo=ppo``) and ``trust_region`` is not used; the rest of the update is the same.

    ``critic_fit`` says when the critic is fitted: ``inline`` (at the end of its own update),
    ``lagged`` (at the end of the next update, after that update's policy step, so each update's
    advantages come from the critic fitted through the update before last), or ``process`` (the
    same learning as ``lagged``, the fit on a forked process beside the next update:
    :class:`~unipolicy_rl.cpu_speed.critic_process.CriticFitProcess`). With either of the last
    two a fit is pending between updates; :meth:`finish_critic_fit` applies it (before anything
    reads or changes the critic outside an update: a normaliser refresh, a checkpoint), and an
    update reports the metrics of the fit it finished, the one of the batch before.
    """

    def __init__(
        self,
        loss_module: TRPOLoss,
        *,
        trust_region: TrustRegion | None = None,
        critic_lr: float = 1e-3,
        critic_epochs: int = 10,
        critic_minibatch_size: int = 128,
        generator: torch.Generator | None = None,
        clipped_step: ClippedStep | None = None,
        critic_fit: str = "inline",
    ) -> None:
        if clipped_step is not None and clipped_step.loss is not loss_module:
            raise ValueError("clipped_step must be built on the updater's loss_module")
        if critic_fit not in CRITIC_FITS:
            raise ValueError(f"critic_fit must be one of {CRITIC_FITS}, got {critic_fit!r}")
        if critic_fit == "process" and clipped_step is not None and generator is not None \
                and clipped_step.generator is generator:
            raise ValueError("critic_fit='process' takes the critic fit's generator to its own process, and "
                             "clipped_step draws from the same one: give the clipped step a generator of its own")
        self.loss_module = loss_module
        self.clipped_step = clipped_step
        self.trust_region = trust_region or TrustRegion()
        self.critic_optimizer = make_critic_optimizer(loss_module, critic_lr)
        self.critic_epochs = critic_epochs
        self.critic_minibatch_size = critic_minibatch_size
        self.generator = generator
        self.last_step: TRPOStepResult | ClippedStepResult | None = None
        self.last_critic_fit: CriticFitResult | None = None
        self.consecutive_skips = 0
        self.critic_fit = critic_fit
        self._lagged_batch: TensorDictBase | None = None  # critic_fit=lagged: the batch whose fit is pending
        self.critic_process = (CriticFitProcess(fit_critic, loss_module, self.critic_optimizer, critic_epochs,
                                                critic_minibatch_size, generator)
                               if critic_fit == "process" else None)

    @property
    def skip_reasons(self) -> list[str]:
        """Why the last update skipped its policy step and/or critic fit (empty if neither)."""
        reasons = []
        if self.last_step is not None and not self.last_step.accepted:
            reasons.append(f"policy step: {self.last_step.skip_reason}")
        if self.last_critic_fit is not None and not self.last_critic_fit.fitted:
            reasons.append(f"critic fit: {self.last_critic_fit.skip_reason}")
        return reasons

    def update(self, batch: TensorDictBase) -> dict[str, float]:
        """Update policy and critic on ``batch`` (advantage keys are written into it)."""
        loss = self.loss_module
        loss.compute_advantage(batch)
        flat = batch.reshape(-1)
        advantage = loss.advantage(flat)
        if self.clipped_step is not None:
            step = self.clipped_step(flat, advantage)
        else:
            step = natural_gradient_step(loss, flat, advantage=advantage, trust_region=self.trust_region)
        self.last_step = step
        metrics = step.as_metrics("train/")
        metrics["train/explained_variance"] = explained_variance(
            flat.get(loss.tensor_keys.value), flat.get(loss.tensor_keys.value_target)
        )
        if self.critic_fit == "inline":
            critic_fit = self._fit(flat)
        else:  # the previous batch's fit, then this one's started (or kept) until the next update
            critic_fit = self._apply_pending_fit() or CriticFitResult(True, None)
            if self.critic_process is not None:
                self.critic_process.start_fit(flat)
            else:
                self._lagged_batch = flat
        self.last_critic_fit = critic_fit
        metrics.update(critic_fit.as_metrics("train/"))
        self.consecutive_skips = 0 if step.accepted and critic_fit.fitted else self.consecutive_skips + 1
        metrics["train/consecutive_skips"] = float(self.consecutive_skips)
        return metrics

    def finish_critic_fit(self) -> CriticFitResult | None:
        """Applies the pending critic fit (``critic_fit`` lagged or process), if any, outside an update
        (before a normaliser refresh or a checkpoint); its result. A fit skipped here counts as a
        skipped update (``consecutive_skips``, ``skip_reasons``), as it would have inside the next
        update: a critic that keeps failing stops the run whenever its fits are applied."""
        result = self._apply_pending_fit()
        if result is not None and not result.fitted:
            self.last_critic_fit = result
            self.consecutive_skips += 1
        return result

    def _apply_pending_fit(self) -> CriticFitResult | None:
        if self.critic_process is not None and self.critic_process.pending:
            return self.critic_process.finish()
        if self._lagged_batch is not None:
            batch, self._lagged_batch = self._lagged_batch, None
            return self._fit(batch)
        return None

    def critic_changed(self) -> None:
        """Tells the fit's process that the critic's weights were changed outside a fit."""
        if self.critic_process is not None:
            self.critic_process.push_weights()

    def critic_optimizer_state(self) -> tuple[dict, torch.Tensor | None]:
        """The critic's Adam state and the fit generator's state (the fit's process has them once it runs)."""
        if self.critic_process is not None and self.critic_process.started:
            return self.critic_process.optimizer_state()
        return self.critic_optimizer.state_dict(), None if self.generator is None else self.generator.get_state()

    def load_critic_optimizer_state(self, optimizer_state: dict, generator_state: torch.Tensor | None) -> None:
        if self.critic_process is not None and self.critic_process.started:  # (one not yet forked inherits these)
            self.critic_process.load_optimizer_state(optimizer_state, generator_state)
            return
        self.critic_optimizer.load_state_dict(optimizer_state)
        if generator_state is not None:
            self.generator.set_state(generator_state)

    def close(self) -> None:
        """Ends the fit's process, if one runs."""
        if self.critic_process is not None:
            self.critic_process.close()

    def _fit(self, flat: TensorDictBase) -> CriticFitResult:
        return fit_critic(self.loss_module, flat, self.critic_optimizer, self.critic_epochs,
                          self.critic_minibatch_size, self.generator)
