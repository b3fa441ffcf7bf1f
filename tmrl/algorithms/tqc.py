"""TQC (Kuznetsov, Shvechikov, Grishin, Vetrov, ICML 2020, "Controlling Overestimation Bias
with Truncated Mixture of Continuous Distributional Quantile Critics", arXiv:2005.04269).

SAC with distributional critics: each of ``N`` critics ``Z_n(o, a)`` outputs ``M`` quantiles
``theta_n^1..M`` of the return at the fractions ``tau_m = (2m - 1) / (2M)``. One update
(:meth:`tmrl.algorithms.sac.SACAgent.train` with the steps below), read against section 4 of the
paper:

- target: with ``a' ~ pi(.|o')``, pool the ``N M`` quantiles of all *target*
  critics at ``(o', a')``, sort them, keep the ``kN`` smallest (``k = M - d``, ``d`` =
  ``drop_per_critic`` atoms dropped per critic: the truncation that controls overestimation),
  and make the target atoms ``y_i = r + gamma (1 - terminated) (z_(i) - alpha log pi(a'|o'))``,
  ``i = 1..kN`` (:meth:`TQCAgent.target_value`);
- critics: each critic's quantiles regress on all the target atoms by the quantile
  Huber loss ``rho_tau(u) = |tau - 1{u < 0}| L_kappa(u)`` with ``u = y_i - theta_n^m`` and
  ``kappa = 1``, averaged over batch, critics, quantiles and atoms (the authors' code; the
  paper's ``1/(kNM)`` sum up to the 1/N of averaging over critics, which SAC's loss has too)
  (:func:`quantile_huber_loss`);
- policy: minimise ``alpha log pi(a~|o) - mean_{n,m} theta_n^m(o, a~)``, the mean over
  all quantiles of all critics (:meth:`TQCAgent.policy_q`), evaluated on the critics before
  their step as in the authors' code; the entropy coefficient as in SAC v2;
- Polyak averaging of the target critics.

Defaults: the paper's ``N = 5`` critics (``ALG.TQC_N``), ``M = 25`` quantiles
(``ALG.TQC_QUANTILES``), ``d = 2`` dropped atoms per critic (``ALG.TQC_DROP_PER_CRITIC``; the
authors tune it per environment: 2 for most MuJoCo tasks, 5 for Hopper, 0 for HalfCheetah) and
critics of three hidden layers of 512 units (:class:`TQCActorCritic`; the actor keeps SAC's
256x256, the policy the workers run). The config defaults are the same. The settings TQC shares
with SAC (learning rates, gamma, polyak, alpha) keep SAC's class defaults (the settings table
gives all agents one class default per key); the paper uses learning rates of 3e-4, gamma 0.99,
polyak 0.995 (tau = 0.005) and a learned alpha with target entropy ``-act_dim``.

SAC's squared-error critic loss does not fit quantile critics: TQC overrides
:meth:`TQCAgent.critic_loss` and keeps SAC's sequence of steps, actor loss, entropy loss,
optimizers, non-finite guard and Polyak averaging; it never takes the fused SAC update. Its cost is the paper's critics: about 160 ms per update at batch
256 on one CPU thread of this project's machine (SAC's autograd update: 11 ms), of which the
quantile loss over ``N x B x M x kN`` pairs is about 20-35 ms; on a CPU, smaller critics
(``critic_hidden_sizes``) or fewer of them are the lever.

Lidar observations (the ``SIMLIDAR*`` and ``TM20LIDAR*`` interfaces): :class:`tmrl.driving.models.LidarTQCActorCritic`,
this model with the lidar input scaling and :class:`~tmrl.driving.models.LidarActor` as the actor
(``tmrl.driving.models.LIDAR_MODELS``). There is no image model.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

import torch
import torch.nn.functional as F
from torch import nn

from tmrl.algorithms.sac import SACAgent, _build_model
from tmrl.batch import Batch
from tmrl.errors import UserError
from tmrl.models import FlatInputCritic, SquashedGaussianMLPActor, mlp, space_dim

__all__ = ["QuantileQFunction", "TQCActorCritic", "TQCAgent", "quantile_huber_loss"]

HUBER_KAPPA = 1.0
"""The quantile Huber loss's threshold (the paper's ``kappa``)."""


def quantile_huber_loss(quantiles: torch.Tensor, atoms: torch.Tensor, kappa: float = HUBER_KAPPA) -> torch.Tensor:
    """The quantile Huber loss of the critics' quantiles against the target atoms.

    Args:
        quantiles: ``theta_n^m(o, a)``, shape ``(N, B, M)``, quantile ``m`` at fraction
            ``(2m - 1) / (2M)``.
        atoms: target atoms ``y_i``, shape ``(B, K)`` (no gradient).
        kappa: the Huber threshold.

    Returns:
        ``mean over (n, b, m, i) of |tau_m - 1{u < 0}| L_kappa(u)``, ``u = y_i - theta_n^m``.
    """
    m = quantiles.shape[-1]
    tau = (torch.arange(m, device=quantiles.device, dtype=quantiles.dtype) + 0.5) / m
    theta = quantiles[..., None]  # (N, B, M, 1)
    y = atoms[None, :, None, :]  # (1, B, 1, K)
    shape = torch.broadcast_shapes(theta.shape, y.shape)  # (N, B, M, K): every pair (theta_n^m, y_i)
    # L_kappa(u), u = y - theta (symmetric in u); PyTorch's fused kernel is 4x faster than spelling it out
    huber = F.huber_loss(theta.expand(shape), y.expand(shape), reduction="none", delta=kappa)
    # |tau - 1{u < 0}|: 1 - tau where the atom lies below the quantile, tau elsewhere
    weight = torch.where(y < theta.detach(), 1.0 - tau[:, None], tau[:, None])
    return (weight * huber).mean()


class QuantileQFunction(FlatInputCritic, nn.Module):
    """A distributional critic: an MLP from ``(obs, act)`` to ``n_quantiles`` quantiles of the
    return, ``(B, n_quantiles)``.

    Args:
        observation_space: the observation space.
        action_space: the action space (a Box).
        hidden_sizes: widths of the hidden layers.
        activation: activation class.
        n_quantiles: number of quantiles ``M``.
    """

    def __init__(
        self,
        observation_space: Any,
        action_space: Any,
        hidden_sizes: Sequence[int] = (512, 512, 512),
        activation: Callable[[], nn.Module] = nn.ReLU,
        n_quantiles: int = 25,
    ) -> None:
        super().__init__()
        dim_in = space_dim(observation_space) + int(torch.Size(action_space.shape).numel())
        self.n_quantiles = int(n_quantiles)
        self.net = mlp([dim_in, *hidden_sizes, self.n_quantiles], activation)

    squeeze_output = False
    """:meth:`forward` keeps the output's last axis (the quantiles) (for :class:`~tmrl.models.StackedCritics`)."""

    def forward(self, obs: Any, act: torch.Tensor) -> torch.Tensor:
        """Quantiles of shape ``(B, n_quantiles)``, ascending fractions.

        Args:
            obs: a batched observation.
            act: actions ``(B, act_dim)``.
        """
        return self.net(self.critic_input(obs, act))


class TQCActorCritic(nn.Module):
    """TQC's actor-critic: SAC's :class:`~tmrl.models.SquashedGaussianMLPActor` (``.actor``,
    the workers' policy) and ``n`` :class:`QuantileQFunction` critics (``.qs``).

    Args:
        observation_space: the observation space.
        action_space: the action space (a bounded Box).
        hidden_sizes: widths of the actor's hidden layers (the paper: 256, 256).
        activation: activation class.
        n: number of critics (the paper: 5).
        n_quantiles: quantiles per critic (the paper: 25).
        critic_hidden_sizes: widths of each critic's hidden layers (the paper: 512, 512, 512).
    """

    def __init__(
        self,
        observation_space: Any,
        action_space: Any,
        hidden_sizes: Sequence[int] = (256, 256),
        activation: Callable[[], nn.Module] = nn.ReLU,
        n: int = 5,
        n_quantiles: int = 25,
        critic_hidden_sizes: Sequence[int] = (512, 512, 512),
    ) -> None:
        super().__init__()
        self.n_quantiles = int(n_quantiles)
        self.actor = SquashedGaussianMLPActor(observation_space, action_space, hidden_sizes, activation)
        self.qs = nn.ModuleList(
            QuantileQFunction(observation_space, action_space, critic_hidden_sizes, activation, n_quantiles)
            for _ in range(int(n))
        )

    def act(self, obs: Any, test: bool = False) -> Any:
        """The actor's action for a batched observation, as a NumPy array.

        Args:
            obs: a batched observation.
            test: take the mean action instead of a sample.
        """
        return self.actor.act(obs, test)


class TQCAgent(SACAgent):
    """TQC. Takes every argument of :class:`~tmrl.algorithms.sac.SACAgent` but ``update_order``
    and ``fused`` (same meaning; ``model_cls`` defaults to :class:`TQCActorCritic`) plus:

    Args:
        n: number of critics ``N``; passed to ``model_cls`` as ``n=`` when it accepts it.
        n_quantiles: quantiles per critic ``M``; passed as ``n_quantiles=`` when accepted.
        drop_per_critic: target atoms dropped per critic ``d``: the target keeps the
            ``N (M - d)`` smallest of the ``N M`` pooled target quantiles.

    Raises:
        UserError: ``n < 1``, ``n_quantiles < 1``, ``drop_per_critic`` not in
            ``[0, n_quantiles)``, or a model whose critics are not ``n`` critics of
            ``n_quantiles`` outputs; plus :class:`SACAgent`'s errors.
    """

    def __init__(
        self,
        observation_space: Any = None,
        action_space: Any = None,
        device: Any = None,
        model_cls: Callable[..., torch.nn.Module] = TQCActorCritic,
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
        n: int = 5,
        n_quantiles: int = 25,
        drop_per_critic: int = 2,
    ) -> None:
        self.n = int(n)
        self.n_quantiles = int(n_quantiles)
        self.drop_per_critic = int(drop_per_critic)
        if self.n < 1:
            raise UserError(f"TQC needs at least one critic, got n={n} (ALG.TQC_N)")
        if self.n_quantiles < 1:
            raise UserError(f"TQC needs at least one quantile per critic, got n_quantiles={n_quantiles} "
                            "(ALG.TQC_QUANTILES)")
        if not 0 <= self.drop_per_critic < self.n_quantiles:
            raise UserError(
                f"drop_per_critic={drop_per_critic} must lie in [0, {self.n_quantiles}) (ALG.TQC_DROP_PER_CRITIC, "
                "below ALG.TQC_QUANTILES): the target needs at least one atom per critic"
            )
        # The target keeps the kN smallest of the NM pooled atoms, k = M - d.
        self.kept_atoms = self.n * (self.n_quantiles - self.drop_per_critic)
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
            update_order="simultaneous",
            fused=False,
        )
        width = getattr(self.model, "n_quantiles", self.n_quantiles)
        if len(self.critics) != self.n or width != self.n_quantiles:
            raise UserError(
                f"TQC was asked for n={self.n} critics of {self.n_quantiles} quantiles but "
                f"{getattr(model_cls, '__name__', type(self.model).__name__)} built {len(self.critics)} of {width}: "
                "give the model `n` and `n_quantiles` arguments or set ALG.TQC_N and ALG.TQC_QUANTILES to match"
            )

    def _make_model(self) -> torch.nn.Module:
        return _build_model(
            self.model_cls, self.observation_space, self.action_space, n=self.n, n_quantiles=self.n_quantiles
        )

    # --- the steps that differ from SAC ---------------------------------------------------------

    def target_q(self, next_obs: Any, next_act: torch.Tensor) -> torch.Tensor:
        """The truncated mixture: the ``kN`` smallest of the ``NM`` target quantiles at
        ``(o', a')``, ascending, shape ``(B, kN)``.

        Args:
            next_obs: the batch's next observations ``o'``.
            next_act: actions ``a'`` drawn from the current policy at ``o'``.
        """
        z = self.critics_target(next_obs, next_act)  # (N, B, M)
        pooled = z.permute(1, 0, 2).reshape(z.shape[1], -1)  # (B, NM): all critics together
        return pooled.sort(dim=1).values[:, : self.kept_atoms]

    @torch.no_grad()
    def target_value(self, batch: Batch, alpha: torch.Tensor) -> torch.Tensor:
        """The target atoms ``y_i = r + gamma (1 - terminated) (z_(i)(o', a') - alpha log pi(a'|o'))``,
        ``a' ~ pi(.|o')``, shape ``(B, kN)``. Truncated episodes bootstrap (as in SAC).

        Args:
            batch: the training batch.
            alpha: the entropy coefficient.
        """
        a2, logp_a2 = self.actor(batch.next_obs)
        r, d = batch.rew.reshape(-1, 1), batch.terminated.reshape(-1, 1)
        return r + self.gamma * (1.0 - d) * (self.target_q(batch.next_obs, a2) - alpha * logp_a2.unsqueeze(1))

    def critic_loss(self, q: torch.Tensor, backup: torch.Tensor) -> torch.Tensor:
        """The quantile Huber loss of every critic's quantiles against the truncated target
        atoms (:func:`quantile_huber_loss`).

        Args:
            q: ``theta_n^m(o, a)`` of every critic, shape ``(N, B, M)``.
            backup: the target atoms, shape ``(B, kN)`` (:meth:`target_value`).
        """
        return quantile_huber_loss(q, backup)

    def policy_q(self, q_pi_all: torch.Tensor) -> torch.Tensor:
        """The mean over all quantiles of all critics, shape ``(B,)``.

        Args:
            q_pi_all: ``theta_n^m(o, a~)`` of every critic, shape ``(N, B, M)``.
        """
        return q_pi_all.mean(dim=(0, 2))
