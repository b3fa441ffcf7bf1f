"""BRO (Nauman, Ostaszewski, Jankowski, Milos, Cygan, NeurIPS 2024, "Bigger, Regularized,
Optimistic: scaling for compute and sample-efficient continuous control", arXiv:2405.16158),
sized for a CPU trainer.

What this agent takes from BRO, and what it leaves out:

- **The critic network, BroNet**: a stem ``Linear -> LayerNorm -> ReLU`` and ``blocks`` residual
  blocks, each ``x + LayerNorm(Linear(ReLU(LayerNorm(Linear(x)))))``, then a linear head
  (:class:`BroNetQuantileCritic`). The normalisation in every block is what lets BRO's critic
  learn fast at a few updates per sample without the divergence a plain MLP shows there.
- **Quantile critics**: each of ``n`` critics (BRO: 2) outputs ``M`` quantiles of the return at
  the fractions ``(2m - 1) / (2M)``, trained by TQC's quantile Huber loss
  (:func:`tmrl.algorithms.tqc.quantile_huber_loss`).
- **Pessimism as a setting** (BRO's ``beta``): the target quantiles are the critics' per-quantile
  mean minus ``pessimism`` times their per-quantile standard deviation (:meth:`BROAgent.target_q`),
  ``pessimism = 0`` is BRO's non-pessimistic target; with two critics ``pessimism = 1`` is exactly
  the per-quantile minimum (clipped double Q), the default here (docs/benchmarks.md has the screen
  that chose it). The actor maximises the mean over quantiles of the same pessimistic estimate
  (:meth:`BROAgent.policy_q`).
- **The fast setting**: BRO-fast trains at 2 updates per sample; the update ratio is the trainer's
  (``MAX_TRAINING_STEPS_PER_ENVIRONMENT_STEP``), not the agent's.
- Left out: BRO's dual-actor optimistic exploration (the workers run one policy, the actor the
  other agents train), full-parameter resets (the runs this project measures are far shorter than
  BRO's reset period), its widths (512 units, for a GPU: 256 here by default, ``ALG.BRO_CRITIC_WIDTH``),
  and its 100 quantiles (25 here: the loss pairs every quantile with every target atom, so its cost
  grows with the square). Weight decay is available through ``ALG.OPTIMIZER_CRITIC = "adamw"``
  and ``ALG.L2_CRITIC``; the settings table gives every agent one default there (none).

Everything else is SAC's (:class:`tmrl.algorithms.sac.SACAgent` via
:class:`tmrl.algorithms.tqc.TQCAgent`): the actor and its loss, the learned entropy coefficient
and its ceiling, the simultaneous order, the non-finite guard, ``ALG.COMPILE``, the device paths
and the checkpoints. The actor is SAC's squashed Gaussian MLP, the policy the workers run.

Lidar observations: :class:`tmrl.driving.models.LidarBROActorCritic` (the lidar scaling on the
critics' input and :class:`~tmrl.driving.models.LidarActor`).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

import torch
from torch import nn

from tmrl.algorithms.sac import _build_model
from tmrl.algorithms.tqc import TQCAgent
from tmrl.errors import UserError
from tmrl.models import FlatInputCritic, SquashedGaussianMLPActor, space_dim

__all__ = ["BROActorCritic", "BROAgent", "BroNet", "BroNetBlock", "BroNetQuantileCritic"]


class BroNetBlock(nn.Module):
    """One residual block of BroNet: ``x + LN(W2 ReLU(LN(W1 x)))``.

    Args:
        width: the block's input, hidden and output width.
    """

    def __init__(self, width: int) -> None:
        super().__init__()
        self.fc1 = nn.Linear(width, width)
        self.ln1 = nn.LayerNorm(width)
        self.fc2 = nn.Linear(width, width)
        self.ln2 = nn.LayerNorm(width)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """The block's output, same shape as ``x``."""
        return x + self.ln2(self.fc2(torch.relu(self.ln1(self.fc1(x)))))


class BroNet(nn.Module):
    """BroNet: ``ReLU(LN(W x))``, then ``blocks`` :class:`BroNetBlock`, then a linear head.

    Args:
        dim_in: input width.
        width: hidden width.
        blocks: residual blocks (0: the stem and the head only).
        dim_out: output width.
    """

    def __init__(self, dim_in: int, width: int, blocks: int, dim_out: int) -> None:
        super().__init__()
        self.stem = nn.Linear(dim_in, width)
        self.stem_ln = nn.LayerNorm(width)
        self.blocks = nn.Sequential(*(BroNetBlock(width) for _ in range(int(blocks))))
        self.head = nn.Linear(width, dim_out)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """``(B, dim_out)`` from ``(B, dim_in)``."""
        return self.head(self.blocks(torch.relu(self.stem_ln(self.stem(x)))))


class BroNetQuantileCritic(FlatInputCritic, nn.Module):
    """A BroNet critic from ``(obs, act)`` to ``n_quantiles`` quantiles of the return,
    ``(B, n_quantiles)``, ascending fractions.

    Args:
        observation_space: the observation space.
        action_space: the action space (a Box).
        width: BroNet's hidden width.
        blocks: BroNet's residual blocks.
        n_quantiles: quantiles ``M``.
    """

    squeeze_output = False
    """:meth:`forward` keeps the quantile axis."""

    def __init__(self, observation_space: Any, action_space: Any, width: int = 256, blocks: int = 1,
                 n_quantiles: int = 25) -> None:
        super().__init__()
        dim_in = space_dim(observation_space) + int(torch.Size(action_space.shape).numel())
        self.n_quantiles = int(n_quantiles)
        self.net = BroNet(dim_in, int(width), int(blocks), self.n_quantiles)

    def forward(self, obs: Any, act: torch.Tensor) -> torch.Tensor:
        """Quantiles ``(B, n_quantiles)``.

        Args:
            obs: a batched observation.
            act: actions ``(B, act_dim)``.
        """
        return self.net(self.critic_input(obs, act))


class BROActorCritic(nn.Module):
    """BRO's actor-critic: SAC's :class:`~tmrl.models.SquashedGaussianMLPActor` (``.actor``, the
    workers' policy) and ``n`` :class:`BroNetQuantileCritic` (``.qs``).

    Args:
        observation_space: the observation space.
        action_space: the action space (a bounded Box).
        hidden_sizes: widths of the actor's hidden layers.
        activation: the actor's activation class.
        n: critics (BRO: 2).
        n_quantiles: quantiles per critic.
        critic_width: BroNet's hidden width.
        critic_blocks: BroNet's residual blocks.
    """

    def __init__(self, observation_space: Any, action_space: Any, hidden_sizes: Sequence[int] = (256, 256),
                 activation: Callable[[], nn.Module] = nn.ReLU, n: int = 2, n_quantiles: int = 25,
                 critic_width: int = 256, critic_blocks: int = 1) -> None:
        super().__init__()
        self.n_quantiles = int(n_quantiles)
        self.actor = SquashedGaussianMLPActor(observation_space, action_space, hidden_sizes, activation)
        self.qs = nn.ModuleList(
            BroNetQuantileCritic(observation_space, action_space, critic_width, critic_blocks, n_quantiles)
            for _ in range(int(n))
        )

    def act(self, obs: Any, test: bool = False) -> Any:
        """The actor's action for a batched observation, as a NumPy array."""
        return self.actor.act(obs, test)


class BROAgent(TQCAgent):
    """BRO, sized for a CPU trainer (the module's notes). Takes every argument of
    :class:`~tmrl.algorithms.sac.SACAgent` but ``update_order`` and ``fused`` (same meaning;
    ``model_cls`` defaults to :class:`BROActorCritic`) plus:

    Args:
        n: critics; passed to ``model_cls`` as ``n=`` when it accepts it.
        n_quantiles: quantiles per critic; passed as ``n_quantiles=``.
        pessimism: ``beta`` of the target and the actor's value: the critics' per-quantile mean
            minus ``beta`` times their per-quantile standard deviation (0: BRO's optimistic
            target; 1 with two critics: their per-quantile minimum).
        critic_width: BroNet's hidden width; passed as ``critic_width=`` when accepted.
        critic_blocks: BroNet's residual blocks; passed as ``critic_blocks=`` when accepted.

    Raises:
        UserError: ``n < 1``, ``n_quantiles < 1``, ``pessimism < 0``, ``critic_width < 1``,
            ``critic_blocks < 0``, or a model whose critics do not match; plus SAC's errors.
    """

    def __init__(
        self,
        observation_space: Any = None,
        action_space: Any = None,
        device: Any = None,
        model_cls: Callable[..., torch.nn.Module] = BROActorCritic,
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
        n: int = 2,
        n_quantiles: int = 25,
        pessimism: float = 1.0,
        critic_width: int = 256,
        critic_blocks: int = 1,
    ) -> None:
        self.pessimism = float(pessimism)
        self.critic_width = int(critic_width)
        self.critic_blocks = int(critic_blocks)
        if not self.pessimism >= 0:
            raise UserError(f"BRO's pessimism must be 0 or more, got {pessimism} (ALG.BRO_PESSIMISM)")
        if self.critic_width < 1:
            raise UserError(f"BRO's critic width must be at least 1, got {critic_width} (ALG.BRO_CRITIC_WIDTH)")
        if self.critic_blocks < 0:
            raise UserError(f"BRO's critic blocks must be 0 or more, got {critic_blocks} (ALG.BRO_CRITIC_BLOCKS)")
        if int(n) < 1:
            raise UserError(f"BRO needs at least one critic, got n={n} (ALG.BRO_N)")
        if int(n_quantiles) < 1:
            raise UserError(f"BRO needs at least one quantile per critic, got n_quantiles={n_quantiles} "
                            "(ALG.BRO_QUANTILES)")
        super().__init__(
            observation_space=observation_space, action_space=action_space, device=device, model_cls=model_cls,
            gamma=gamma, polyak=polyak, alpha=alpha, lr_actor=lr_actor, lr_critic=lr_critic, lr_entropy=lr_entropy,
            learn_entropy_coef=learn_entropy_coef, target_entropy=target_entropy, alpha_max=alpha_max,
            optimizer_actor=optimizer_actor, optimizer_critic=optimizer_critic, betas_actor=betas_actor,
            betas_critic=betas_critic, l2_actor=l2_actor, l2_critic=l2_critic, compile=compile,
            n=n, n_quantiles=n_quantiles, drop_per_critic=0,
        )

    def _make_model(self) -> torch.nn.Module:
        return _build_model(self.model_cls, self.observation_space, self.action_space, n=self.n,
                            n_quantiles=self.n_quantiles, critic_width=self.critic_width,
                            critic_blocks=self.critic_blocks)

    def _pessimistic(self, z: torch.Tensor) -> torch.Tensor:
        """Per quantile, the critics' mean minus ``pessimism`` times their standard deviation
        (population: with two critics ``(mean - |a - b| / 2)``), ``(N, B, M) -> (B, M)``."""
        if z.shape[0] == 1 or self.pessimism == 0.0:
            return z.mean(0)
        if z.shape[0] == 2:  # the same value in closed form: ``std`` is 8 % of an update on a CPU
            a, b = z[0], z[1]
            return 0.5 * (a + b) - (0.5 * self.pessimism) * (a - b).abs()
        return z.mean(0) - self.pessimism * z.std(0, unbiased=False)

    def target_q(self, next_obs: Any, next_act: torch.Tensor) -> torch.Tensor:
        """The target critics' pessimistic quantiles at ``(o', a')``, shape ``(B, M)``.

        Args:
            next_obs: the batch's next observations ``o'``.
            next_act: actions ``a'`` drawn from the current policy at ``o'``.
        """
        return self._pessimistic(self.critics_target(next_obs, next_act))

    def policy_q(self, q_pi_all: torch.Tensor) -> torch.Tensor:
        """The mean over quantiles of the critics' pessimistic quantiles at ``(o, a~)``, ``(B,)``.

        Args:
            q_pi_all: quantiles of every critic, shape ``(N, B, M)``.
        """
        return self._pessimistic(q_pi_all).mean(-1)
