"""DroQ (Hiraoka, Imagawa, Hashimoto, Onishi, Tsuruoka, ICLR 2022, "Dropout Q-Functions for
Doubly Efficient Reinforcement Learning", arXiv:2110.02034).

DroQ is REDQ with a small ensemble made of *dropout Q-functions*: every hidden layer of a critic
is ``Linear -> Dropout -> LayerNorm -> ReLU`` (the paper's Fig. 1), and there are only two
critics, so the "random subset" of the target is both of them. Read against Algorithm 2 of the
paper, one update of :meth:`tmrl.algorithms.sac.SACAgent.train` is:

- target (line 6): ``y = r + gamma (1 - terminated) (min_i Qbar^Dr_i(o', a') - alpha log pi(a'|o'))``
  with ``a' ~ pi(.|o')``, from the *target* dropout critics (dropout active there too; SAC's
  :meth:`~tmrl.algorithms.sac.SACAgent.target_q`, the minimum over all target critics);
- critics: each ``Q^Dr_i`` regresses on ``y`` (mean squared error, SAC's);
- policy (line 10): once every ``q_updates_per_policy_update`` critic updates (the paper's ``G``,
  :meth:`DroQAgent.policy_update_due`), maximise ``mean_i Q^Dr_i(o, a~) - alpha log pi(a~|o)``
  (the mean over the critics, REDQ's policy objective, :meth:`DroQAgent.policy_q`), and the
  entropy coefficient toward its target entropy;
- Polyak averaging of the targets after every update.

Defaults and the paper. Class defaults follow the paper where the setting is
DroQ's own: dropout rate 0.01 (``ALG.DROQ_DROPOUT_RATE``) and ``G = 20`` critic updates per
policy update (``ALG.DROQ_Q_UPDATES_PER_POLICY_UPDATE``; the config default is 20 as well), two
critics (the model's ``n``), hidden layers of 256 units. The update-to-data ratio itself (the
paper's 20 updates per environment step) is the trainer's pacing, not the agent's: set
``MAX_TRAINING_STEPS_PER_ENVIRONMENT_STEP`` to 20 to get it. The two go together: the paper
updates the policy once per environment step, so with another ratio set ``G`` to that ratio (with
4 updates per step and ``G = 20``, the policy learns five times slower: in
``python -m bench track_learning`` DroQ had not lapped ``classic`` after 6,500 steps, against 3,000
with ``G = 4``, seed 0). The settings DroQ shares with SAC
(learning rates, gamma, polyak, alpha) keep SAC's class defaults (the settings table gives all
agents one class default per key); the paper uses learning rates of 3e-4, gamma 0.99 and
polyak 0.995 (tau = 0.005).

The update order is SAC's "simultaneous" (the actor loss reads the critics before their step,
as in the REDQ and DroQ authors' code), and the fused update never applies: DroQ overrides
:meth:`policy_update_due` and :meth:`policy_q`, and its critics are not a plain
:class:`~tmrl.models.EnsembleQFunction`.

Random numbers: the dropout masks come from the global torch generator, drawn in this order in
every update: the policy's actions at ``o`` (when the policy is updated), the target actions at
``o'``, the masks of the target critics at ``(o', a')`` (critic by critic, layer by layer), of
the online critics at ``(o, a)``, then at ``(o, a~)`` (when the policy is updated).

Lidar observations (the ``SIMLIDAR*`` and ``TM20LIDAR*`` interfaces): :class:`tmrl.driving.models.LidarDroQActorCritic`,
this model with the lidar input scaling and :class:`~tmrl.driving.models.LidarActor` as the actor
(``tmrl.driving.models.LIDAR_MODELS``). There is no image model.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

import torch
from torch import nn

from tmrl.algorithms.sac import SACAgent, _build_model
from tmrl.errors import UserError
from tmrl.models import FlatInputCritic, SquashedGaussianMLPActor, space_dim

__all__ = ["DroQAgent", "DroQMLPActorCritic", "DropoutQFunction"]


class DropoutQFunction(FlatInputCritic, nn.Module):
    """A dropout Q-function ``Q^Dr(obs, act) -> (B,)``: every hidden layer is
    ``Linear -> Dropout -> LayerNorm -> activation``, then a linear output layer.

    Dropout is active whenever the module is in training mode (the default, and how the trainer
    uses it: targets included).

    Args:
        observation_space: the observation space.
        action_space: the action space (a Box).
        hidden_sizes: widths of the hidden layers.
        activation: activation class.
        dropout_rate: probability of zeroing each hidden unit.
    """

    def __init__(
        self,
        observation_space: Any,
        action_space: Any,
        hidden_sizes: Sequence[int] = (256, 256),
        activation: Callable[[], nn.Module] = nn.ReLU,
        dropout_rate: float = 0.01,
    ) -> None:
        super().__init__()
        width = space_dim(observation_space) + int(torch.Size(action_space.shape).numel())
        layers: list[nn.Module] = []
        for size in hidden_sizes:
            layers += [nn.Linear(width, size), nn.Dropout(dropout_rate), nn.LayerNorm(size), activation()]
            width = size
        layers.append(nn.Linear(width, 1))
        self.net = nn.Sequential(*layers)

    def forward(self, obs: Any, act: torch.Tensor) -> torch.Tensor:
        """Q values of shape ``(B,)``.

        Args:
            obs: a batched observation.
            act: actions ``(B, act_dim)``.
        """
        return self.net(self.critic_input(obs, act)).squeeze(-1)


class DroQMLPActorCritic(nn.Module):
    """DroQ's actor-critic: SAC's :class:`~tmrl.models.SquashedGaussianMLPActor` (``.actor``,
    the same policy the workers run) and ``n`` :class:`DropoutQFunction` critics (``.qs``).

    Args:
        observation_space: the observation space.
        action_space: the action space (a bounded Box).
        hidden_sizes: widths of the hidden layers of the actor and of each critic.
        activation: activation class.
        n: number of critics (the paper: 2).
        dropout_rate: the critics' dropout rate (the paper: 0.01).
    """

    def __init__(
        self,
        observation_space: Any,
        action_space: Any,
        hidden_sizes: Sequence[int] = (256, 256),
        activation: Callable[[], nn.Module] = nn.ReLU,
        n: int = 2,
        dropout_rate: float = 0.01,
    ) -> None:
        super().__init__()
        self.actor = SquashedGaussianMLPActor(observation_space, action_space, hidden_sizes, activation)
        self.qs = nn.ModuleList(
            DropoutQFunction(observation_space, action_space, hidden_sizes, activation, dropout_rate)
            for _ in range(int(n))
        )

    def act(self, obs: Any, test: bool = False) -> Any:
        """The actor's action for a batched observation, as a NumPy array.

        Args:
            obs: a batched observation.
            test: take the mean action instead of a sample.
        """
        return self.actor.act(obs, test)


class DroQAgent(SACAgent):
    """DroQ. Takes every argument of :class:`~tmrl.algorithms.sac.SACAgent` but
    ``update_order`` and ``fused`` (same meaning; ``model_cls`` defaults to
    :class:`DroQMLPActorCritic`) plus:

    Args:
        dropout_rate: dropout rate of the critics, passed to ``model_cls`` as ``dropout_rate=``
            when it accepts it (the paper: 0.01).
        q_updates_per_policy_update: critic updates per actor (and entropy) update (the
            paper's ``G``: 20).

    Raises:
        UserError: ``dropout_rate`` not in ``[0, 1)``, ``q_updates_per_policy_update < 1``, a
            model with fewer than two critics or whose critics lack dropout or layer
            normalisation; plus :class:`SACAgent`'s errors.
    """

    def __init__(
        self,
        observation_space: Any = None,
        action_space: Any = None,
        device: Any = None,
        model_cls: Callable[..., torch.nn.Module] = DroQMLPActorCritic,
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
        dropout_rate: float = 0.01,
        q_updates_per_policy_update: int = 20,
    ) -> None:
        self.dropout_rate = float(dropout_rate)
        self.q_updates_per_policy_update = int(q_updates_per_policy_update)
        if not 0.0 <= self.dropout_rate < 1.0:
            raise UserError(f"dropout_rate={dropout_rate} must lie in [0, 1) (ALG.DROQ_DROPOUT_RATE), typically 0.01")
        if self.q_updates_per_policy_update < 1:
            raise UserError(
                f"q_updates_per_policy_update={q_updates_per_policy_update} must be >= 1 "
                "(ALG.DROQ_Q_UPDATES_PER_POLICY_UPDATE)"
            )
        self.i_update = 0
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
        self._check_critics(model_cls)

    def _make_model(self) -> torch.nn.Module:
        return _build_model(self.model_cls, self.observation_space, self.action_space, dropout_rate=self.dropout_rate)

    def _check_critics(self, model_cls: Any) -> None:
        name = getattr(model_cls, "__name__", type(self.model).__name__)
        if len(self.critics) < 2:
            raise UserError(f"DroQ needs at least two critics, {name} built {len(self.critics)}")
        critics = self.critics.modules or [self.critics.ensemble]
        kinds = {type(m) for c in critics for m in c.modules()}  # type: ignore[union-attr]
        if not {nn.Dropout, nn.LayerNorm} <= kinds:
            raise UserError(
                f"DroQ's critics need dropout and layer normalisation in their hidden layers, and {name}'s "
                "have not: use tmrl.algorithms.droq.DroQMLPActorCritic (or its DropoutQFunction) as the model"
            )

    # --- the steps that differ from SAC ---------------------------------------------------------

    def policy_update_due(self) -> bool:
        """Counts the update; true once every ``q_updates_per_policy_update`` of them (the
        policy update after the paper's loop of ``G`` critic updates)."""
        self.i_update += 1
        return self.i_update % self.q_updates_per_policy_update == 0

    def policy_q(self, q_pi_all: torch.Tensor) -> torch.Tensor:
        """The mean over the dropout critics (Algorithm 2, line 10).

        Args:
            q_pi_all: ``Q^Dr_i(o, a~)`` of every critic, shape ``(n, B)``.
        """
        return q_pi_all.mean(0)

    # target_q is SAC's: the minimum over all (both) target dropout critics (Algorithm 2, line 6).

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
            setattr(self, attr, torch.as_tensor(state.get(key, 0.0), device=self.device).reshape(()))
