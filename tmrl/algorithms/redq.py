"""REDQ-SAC (Chen et al. 2021, "Randomized Ensembled Double Q-Learning").

SAC's update (:meth:`tmrl.algorithms.sac.SACAgent.train`) with three of its steps changed:
``n`` critics all regress on one target, which takes the minimum over a random subset of ``m``
target critics (:meth:`REDQSACAgent.target_q`); the actor maximises the mean of all ``n``
critics (:meth:`REDQSACAgent.policy_q`); and the actor and the entropy coefficient are updated
once every ``q_updates_per_policy_update`` critic updates (:meth:`REDQSACAgent.policy_update_due`,
the update-to-data ratio). The ``n`` critics are one :class:`~tmrl.models.EnsembleQFunction`,
evaluated by batched matrix products.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

import torch

from tmrl.algorithms.sac import SACAgent, _build_model
from tmrl.config.schema import redq_subset_problem
from tmrl.errors import UserError
from tmrl.models import REDQMLPActorCritic

__all__ = ["REDQSACAgent"]


class REDQSACAgent(SACAgent):
    """REDQ-SAC. Takes every argument of :class:`~tmrl.algorithms.sac.SACAgent` but
    ``update_order`` and ``fused`` (same meaning; ``model_cls`` defaults to
    :class:`~tmrl.models.REDQMLPActorCritic`) plus:

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
        alpha_max: float | None = None,
        optimizer_actor: str = "adam",
        optimizer_critic: str = "adam",
        betas_actor: Sequence[float] | None = None,
        betas_critic: Sequence[float] | None = None,
        l2_actor: float | None = None,
        l2_critic: float | None = None,
        compile: str = "off",
        n: int = 10,
        m: int = 2,
        q_updates_per_policy_update: int = 1,
    ) -> None:
        self.n = int(n)
        self.m = int(m)
        self.q_updates_per_policy_update = int(q_updates_per_policy_update)
        problem = redq_subset_problem(self.n, self.m)
        if problem:
            raise UserError(f"REDQ-SAC needs 1 <= m <= n, got n={n}, m={m}: {problem}")
        if self.q_updates_per_policy_update < 1:
            raise UserError(
                f"q_updates_per_policy_update={q_updates_per_policy_update} must be >= 1 "
                "(ALG.REDQ_Q_UPDATES_PER_POLICY_UPDATE)"
            )
        self.i_update = 0
        # The target subset drawn ahead (off a CPU): on the CPU and on the device.
        self._subset: tuple[torch.Tensor, torch.Tensor] | None = None
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
            alpha_max=alpha_max,
            optimizer_actor=optimizer_actor,
            optimizer_critic=optimizer_critic,
            betas_actor=betas_actor,
            betas_critic=betas_critic,
            l2_actor=l2_actor,
            l2_critic=l2_critic,
            compile=compile,
        )
        if len(self.critics) != self.n:
            raise UserError(
                f"REDQ was asked for n={self.n} critics but {getattr(model_cls, '__name__', model_cls)} built "
                f"{len(self.critics)}: give the model an `n` argument or set ALG.REDQ_N={len(self.critics)}"
            )

    def _make_model(self) -> torch.nn.Module:
        return _build_model(self.model_cls, self.observation_space, self.action_space, n=self.n)

    # --- the steps that differ from SAC ---------------------------------------------------------

    def policy_update_due(self) -> bool:
        """Counts the update; true once every ``q_updates_per_policy_update`` of them."""
        self.i_update += 1
        return self.i_update % self.q_updates_per_policy_update == 0

    def target_q(self, next_obs: Any, next_act: torch.Tensor) -> torch.Tensor:
        """The minimum over a random subset of ``m`` of the ``n`` target critics (drawn from the
        global torch generator, so that ``torch.manual_seed`` makes runs reproducible).

        Args:
            next_obs: the batch's next observations ``o'``.
            next_act: actions ``a'`` drawn from the current policy at ``o'``.
        """
        if self._subset is None:
            subset = torch.randperm(self.n)[: self.m]
        else:  # the device's copy for an ensemble, the CPU's to pick modules from
            subset = self._subset[1] if self.critics_target.ensemble is not None else self._subset[0]
        return self.critics_target(next_obs, next_act, members=subset).min(0).values

    def _prepare_batch(self, b: Any) -> Any:
        """Off a CPU, the target subset is drawn here, before the forward pass, and sent to the
        device without waiting: the CPU generator it comes from is not the device's, whose draws
        (the actions) it would follow on a CPU, so the subset is the one :meth:`target_q` would
        draw, and a compiled or captured forward pass holds no CPU operation."""
        if self.device.type != "cpu":
            subset = torch.randperm(self.n)[: self.m]
            staged = subset.pin_memory() if self.device.type == "cuda" else subset  # pageable would wait
            self._subset = (subset, staged.to(self.device, non_blocking=True))
        return b

    def policy_q(self, q_pi_all: torch.Tensor) -> torch.Tensor:
        """The mean over all ``n`` critics.

        Args:
            q_pi_all: ``Q(o, pi)`` of every critic, shape ``(n, B)``.
        """
        return q_pi_all.mean(0)

    # --- checkpointing ------------------------------------------------------------------------

    def state_dict(self) -> dict[str, Any]:
        """:meth:`SACAgent.state_dict` plus the update counter (it decides policy updates) and
        the losses of the latest policy update (reported until the next one)."""
        state = super().state_dict()
        state["i_update"] = self.i_update
        state["loss_actor"] = self.loss_pi
        state["loss_entropy_coef"] = self.loss_alpha
        return state

    def _load_extra_state(self, state: dict[str, Any]) -> None:
        self.i_update = int(state["i_update"])
        for attr, key in (("loss_pi", "loss_actor"), ("loss_alpha", "loss_entropy_coef")):
            value = torch.as_tensor(state.get(key, 0.0), device=self.device).reshape(())
            setattr(self, attr, value)
