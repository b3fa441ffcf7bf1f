"""REDQ-SAC (Chen et al. 2021, "Randomized Ensembled Double Q-Learning").

``n`` critics, all trained on the same targets; each target takes the minimum over a random
subset of ``m`` target critics; the actor maximises the mean of all ``n`` critics and is updated
once every ``q_updates_per_policy_update`` critic updates (the update-to-data ratio). The ``n``
critics are one :class:`~tmrl.models.EnsembleQFunction`, evaluated by batched matrix products.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

import torch

from tmrl.algorithms.sac import SACAgent, _build_model
from tmrl.errors import UserError
from tmrl.models import REDQMLPActorCritic

__all__ = ["REDQSACAgent"]


class REDQSACAgent(SACAgent):
    """REDQ-SAC. Takes every argument of :class:`~tmrl.algorithms.sac.SACAgent` (same meaning;
    ``model_cls`` defaults to :class:`~tmrl.models.REDQMLPActorCritic`) plus:

    Args:
        n: number of critics; passed to ``model_cls`` as ``n=`` when it accepts it.
        m: size of the random subset of target critics whose minimum makes the target.
        q_updates_per_policy_update: critic updates per actor (and entropy) update.

    Raises:
        UserError: ``m`` not in ``[1, n]``, ``q_updates_per_policy_update < 1``, or a model
            whose number of critics is not ``n``; plus :class:`SACAgent`'s errors.
    """

    def __init__(
        self,
        observation_space: Any = None,
        action_space: Any = None,
        device: Any = None,
        model_cls: Callable[..., torch.nn.Module] = REDQMLPActorCritic,
        gamma: float = 0.99,
        polyak: float = 0.995,
        alpha: float = 0.2,
        lr_actor: float = 1e-3,
        lr_critic: float = 1e-3,
        lr_entropy: float = 1e-3,
        learn_entropy_coef: bool = True,
        target_entropy: float | None = None,
        optimizer_actor: str = "adam",
        optimizer_critic: str = "adam",
        betas_actor: Sequence[float] | None = None,
        betas_critic: Sequence[float] | None = None,
        l2_actor: float | None = None,
        l2_critic: float | None = None,
        n: int = 10,
        m: int = 2,
        q_updates_per_policy_update: int = 1,
    ) -> None:
        self.n = int(n)
        self.m = int(m)
        self.q_updates_per_policy_update = int(q_updates_per_policy_update)
        if not 1 <= self.m <= self.n:
            raise UserError(f"REDQ needs 1 <= m <= n, got n={n}, m={m}: fix ALG.REDQ_M / ALG.REDQ_N")
        if self.q_updates_per_policy_update < 1:
            raise UserError(
                f"q_updates_per_policy_update={q_updates_per_policy_update} must be >= 1 "
                "(ALG.REDQ_Q_UPDATES_PER_POLICY_UPDATE)"
            )
        super().__init__(
            observation_space=observation_space,
            action_space=action_space,
            device=device,
            model_cls=model_cls,
            gamma=gamma,
            polyak=polyak,
            alpha=alpha,
            lr_actor=lr_actor,
            lr_critic=lr_critic,
            lr_entropy=lr_entropy,
            learn_entropy_coef=learn_entropy_coef,
            target_entropy=target_entropy,
            optimizer_actor=optimizer_actor,
            optimizer_critic=optimizer_critic,
            betas_actor=betas_actor,
            betas_critic=betas_critic,
            l2_actor=l2_actor,
            l2_critic=l2_critic,
        )
        if len(self.critics) != self.n:
            raise UserError(
                f"REDQ was asked for n={self.n} critics but {getattr(model_cls, '__name__', model_cls)} built "
                f"{len(self.critics)}: give the model an `n` argument or set ALG.REDQ_N={len(self.critics)}"
            )
        self.i_update = 0
        self.loss_pi = torch.zeros((), device=self.device)
        self.loss_alpha = torch.zeros((), device=self.device)

    def _make_model(self) -> torch.nn.Module:
        return _build_model(self.model_cls, self.observation_space, self.action_space, n=self.n)

    def train(self, batch: tuple) -> dict[str, Any]:
        """One REDQ critic update, plus an actor (and entropy) update every
        ``q_updates_per_policy_update`` calls.

        Returns:
            Same metrics as :meth:`SACAgent.train`; ``loss_actor`` and ``loss_entropy_coef``
            are those of the latest actor update.
        """
        self.i_update += 1
        update_policy = self.i_update % self.q_updates_per_policy_update == 0
        o, a, r, o2, d, _ = batch  # the truncated flag is deliberately unused
        r = r.reshape(-1)
        d = d.reshape(-1)
        alpha = self._entropy_coef()  # defined on every update, learned or not

        with torch.no_grad():
            a2, logp_a2 = self.actor(o2)
            # Global torch RNG, so that torch.manual_seed makes runs reproducible.
            subset = torch.randperm(self.n)[: self.m]
            q_targ = self.critics_target(o2, a2, members=subset).min(0).values
            # Bootstrap unless terminated; truncated transitions keep their future value.
            backup = r + self.gamma * (1.0 - d) * (q_targ - alpha * logp_a2)

        pi = logp_pi = None
        if update_policy:
            pi, logp_pi = self.actor(o)
        # q (n, B); on policy updates also Q(o, pi) with the critic weights detached.
        q, q_pi_all = self.critics.with_policy_values(o, a, pi)
        loss_critic = (q - backup).square().mean()  # mean over critics: homogeneous with SAC
        loss = loss_critic

        if q_pi_all is not None and logp_pi is not None:
            # Mean over all n critics: this loss moves the actor only.
            q_pi = q_pi_all.mean(0)
            loss_actor = (alpha * logp_pi - q_pi).mean()
            loss = loss + loss_actor
            self.loss_pi = loss_actor.detach()
            if self.log_alpha is not None:
                loss_alpha = -(self.log_alpha * (logp_pi.detach() + self.target_entropy)).mean()
                loss = loss + loss_alpha
                self.loss_alpha = loss_alpha.detach()

        self.q_optimizer.zero_grad(set_to_none=True)
        if update_policy:
            self.pi_optimizer.zero_grad(set_to_none=True)
            if self.alpha_optimizer is not None:
                self.alpha_optimizer.zero_grad(set_to_none=True)
        loss.backward()
        if not self.guard.update_ok(loss, self._guarded):
            return self.guard.skipped_metrics()
        self.q_optimizer.step()
        if update_policy:
            self.pi_optimizer.step()
            if self.alpha_optimizer is not None:
                self.alpha_optimizer.step()
        self._update_targets()

        metrics: dict[str, Any] = {
            "loss_actor": self.loss_pi,
            "loss_critic": loss_critic.detach(),
            "entropy_coef": alpha,
            "debug_q": q.detach().mean(),
            "debug_backup": backup.mean(),
        }
        if logp_pi is not None:
            metrics["debug_log_pi"] = logp_pi.detach().mean()
        if self.log_alpha is not None:
            metrics["loss_entropy_coef"] = self.loss_alpha
        return metrics

    def state_dict(self) -> dict[str, Any]:
        """:meth:`SACAgent.state_dict` plus the update counter (it decides actor updates)."""
        state = super().state_dict()
        state["i_update"] = self.i_update
        state["loss_actor"] = self.loss_pi
        return state

    def _load_extra_state(self, state: dict[str, Any]) -> None:
        self.i_update = int(state["i_update"])
        self.loss_pi = torch.as_tensor(state.get("loss_actor", 0.0), device=self.device).reshape(())
