"""Soft Actor-Critic (SAC v1 with a fixed entropy coefficient, v2 with a learned one).

One update reads top to bottom in :meth:`SACAgent.train`. Two choices make it fast without
changing what is learned:

- the twin critics are one :class:`~tmrl.models.EnsembleQFunction`, evaluated by one batched
  matrix product per layer;
- the critic, actor and entropy losses share one backward pass. The actor's loss evaluates the
  critics with detached weights, so critic weights get gradients from the critic loss only, and
  all three optimizers step on gradients computed from the same (pre-update) parameters.

The original tmrl SAC evaluates its actor loss against the critics *after* their optimizer step;
by default ours does it *before* (``update_order="simultaneous"``, as the original tmrl REDQ-SAC
and the REDQ authors' code do), which saves a second critic pass. ``update_order="sequential"``
(config ``ALG.UPDATE_ORDER``) gives the original's order: the critic and entropy steps first,
then the actor loss on the updated critics, with a backward pass of its own.
``python -m bench pendulum_learning`` compares the two.
"""

from __future__ import annotations

import copy
import inspect
import logging
import math
from collections.abc import Callable, Iterable, Sequence
from typing import Any, cast

import numpy as np
import torch

from tmrl.actor import TorchActorModule
from tmrl.algorithms.compiled_sac import (
    CompileState,
    compile_mode_for,
    compiled_functions,
    first_compiled_update,
)
from tmrl.algorithms.critics import CriticSet
from tmrl.algorithms.fused_sac import FusedSACUpdate
from tmrl.algorithms.guard import GuardedUpdate, NonFiniteGuard, optimizer_state, stepped_tensors
from tmrl.batch import Batch
from tmrl.config.schema import COMPILE_MODES, OPTIMIZERS, UPDATE_ORDERS
from tmrl.errors import UserError
from tmrl.models import MLPActorCritic
from tmrl.nn import copy_shared, no_grad
from tmrl.training import TrainingAgent
from tmrl.util import cached_property

__all__ = ["COMPILE_MODES", "UPDATE_ORDERS", "CriticSet", "SACAgent", "SpinupSacAgent", "make_optimizer"]

logger = logging.getLogger(__name__)

_OPTIMIZERS: dict[str, Callable[..., torch.optim.Optimizer]] = {
    "adam": torch.optim.Adam,
    "adamw": torch.optim.AdamW,
    "sgd": torch.optim.SGD,
}
"""The optimizer of each name of :data:`tmrl.config.schema.OPTIMIZERS` (a test checks they match)."""


def make_optimizer(
    name: str,
    params: Iterable[torch.Tensor],
    lr: float,
    betas: Sequence[float] | None = None,
    weight_decay: float | None = None,
    what: str = "optimizer",
) -> torch.optim.Optimizer:
    """Build an optimizer by name, fused (or foreach) when PyTorch supports it for the params.

    Args:
        name: ``"adam"``, ``"adamw"`` or ``"sgd"`` (case-insensitive).
        params: the parameters to optimise.
        lr: learning rate.
        betas: Adam/AdamW betas (None: PyTorch's default); ignored by SGD.
        weight_decay: weight decay (None: the optimizer's default).
        what: the config key this choice comes from, for error messages.

    Raises:
        UserError: unknown optimizer name or malformed betas.
    """
    key = str(name).lower()
    if key not in _OPTIMIZERS:
        raise UserError(f"{what}={name!r} is not a known optimizer: use one of {', '.join(map(repr, OPTIMIZERS))}")
    params = list(params)
    kwargs: dict[str, Any] = {"lr": float(lr)}
    if betas is not None and key in ("adam", "adamw"):
        try:
            b1, b2 = (float(b) for b in betas)
        except (TypeError, ValueError):
            raise UserError(
                f"betas for {what} must be two numbers like [0.9, 0.999], got {betas!r}"
            ) from None
        kwargs["betas"] = (b1, b2)
    elif betas is not None:
        logger.warning("betas %s are ignored by %s=%r (SGD has no betas)", betas, what, name)
    if weight_decay is not None:
        kwargs["weight_decay"] = float(weight_decay)
    cls = _OPTIMIZERS[key]
    # Fused kernels update every tensor in one call; fall back to foreach where the device or
    # dtype does not support them (the arithmetic is the same).
    for extra in ({"fused": True}, {"foreach": True}, {}):
        try:
            return cls(params, **kwargs, **extra)
        except (RuntimeError, TypeError, ValueError):
            continue
    raise AssertionError("unreachable: plain optimizer construction failed")


def _build_model(
    model_cls: Callable[..., torch.nn.Module], observation_space: Any, action_space: Any, **extra: Any
) -> torch.nn.Module:
    """Call ``model_cls(observation_space, action_space, **extra)``, passing each extra keyword
    only when the callable accepts it (a user model may not take ``n``)."""
    try:
        params = inspect.signature(model_cls).parameters
        takes_kwargs = any(p.kind is inspect.Parameter.VAR_KEYWORD for p in params.values())
        accepted = {k: v for k, v in extra.items() if takes_kwargs or k in params}
    except (TypeError, ValueError):
        accepted = {}
    return model_cls(observation_space, action_space, **accepted)


def _resolve_device(device: Any) -> torch.device:
    if device is None:
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    try:
        return torch.device(device)
    except (RuntimeError, TypeError):
        raise UserError(f"device {device!r} is not a torch device: use 'cpu', 'cuda' or 'cuda:N'") from None


class SACAgent(TrainingAgent):
    """Soft Actor-Critic with twin critics and Polyak-averaged targets.

    Args:
        observation_space: the (preprocessed) observation space.
        action_space: the action space (a bounded Box).
        device: training device; None picks ``"cuda"`` when available, else ``"cpu"``.
        model_cls: actor-critic class (or partial) called as ``model_cls(observation_space,
            action_space)``; it needs ``.actor`` (a :class:`~tmrl.actor.TorchActorModule`
            whose forward returns ``(action, logp)``) and critics (``.qs`` or ``.q1``/``.q2``).
        gamma: discount factor.
        polyak: target update factor, ``target <- polyak * target + (1 - polyak) * online``.
        alpha: entropy coefficient: fixed (``learn_entropy_coef=False``, SAC v1) or initial
            value (SAC v2).
        lr_actor: actor learning rate.
        lr_critic: critic learning rate.
        lr_entropy: learning rate of ``log_alpha`` (SAC v2), optimised with Adam.
        learn_entropy_coef: learn alpha toward ``target_entropy`` (SAC v2).
        target_entropy: target policy entropy; None means ``-act_dim``.
        alpha_max: a ceiling for a learned coefficient, from the first update that finds it at or
            under ``alpha_max``: from then on each update that moves it above is cut back to it
            (it starts above when ``alpha > alpha_max``, and falls freely until then). None: no
            ceiling. Ignored when the coefficient is fixed.
        optimizer_actor: ``"adam"``, ``"adamw"`` or ``"sgd"``.
        optimizer_critic: ``"adam"``, ``"adamw"`` or ``"sgd"``.
        betas_actor: Adam/AdamW betas of the actor optimizer (None: PyTorch's default).
        betas_critic: Adam/AdamW betas of the critic optimizer (None: PyTorch's default).
        l2_actor: weight decay of the actor optimizer (None: the optimizer's default).
        l2_critic: weight decay of the critic optimizer (None: the optimizer's default).
        update_order: ``"simultaneous"`` (one backward pass; the actor loss reads the critics
            before their step) or ``"sequential"`` (the original tmrl SAC: the actor loss reads
            the critics after their step; one more critic pass and backward per update).
        fused: use :class:`~tmrl.algorithms.fused_sac.FusedSACUpdate` (the same update with
            hand-written gradients, about twice as fast on a CPU) when the model and settings
            allow it; False always takes the autograd path.
        compile: ``ALG.COMPILE``: ``"off"`` (eager; the fused update where it applies),
            ``"compile"`` (the update's forward passes and losses, the methods of
            :attr:`COMPILED`, through :func:`torch.compile`) or ``"cudagraph"`` (the same,
            replayed as CUDA graphs; CUDA devices only). Every built-in agent's update compiles;
            the sequential order, or a subclass with a ``train`` of its own, logs one warning and
            runs eager. See :mod:`tmrl.algorithms.compiled_sac`.

    Raises:
        UserError: an unknown optimizer, malformed betas, an unknown device, an unknown
            update order, an unknown compile mode, ``"cudagraph"`` off CUDA, or a model without
            critics.
    """

    model_nograd = cached_property(lambda self: no_grad(copy_shared(self.model)))

    STEPS = ("train", "policy_update_due", "target_q", "policy_q", "target_value", "critic_loss", "actor_loss",
             "entropy_loss")
    """The steps a subclass may override; the fused update computes SAC's own and is used only
    when none of them is overridden."""

    @classmethod
    def overridden_steps(cls) -> list[str]:
        """The steps of :attr:`STEPS` that this class defines differently from SAC's own, in
        :attr:`STEPS` order (empty for SAC itself)."""
        return [step for step in SACAgent.STEPS if getattr(cls, step) is not getattr(SACAgent, step)]

    def __init__(
        self,
        observation_space: Any = None,
        action_space: Any = None,
        device: Any = None,
        model_cls: Callable[..., torch.nn.Module] = MLPActorCritic,
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
        update_order: str = "simultaneous",
        fused: bool = True,
        compile: str = "off",
    ) -> None:
        if compile not in COMPILE_MODES:
            raise UserError(f"ALG.COMPILE={compile!r} is not known: use one of {', '.join(map(repr, COMPILE_MODES))}")
        if update_order not in UPDATE_ORDERS:
            raise UserError(
                f"update_order={update_order!r} is not known: set ALG.UPDATE_ORDER to one of "
                f"{', '.join(UPDATE_ORDERS)}"
            )
        self.update_order = update_order
        device = _resolve_device(device)
        if compile == "cudagraph" and device.type != "cuda":
            raise UserError(
                f"ALG.COMPILE='cudagraph': cudagraph needs a CUDA device, the training device is {device} "
                "(use 'compile' or 'off', or train on a GPU)"
            )
        super().__init__(observation_space, action_space, device)
        self.model_cls = model_cls
        self.gamma = float(gamma)
        self.polyak = float(polyak)
        self.alpha = float(alpha)
        self.lr_actor = lr_actor
        self.lr_critic = lr_critic
        self.lr_entropy = lr_entropy
        self.learn_entropy_coef = bool(learn_entropy_coef)
        self.optimizer_actor = optimizer_actor
        self.optimizer_critic = optimizer_critic
        self.betas_actor = betas_actor
        self.betas_critic = betas_critic
        self.l2_actor = l2_actor
        self.l2_critic = l2_critic
        if not 0.0 <= self.polyak <= 1.0:
            raise UserError(f"polyak={polyak} must lie in [0, 1] (ALG.POLYAK), typically 0.995")
        if self.alpha <= 0.0 and self.learn_entropy_coef:
            raise UserError(f"alpha={alpha} must be > 0 when the entropy coefficient is learned (ALG.ALPHA)")
        if alpha_max is not None and not alpha_max > 0.0:
            raise UserError(f"alpha_max={alpha_max} must be > 0, or null for no ceiling (ALG.ALPHA_MAX)")
        self.alpha_max = None if alpha_max is None else float(alpha_max)

        self.model = self._make_model().to(device)
        self.model_target = no_grad(copy.deepcopy(self.model))
        # The actor: a TorchActorModule whose forward returns (action, logp).
        self.actor: torch.nn.Module = cast(torch.nn.Module, self.model.actor)
        self.critics = CriticSet(self.model)
        self.critics_target = CriticSet(self.model_target)

        self._make_optimizers()
        self._make_entropy_coef(target_entropy, lr_entropy)
        # log(alpha_max) rounded to log_alpha's precision: the value a cut writes, so that a
        # coefficient cut back to it reads as at the ceiling at the next step (in float64 the
        # rounded value can lie just above, for example for 0.07). None: no ceiling acts.
        self._log_alpha_max: float | None = None
        if self.log_alpha is not None and self.alpha_max is not None:
            self._log_alpha_max = float(torch.tensor(math.log(self.alpha_max), dtype=self.log_alpha.dtype))

        # Same order in both lists: Polyak averaging pairs them up.
        self._params: list[torch.Tensor] = list(self.model.parameters())
        self._target_params: list[torch.Tensor] = list(self.model_target.parameters())
        # Non-finite losses or gradients skip the update (tmrl/algorithms/guard.py), decided on
        # the device off a CPU (no synchronisation per update).
        self.guard = NonFiniteGuard(device_side=device.type != "cpu")
        self._guarded: list[torch.Tensor] = self._params + ([self.log_alpha] if self.log_alpha is not None else [])
        # The losses of the latest policy update (reported by updates that do not update it).
        self.loss_pi = torch.zeros((), device=device)
        self.loss_alpha = torch.zeros((), device=device)
        self.fused_update: FusedSACUpdate | None = FusedSACUpdate.for_agent(self) if fused else None
        self.compile = compile
        self._compile_state = CompileState(compile_mode_for(self, compile))

    def _make_optimizers(self) -> None:
        self.pi_optimizer = make_optimizer(
            self.optimizer_actor, self.actor.parameters(), self.lr_actor, self.betas_actor, self.l2_actor,
            "optimizer_actor",
        )
        self.q_optimizer = make_optimizer(
            self.optimizer_critic, self.critics.parameters(), self.lr_critic, self.betas_critic, self.l2_critic,
            "optimizer_critic",
        )

    def _make_entropy_coef(self, target_entropy: float | None, lr_entropy: float) -> None:
        """``alpha_t`` (fixed, SAC v1) or ``log_alpha`` and its Adam optimizer (learned, SAC v2)."""
        device = self.device
        if target_entropy is None:
            self.target_entropy = -float(np.prod(self.action_space.shape))
        else:
            self.target_entropy = float(target_entropy)
        self.log_alpha: torch.Tensor | None = None
        self.alpha_optimizer: torch.optim.Optimizer | None = None
        if self.learn_entropy_coef:
            # Optimise log(alpha) rather than alpha (softlearning issue 37): it stays positive.
            self.log_alpha = torch.tensor(math.log(self.alpha), device=device, requires_grad=True)
            self.alpha_optimizer = make_optimizer("adam", [self.log_alpha], lr_entropy, what="lr_entropy")
        self.alpha_t = torch.tensor(self.alpha, device=device)

    @property
    def skipped_updates(self) -> int:
        """Updates skipped because their loss or gradients were not finite."""
        return self.guard.skipped

    def _make_model(self) -> torch.nn.Module:
        return _build_model(self.model_cls, self.observation_space, self.action_space)

    def get_actor(self) -> TorchActorModule:
        """The actor, sharing parameter memory with the trained one (no copy, no gradients)."""
        return cast(TorchActorModule, self.model_nograd.actor)

    def _entropy_coef(self) -> torch.Tensor:
        if self.log_alpha is not None:
            return self.log_alpha.detach().exp()
        return self.alpha_t

    def _at_alpha_max(self, on_device: bool = False) -> bool | torch.Tensor:
        """Whether the learned coefficient is at or under ``alpha_max`` (read before its step):
        a bool, or with ``on_device`` a 0-d boolean tensor (nothing read on the host)."""
        cap = self._log_alpha_max
        if cap is None:
            return False
        log_alpha = cast(torch.Tensor, self.log_alpha).detach()
        if on_device:
            return log_alpha <= cap
        return float(log_alpha) <= cap

    @torch.no_grad()
    def _hold_alpha(self, was_at_max: bool | torch.Tensor) -> None:
        """After the coefficient's step: back to ``alpha_max`` if it was at or under it before
        (``was_at_max`` as :meth:`_at_alpha_max` returned it)."""
        log_alpha = cast(torch.Tensor, self.log_alpha)
        if isinstance(was_at_max, torch.Tensor):
            log_alpha.copy_(torch.where(was_at_max, log_alpha.clamp(max=self._log_alpha_max), log_alpha))
        elif was_at_max:
            log_alpha.clamp_(max=self._log_alpha_max)

    @torch.no_grad()
    def _update_targets(self) -> None:
        # target <- polyak * target + (1 - polyak) * online, every tensor in one call.
        torch._foreach_lerp_(self._target_params, self._params, 1.0 - self.polyak)

    # --- one update, top to bottom ------------------------------------------------------------

    def train(self, batch: tuple) -> dict[str, Any]:
        """One update on ``batch`` (a :class:`~tmrl.batch.Batch`, or any 6-tuple ``(obs, act,
        rew, next_obs, terminated, truncated)``), in the order of the SAC paper: the soft
        Bellman target from the target critics, the critics' regression on it, then (when
        :meth:`policy_update_due`) the actor and the entropy coefficient, and Polyak averaging.
        Subclasses change the steps below, not this method.

        With ``ALG.COMPILE`` off the update runs eager: the fused update where it applies, else
        :meth:`_update_with` on :meth:`_update_losses` (the simultaneous order) or the sequential
        order below; with it on, :meth:`_update_with` on the compiled :meth:`_update_losses`.

        Returns:
            ``loss_actor`` and ``loss_entropy_coef`` (SAC v2) of the latest policy update,
            ``loss_critic``, ``entropy_coef`` (the coefficient used in this update) and a few
            ``debug_*`` means, all 0-dim tensors (``float()`` them to log).
        """
        if self._compile_state.mode != "off":
            return self._compiled_train(batch)
        return self._update_off(batch, self.policy_update_due())

    def _update_off(self, batch: tuple, update_policy: bool) -> dict[str, Any]:
        """The eager update (``ALG.COMPILE`` off), :meth:`policy_update_due` already asked."""
        fused = self._fused()
        if fused is not None:
            return fused(batch)
        if self.update_order == "simultaneous":
            return self._update_with(self._eager_functions(), batch, update_policy)
        return self._sequential_update(batch, update_policy)

    def _sequential_update(self, batch: tuple, update_policy: bool) -> dict[str, Any]:
        """The sequential order (the original tmrl SAC): the critics' and the entropy
        coefficient's step, then the actor loss on the updated critics with a backward pass of
        its own, then Polyak averaging."""
        b = Batch(*batch)
        alpha = self._entropy_coef()
        g = self._begin_update(update_policy)
        # a ~ pi(.|o), reparameterised: what the actor and entropy losses differentiate through
        pi, logp_pi = self.actor(b.obs) if update_policy else (None, None)
        backup = self.target_value(b, alpha)
        q, _ = self.critics.with_policy_values(b.obs, b.act, None)
        loss_critic = self.critic_loss(q, backup)
        loss_alpha = self.entropy_loss(logp_pi) if logp_pi is not None else None
        if not self._step(loss_critic, None, loss_alpha, update_policy, g, targets=False):
            return self.guard.skipped_metrics()
        g.restore()  # on the device: the critics' step stands alone when finite, as on the host
        loss_actor = None
        if update_policy:
            loss_actor = self._actor_step_after_critics(b.obs, alpha, pi, logp_pi, g)
            if loss_actor is None:
                return self.guard.skipped_metrics()
        g.keep(self._target_params)
        self._update_targets()
        if loss_actor is not None:
            self.loss_pi = g.pick(loss_actor.detach(), self.loss_pi)
        if loss_alpha is not None:
            self.loss_alpha = g.pick(loss_alpha.detach(), self.loss_alpha)
        return g.finish(self._metrics(alpha, loss_critic, q, backup, logp_pi))

    # --- the steps (REDQ and other agents override these) -------------------------------------

    def policy_update_due(self) -> bool:
        """Whether this update also steps the actor and the entropy coefficient. Called once at
        the start of every update. SAC: always."""
        return True

    def target_q(self, next_obs: Any, next_act: torch.Tensor) -> torch.Tensor:
        """``Q_targ(o', a')``, shape ``(B,)``. SAC: the minimum over the target critics (clipped
        double Q).

        Args:
            next_obs: the batch's next observations ``o'``.
            next_act: actions ``a'`` drawn from the current policy at ``o'``.
        """
        return self.critics_target(next_obs, next_act).min(0).values

    def policy_q(self, q_pi_all: torch.Tensor) -> torch.Tensor:
        """The value the actor maximises, from the critics' ``Q(o, pi)`` ``(k, B)``. SAC: their
        minimum.

        Args:
            q_pi_all: ``Q(o, pi)`` of every critic, shape ``(k, B)``.
        """
        return q_pi_all.min(0).values

    @torch.no_grad()
    def target_value(self, batch: Batch, alpha: torch.Tensor) -> torch.Tensor:
        """The soft Bellman target ``r + gamma (1 - terminated) (Q_targ(o', a') - alpha log pi(a'|o'))``
        with ``a' ~ pi(.|o')`` from the current policy, shape ``(B,)``.

        Bootstraps unless the episode *terminated*: a truncated episode would have gone on, so
        its last transition keeps its future value (the truncated flag is deliberately unused).

        Args:
            batch: the training batch (:class:`tmrl.batch.Batch`).
            alpha: the entropy coefficient.
        """
        a2, logp_a2 = self.actor(batch.next_obs)
        r, d = batch.rew.reshape(-1), batch.terminated.reshape(-1)
        return r + self.gamma * (1.0 - d) * (self.target_q(batch.next_obs, a2) - alpha * logp_a2)

    def critic_loss(self, q: torch.Tensor, backup: torch.Tensor) -> torch.Tensor:
        """The critics' regression on the target. SAC: the squared error, averaged over critics
        (one scale for SAC and REDQ whatever the number of critics).

        Args:
            q: ``Q(o, a)`` of every critic, shape ``(k, B)``.
            backup: the target, as :meth:`target_value` returns it.
        """
        return (q - backup).square().mean()

    def actor_loss(self, alpha: torch.Tensor, logp_pi: torch.Tensor, q_pi_all: torch.Tensor) -> torch.Tensor:
        """``mean(alpha log pi(a|o) - policy_q(Q(o, a)))``, ``a ~ pi(.|o)``.

        Args:
            alpha: the entropy coefficient (no gradient).
            logp_pi: ``log pi(a|o)`` of the sampled actions, shape ``(B,)``.
            q_pi_all: ``Q(o, a)`` of every critic for those actions, shape ``(k, B)``.
        """
        return (alpha * logp_pi - self.policy_q(q_pi_all)).mean()

    def entropy_loss(self, logp_pi: torch.Tensor) -> torch.Tensor | None:
        """SAC v2's loss of ``log(alpha)`` toward ``target_entropy`` (None when alpha is fixed).

        Args:
            logp_pi: ``log pi(a|o)`` of the sampled actions (detached in the loss).
        """
        if self.log_alpha is None:
            return None
        return -(self.log_alpha * (logp_pi.detach() + self.target_entropy)).mean()

    # --- mechanics ------------------------------------------------------------------------------

    def _fused(self) -> FusedSACUpdate | None:
        """The fused update when this agent takes it (rebuilt for a copy of the agent)."""
        fused = self.fused_update
        if fused is not None and fused.agent is not self:  # this agent is a copy (copy.deepcopy)
            fused = self.fused_update = FusedSACUpdate.for_agent(self)
        return fused

    def _stepping_optimizers(self, update_policy: bool) -> list[torch.optim.Optimizer]:
        """The optimizers that step in an update (the actor's and the coefficient's only when
        ``update_policy``)."""
        optimizers = [self.q_optimizer]
        if update_policy:
            if self.alpha_optimizer is not None:
                optimizers.append(self.alpha_optimizer)
            optimizers.append(self.pi_optimizer)
        return optimizers

    def _begin_update(self, update_policy: bool) -> GuardedUpdate:
        """The non-finite guard of one update: on the device when the guard is device-side and
        the state of every optimizer that steps exists on its parameters' device (Adam creates
        it at its first step: that update is checked on the host)."""
        on_device = self.guard.device_side and optimizer_state(self._stepping_optimizers(update_policy)) is not None
        return GuardedUpdate(self.guard, on_device)

    def _step(
        self,
        loss_critic: torch.Tensor,
        loss_actor: torch.Tensor | None,
        loss_alpha: torch.Tensor | None,
        update_policy: bool,
        guard: GuardedUpdate | None = None,
        targets: bool = True,
    ) -> bool:
        """One backward pass through the sum of the losses, then a step of each optimizer whose
        loss is in it (the entropy coefficient's and the actor's only when ``update_policy``);
        False (and no step) when a loss or gradient is not finite and ``guard`` (default: on the
        host) decides on the host. On the device the steps run, and what they change (with the
        target parameters when ``targets``: the caller's Polyak averaging follows) is kept for
        ``guard`` to put back."""
        g = guard if guard is not None else GuardedUpdate(self.guard, False)
        if not update_policy:
            loss_actor = loss_alpha = None
        loss = loss_critic
        optimizers = [self.q_optimizer]
        if loss_alpha is not None:
            loss = loss + loss_alpha
            optimizers.append(cast(torch.optim.Optimizer, self.alpha_optimizer))
        if loss_actor is not None:
            loss = loss + loss_actor
            optimizers.append(self.pi_optimizer)
        for opt in optimizers:
            opt.zero_grad(set_to_none=True)
        if g.on_device:
            # The host check clears the gradients of a skipped update; the device's cannot, so
            # a NaN gradient left on a parameter that does not step now must not be checked again.
            for p in self._guarded:
                p.grad = None
        loss.backward()
        if not g.check(loss, self._guarded):
            return False
        if g.on_device:
            g.keep(stepped_tensors(optimizers) + (self._target_params if targets else []))
        held = loss_alpha is not None and self._at_alpha_max(g.on_device)
        for opt in optimizers:
            opt.step()
        self._hold_alpha(held)
        self._after_step(optimizers, g)
        return True

    def _after_step(self, optimizers: list[torch.optim.Optimizer], guard: GuardedUpdate) -> None:
        """Called after the optimizers of :meth:`_step` (and of the sequential order's actor
        step) have stepped, only when they did (a finite update, or on the device any update:
        ``guard`` puts back what it kept). Nothing for SAC; SimbaV2 projects its critics' weights
        back onto the unit sphere here. A subclass that changes tensors other than the stepped
        parameters, their optimizer state and the targets hands them to ``guard.keep`` before
        changing them, so that a non-finite update decided on the device puts them back.

        Args:
            optimizers: the optimizers that just stepped.
            guard: the update's non-finite guard.
        """

    def _actor_step_after_critics(
        self, obs: Any, alpha: torch.Tensor, pi: torch.Tensor, logp_pi: torch.Tensor,
        guard: GuardedUpdate | None = None,
    ) -> torch.Tensor | None:
        """The sequential order (the original tmrl SAC): the actor loss reads the critics after
        their step, with a backward pass of its own. None when its gradient is not finite (the
        critics have stepped already; the actor and the targets do not)."""
        g = guard if guard is not None else GuardedUpdate(self.guard, False)
        loss_actor = self.actor_loss(alpha, logp_pi, self.critics(obs, pi, detach_params=True))
        self.pi_optimizer.zero_grad(set_to_none=True)
        loss_actor.backward()
        if not g.check(loss_actor, self.actor.parameters()):
            return None
        if g.on_device:
            g.keep(stepped_tensors([self.pi_optimizer]))
        self.pi_optimizer.step()
        self._after_step([self.pi_optimizer], g)
        return loss_actor

    def _metrics(
        self,
        alpha: torch.Tensor,
        loss_critic: torch.Tensor,
        q: torch.Tensor,
        backup: torch.Tensor,
        logp_pi: torch.Tensor | None,
    ) -> dict[str, Any]:
        metrics: dict[str, Any] = {
            "loss_actor": self.loss_pi,
            "loss_critic": loss_critic.detach(),
            "entropy_coef": alpha,
        }
        if logp_pi is not None:
            metrics["debug_log_pi"] = logp_pi.detach().mean()
        metrics["debug_q"] = q.detach().mean()
        metrics["debug_backup"] = backup.mean()
        if self.log_alpha is not None:
            metrics["loss_entropy_coef"] = self.loss_alpha
        return metrics

    # --- one update as functions of the batch (ALG.COMPILE, tmrl/algorithms/compiled_sac.py) -----

    COMPILED: tuple[str, ...] = ("_update_losses",)
    """The methods :meth:`_update_with` calls with the batch, which ``ALG.COMPILE`` compiles
    (:func:`~tmrl.algorithms.compiled_sac.compiled_functions`)."""

    def _eager_functions(self) -> dict[str, Callable[..., Any]]:
        """The methods of :attr:`COMPILED`, eager."""
        return {name: getattr(self, name) for name in self.COMPILED}

    def _prepare_batch(self, b: Batch) -> Batch:
        """What an update does with the batch before its forward pass, eager in every mode (the
        random draws that must reach the device before a compiled or captured function runs):
        nothing for SAC; DrQ's random shifts, REDQ's target subset on a GPU."""
        return b

    def _update_losses(self, b: Batch, update_policy: bool) -> tuple[Any, ...]:
        """The forward pass and losses of the simultaneous order, in the order of :meth:`train`:
        ``(alpha, loss_critic, loss_actor, loss_alpha, stats)``, the actor's and the entropy
        coefficient's losses None when not ``update_policy``, ``stats`` the ``debug_*`` means.
        The function that ``ALG.COMPILE`` compiles."""
        alpha = self._entropy_coef()
        # a ~ pi(.|o), reparameterised: what the actor and entropy losses differentiate through
        pi, logp_pi = self.actor(b.obs) if update_policy else (None, None)
        backup = self.target_value(b, alpha)
        # Q(o, a) of every critic and Q(o, pi) with the critic weights detached, so that the
        # actor loss moves the actor only.
        q, q_pi_all = self.critics.with_policy_values(b.obs, b.act, pi)
        loss_critic = self.critic_loss(q, backup)
        loss_alpha = self.entropy_loss(logp_pi) if logp_pi is not None else None
        loss_actor = self.actor_loss(alpha, logp_pi, q_pi_all) if q_pi_all is not None else None
        stats: dict[str, torch.Tensor] = {}
        if logp_pi is not None:
            stats["debug_log_pi"] = logp_pi.detach().mean()
        stats["debug_q"] = q.detach().mean()
        stats["debug_backup"] = backup.mean()
        return alpha, loss_critic, loss_actor, loss_alpha, stats

    def _update_with(self, fns: dict[str, Callable[..., Any]], batch: tuple, update_policy: bool) -> dict[str, Any]:
        """One update in the simultaneous order whose forward pass and losses come from
        ``fns["_update_losses"]`` (eager or compiled); the backward pass, the non-finite guard,
        the optimizer steps (fused or foreach kernels, :func:`make_optimizer`) and Polyak
        averaging run eager. Under ``"cudagraph"`` the kept tensors are cloned: a CUDA graph's
        outputs are overwritten by its next replay."""
        b = self._prepare_batch(Batch(*batch))
        g = self._begin_update(update_policy)
        alpha, loss_critic, loss_actor, loss_alpha, stats = fns["_update_losses"](b, update_policy)
        if not self._step(loss_critic, loss_actor, loss_alpha, update_policy, g):
            return self.guard.skipped_metrics()
        self._update_targets()
        own = self._owned
        if loss_actor is not None:
            self.loss_pi = g.pick(own(loss_actor), self.loss_pi)
        if loss_alpha is not None:
            self.loss_alpha = g.pick(own(loss_alpha), self.loss_alpha)
        metrics: dict[str, Any] = {"loss_actor": self.loss_pi, "loss_critic": own(loss_critic), "entropy_coef": own(alpha)}
        metrics.update((k, own(v)) for k, v in stats.items())
        if self.log_alpha is not None:
            metrics["loss_entropy_coef"] = self.loss_alpha
        return g.finish(metrics)

    def _owned(self, t: torch.Tensor) -> torch.Tensor:
        """``t`` detached, cloned under ``"cudagraph"`` (out of the graph's memory)."""
        t = t.detach()
        return t.clone() if self._compile_state.mode == "cudagraph" else t

    def _compiled_train(self, batch: tuple) -> dict[str, Any]:
        """One update with ``ALG.COMPILE`` on: the functions of :attr:`COMPILED` compiled, the rest
        eager (:mod:`tmrl.algorithms.compiled_sac` says why); the first update of each kind (with
        and without a policy update) checked against eager."""
        update_policy = self.policy_update_due()
        st = self._compile_state
        if st.fns is None:
            st.fns = compiled_functions(self, st.mode)
        if update_policy not in st.checked:
            return first_compiled_update(self, batch, update_policy)
        return self._update_with(st.fns, batch, update_policy)

    def _compile_unsupported(self) -> str | None:
        """Why this agent's update cannot be compiled (None: it can): ``train`` overridden by a
        class that does not also define :meth:`_update_with`, or SAC's update in the sequential
        order, which backpropagates twice through one forward pass."""
        def owner(name: str) -> type:
            return next(c for c in type(self).__mro__ if name in vars(c))

        if owner("train") is not owner("_update_with"):
            return f"{type(self).__name__} overrides train"
        if owner("_update_with") is SACAgent and self.update_order != "simultaneous":
            return "update_order='sequential' backpropagates twice through one forward pass"
        return None

    def _checked_tensors(self) -> list[torch.Tensor]:
        """What the first compiled update must agree on: parameters, target parameters, the
        model's floating-point buffers (running statistics), log(alpha)."""
        extra = [self.log_alpha] if self.log_alpha is not None else []
        buffers = [b for b in self.model.buffers() if b.is_floating_point()]
        return self._params + self._target_params + buffers + extra

    # --- checkpointing ------------------------------------------------------------------------

    def state_dict(self) -> dict[str, Any]:
        """Model, target model, optimizers and ``log_alpha``: everything needed to resume.

        The returned tensors are the live ones (no copy): serialise before the next update.
        """
        return {
            "model": self.model.state_dict(),
            "model_target": self.model_target.state_dict(),
            "optimizer_actor": self.pi_optimizer.state_dict(),
            "optimizer_critic": self.q_optimizer.state_dict(),
            "log_alpha": None if self.log_alpha is None else self.log_alpha.detach(),
            "optimizer_entropy": None if self.alpha_optimizer is None else self.alpha_optimizer.state_dict(),
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Restore :meth:`state_dict`'s output in place (the actor from :meth:`get_actor` stays
        shared).

        Raises:
            UserError: the state comes from a differently configured agent.
        """
        try:
            self.model.load_state_dict(state["model"])
            self.model_target.load_state_dict(state["model_target"])
            self.pi_optimizer.load_state_dict(state["optimizer_actor"])
            self.q_optimizer.load_state_dict(state["optimizer_critic"])
            if (state.get("log_alpha") is None) != (self.log_alpha is None):
                raise ValueError("learn_entropy_coef differs")
            if self.log_alpha is not None:
                with torch.no_grad():
                    self.log_alpha.copy_(torch.as_tensor(state["log_alpha"]).reshape(()))
                self.alpha_optimizer.load_state_dict(state["optimizer_entropy"])  # type: ignore[union-attr]
            self._load_extra_state(state)
        except (KeyError, ValueError, RuntimeError) as e:
            detail = " ".join(str(e).split())[:200]
            raise UserError(
                f"the saved training state does not fit this {type(self).__name__} ({detail}): "
                "resume with the same algorithm and model settings, or start a new run"
            ) from None

    def _load_extra_state(self, state: dict[str, Any]) -> None:
        """Hook for subclasses with more state."""


SpinupSacAgent = SACAgent
