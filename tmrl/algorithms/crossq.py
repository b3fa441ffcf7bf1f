"""CrossQ (Bhatt, Palenicek, Belousov, Argus, Amiranashvili, Brox, Peters, ICLR 2024, "CrossQ:
Batch Normalization in Deep Reinforcement Learning for Greater Sample Efficiency and Simplicity",
arXiv:1902.05605).

CrossQ is SAC with three changes: no target networks, batch normalisation in the critics, and
wider critics. Batch normalisation fails in SAC as usually written because the critic sees
``(o, a)`` (replay actions) and ``(o', a')`` (policy actions) in separate passes, two different
distributions, and its normalisation statistics fit only the first; CrossQ evaluates both in *one*
pass (the paper's central change), so that the statistics of every normalisation layer are those of
the mixture. One update (:meth:`CrossQAgent.train`) read against the paper:

- joint pass (:meth:`CrossQAgent.joint_critic_pass`): ``a' ~ pi(.|o')`` from the current policy
  (no gradient); the critics, in *training* mode, evaluate the concatenated batch
  ``[(o, a); (o', a')]`` of ``2B`` rows in one forward pass, which also updates the normalisation
  layers' running statistics once; the result is split into ``Q_i(o, a)`` and ``Q_i(o', a')``;
- target: ``y = r + gamma (1 - terminated) (min_i Q_i(o', a') - alpha log pi(a'|o'))`` with the
  ``(o', a')`` half *detached* (the paper's ``stop_gradient``; :meth:`CrossQAgent.target_q_from`,
  the minimum over the critics as in SAC). There is no target network, hence no Polyak averaging:
  ``polyak`` (``ALG.POLYAK``) is accepted for the settings table's sake and unused;
- critics: each ``Q_i(o, a)`` regresses on ``y`` (SAC's mean squared error, averaged over the
  critics: the reference code's ``0.5 * sum_i mse_i`` for its two critics), one Adam step;
- policy, once every ``policy_delay`` critic updates (:meth:`CrossQAgent.policy_update_due`,
  the paper's policy delay of 3): ``a~ ~ pi(.|o)``, minimise ``alpha log pi(a~|o) - min_i Q_i(o, a~)``
  with the critics in *evaluation* mode (their running statistics, no update of them) and their
  weights as constants, after the critic step; then SAC v2's entropy-coefficient step on the same
  ``log pi(a~|o)``.

The last point follows the authors' reference code (SBX, and the PyTorch port in
stable-baselines3-contrib, whose ``CrossQ.train`` we read): the actor loss evaluates the critics
in evaluation mode, after their optimizer step (the "sequential" order of
:class:`~tmrl.algorithms.sac.SACAgent`), with the minimum over the critics.

The normalisation is Batch Renormalization (Ioffe 2017, arXiv:1702.03275), as in the authors'
code and its PyTorch port (:class:`BatchRenorm1d`): plain batch normalisation for the first
``renorm_warmup_steps`` critic updates, then the batch statistics are corrected toward the running
ones by ``r`` and ``d`` clipped to ``[1/3, 3]`` and ``[-5, 5]``. Normalisation layers sit on the
critic's input and after every hidden activation (``BRN -> Linear -> ReLU -> BRN -> ... ->
Linear``), as in the reference code.

Defaults and the paper. The paper's and its code's: two critics, policy delay 3
(``ALG.CROSSQ_POLICY_DELAY``), learning rates 1e-3 (SAC's class defaults already), Adam with
``betas = (0.5, 0.999)`` for the actor and the critics (``betas_actor``/``betas_critic`` None means
these here, where SAC's None means PyTorch's; the entropy coefficient's Adam keeps PyTorch's, as in
the code), normalisation momentum 0.01 in PyTorch's convention (0.99 in the JAX code's;
``ALG.CROSSQ_BN_MOMENTUM``), epsilon 1e-3, renormalisation after 100,000 updates
(``ALG.CROSSQ_RENORM_WARMUP_STEPS``), an update-to-data ratio of 1 (the trainer's pacing:
``MAX_TRAINING_STEPS_PER_ENVIRONMENT_STEP`` 1) and a learned entropy coefficient with target
``-act_dim``. Departures:

- critic width 1024 (``ALG.CROSSQ_CRITIC_WIDTH``), not the paper's 2048: one whole update at
  batch 256 (83 observation values) takes about 410 ms with 2048 units on one CPU thread of this
  project's (shared) machine, 125 ms with 1024, 46 ms with 512, against 10-12 ms for SAC; the
  critics see ``2B`` rows per pass. stable-baselines3-contrib's port makes the same choice. On a
  GPU, set 2048 for the paper's network;
- the lidar model (:class:`~tmrl.driving.models.LidarCrossQActorCritic`) has no normalisation
  layer on the critics' input (``input_norm`` of :class:`CrossQQFunction`; the generic
  :class:`CrossQActorCritic` keeps it): the lidar scaling already gives the inputs a common
  scale, and standardising each of the 76 redundant lidar features left the action's 3 too little
  weight for the car to start moving on some seeds (docs/benchmarks.md);
- the actor is SAC's :class:`~tmrl.models.SquashedGaussianMLPActor` without normalisation layers
  (the reference code puts them in the actor too): the workers run that policy class (or
  :class:`~tmrl.driving.models.LidarActor` on lidar observations) and must load the trained
  actor's weights; the paper's analysis concerns the critic;
- through ``config.json``, ``ALG.BETAS_ACTOR``/``ALG.BETAS_CRITIC`` (tmrl's [0.997, 0.997] by
  default) and ``ALG.LR_ACTOR``/``ALG.LR_CRITIC`` apply to CrossQ as to every agent: set them to
  [0.5, 0.999] and 0.001 for the paper's. ``ALG.UPDATE_ORDER`` (SAC only) is ignored.

Random numbers, drawn from the global torch generator in this order in every update: the target
actions at ``o'``, then (when the policy is updated) the policy's actions at ``o``.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from typing import Any, cast

import torch
from torch import nn

from tmrl.algorithms.guard import GuardedUpdate, stepped_tensors
from tmrl.algorithms.sac import SACAgent, _build_model
from tmrl.batch import Batch
from tmrl.errors import UserError
from tmrl.models import FlatInputCritic, SquashedGaussianMLPActor, space_dim
from tmrl.util import partial

__all__ = ["PAPER_BETAS", "BatchRenorm1d", "CrossQActorCritic", "CrossQAgent", "CrossQQFunction"]

PAPER_BETAS = (0.5, 0.999)
"""Adam's betas in the paper (actor and critics)."""


class BatchRenorm1d(nn.Module):
    """Batch Renormalization (Ioffe 2017) over the features of ``(B, C)`` inputs.

    Training mode, with the batch's mean ``mu_B`` and (biased) variance ``var_B``,
    ``sigma_B = sqrt(var_B + eps)`` and the running ``mu``, ``sigma = sqrt(var + eps)``:
    ``x_hat = (x - mu_B) / sigma_B * r + d`` with ``r = clip(sigma_B / sigma, 1/r_max, r_max)`` and
    ``d = clip((mu_B - mu) / sigma, -d_max, d_max)`` treated as constants (no gradient); ``r = 1``,
    ``d = 0`` (plain batch normalisation) during the first ``warmup_steps`` training passes. Then
    ``mu`` and ``var`` move toward ``mu_B`` and ``var_B`` by ``momentum``. Evaluation mode:
    ``x_hat = (x - mu) / sigma``. Output: ``weight * x_hat + bias``.

    The running statistics and the count of training passes (``num_batches_tracked``) are buffers:
    they are in ``state_dict()``, hence in checkpoints.

    Args:
        num_features: ``C``.
        momentum: weight of the batch in the running statistics (PyTorch's convention).
        eps: added to the variances.
        warmup_steps: training passes of plain batch normalisation before renormalisation.
        r_max: bound of the scale correction ``r``.
        d_max: bound of the shift correction ``d``.

    Raises:
        UserError: ``momentum`` not in ``(0, 1]``, ``eps <= 0``, ``warmup_steps < 0``,
            ``r_max < 1`` or ``d_max < 0``.
    """

    num_batches_tracked: torch.Tensor
    running_mean: torch.Tensor
    running_var: torch.Tensor

    def __init__(self, num_features: int, momentum: float = 0.01, eps: float = 1e-3, warmup_steps: int = 100_000,
                 r_max: float = 3.0, d_max: float = 5.0) -> None:
        super().__init__()
        if not 0.0 < float(momentum) <= 1.0:
            raise UserError(f"batch normalisation momentum={momentum} must lie in (0, 1] (ALG.CROSSQ_BN_MOMENTUM)")
        if float(eps) <= 0.0 or int(warmup_steps) < 0 or float(r_max) < 1.0 or float(d_max) < 0.0:
            raise UserError(
                f"BatchRenorm1d needs eps > 0, warmup_steps >= 0, r_max >= 1 and d_max >= 0, got eps={eps}, "
                f"warmup_steps={warmup_steps}, r_max={r_max}, d_max={d_max}"
            )
        self.num_features = int(num_features)
        self.momentum = float(momentum)
        self.eps = float(eps)
        self.warmup_steps = int(warmup_steps)
        self.r_max = float(r_max)
        self.d_max = float(d_max)
        self.weight = nn.Parameter(torch.ones(self.num_features))
        self.bias = nn.Parameter(torch.zeros(self.num_features))
        self.register_buffer("running_mean", torch.zeros(self.num_features))
        self.register_buffer("running_var", torch.ones(self.num_features))
        self.register_buffer("num_batches_tracked", torch.zeros((), dtype=torch.long))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """Normalise ``x`` of shape ``(B, C)`` (see the class)."""
        if not self.training:
            x_hat = (x - self.running_mean) / torch.sqrt(self.running_var + self.eps)
            return x_hat * self.weight + self.bias
        mean = x.mean(0)
        var = x.var(0, unbiased=False)
        std = torch.sqrt(var + self.eps)
        with torch.no_grad():
            running_std = torch.sqrt(self.running_var + self.eps)
            # No host synchronisation: r = 1, d = 0 during the warm-up, chosen on the device.
            warm = self.num_batches_tracked >= self.warmup_steps
            r = torch.where(warm, (std / running_std).clamp(1.0 / self.r_max, self.r_max), 1.0)
            d = torch.where(warm, ((mean - self.running_mean) / running_std).clamp(-self.d_max, self.d_max), 0.0)
            self.running_mean.lerp_(mean, self.momentum)
            self.running_var.lerp_(var, self.momentum)
            self.num_batches_tracked += 1
        x_hat = (x - mean) / std * r + d
        return x_hat * self.weight + self.bias

    def extra_repr(self) -> str:
        return f"{self.num_features}, momentum={self.momentum}, eps={self.eps}, warmup_steps={self.warmup_steps}"

    # --- several critics' layers at once (tmrl.models.stacked_mlp) ----------------------------

    @staticmethod
    def stacks_with(first: BatchRenorm1d, layers: Sequence[nn.Module]) -> bool:
        """Whether ``layers`` (all of this class) have ``first``'s settings, hence can be
        evaluated together by :meth:`stacked_forward`."""
        key = (first.num_features, first.momentum, first.eps, first.warmup_steps, first.r_max, first.d_max)
        return all(isinstance(m, BatchRenorm1d)
                   and (m.num_features, m.momentum, m.eps, m.warmup_steps, m.r_max, m.d_max) == key for m in layers)

    @staticmethod
    def stacked_forward(layers: Sequence[BatchRenorm1d], x: torch.Tensor, detach_params: bool = False) -> torch.Tensor:
        """``torch.stack([layer(x[i]) for i, layer in enumerate(layers)])`` for ``x`` of shape
        ``(k, B, C)``: each layer normalises its own slice with its own statistics and updates its
        own running statistics (in training mode), as :meth:`forward` does, in batched operations.

        Args:
            layers: ``k`` layers with the same settings (:meth:`stacks_with`).
            x: ``(k, B, C)``.
            detach_params: use the affine weights as constants.
        """
        first = layers[0]
        weight = torch.stack([m.weight for m in layers]).unsqueeze(1)  # (k, 1, C)
        bias = torch.stack([m.bias for m in layers]).unsqueeze(1)
        if detach_params:
            weight, bias = weight.detach(), bias.detach()
        running_mean = torch.stack([m.running_mean for m in layers])  # (k, C)
        running_var = torch.stack([m.running_var for m in layers])
        if not first.training:
            x_hat = (x - running_mean.unsqueeze(1)) / torch.sqrt(running_var + first.eps).unsqueeze(1)
            return x_hat * weight + bias
        mean = x.mean(1)  # (k, C)
        var = x.var(1, unbiased=False)
        std = torch.sqrt(var + first.eps)
        with torch.no_grad():
            running_std = torch.sqrt(running_var + first.eps)
            counts = torch.stack([m.num_batches_tracked for m in layers])  # (k,)
            warm = (counts >= first.warmup_steps).unsqueeze(1)
            r = torch.where(warm, (std / running_std).clamp(1.0 / first.r_max, first.r_max), 1.0)
            d = torch.where(warm, ((mean - running_mean) / running_std).clamp(-first.d_max, first.d_max), 0.0)
            torch._foreach_lerp_([m.running_mean for m in layers], list(mean.unbind(0)), first.momentum)
            torch._foreach_lerp_([m.running_var for m in layers], list(var.unbind(0)), first.momentum)
            torch._foreach_add_([m.num_batches_tracked for m in layers], 1)
        x_hat = (x - mean.unsqueeze(1)) / std.unsqueeze(1) * r.unsqueeze(1) + d.unsqueeze(1)
        return x_hat * weight + bias


class CrossQQFunction(FlatInputCritic, nn.Module):
    """CrossQ's critic ``Q(obs, act) -> (B,)``: an MLP with :class:`BatchRenorm1d` on its input and
    after every hidden activation (``BRN -> Linear -> act -> BRN -> ... -> Linear``).

    Args:
        observation_space: the observation space.
        action_space: the action space (a Box).
        hidden_sizes: widths of the hidden layers (the paper: 2048, 2048).
        activation: activation class.
        bn_momentum: momentum of the normalisation layers (PyTorch's convention).
        renorm_warmup_steps: training passes of plain batch normalisation before renormalisation.
        bn_eps: epsilon of the normalisation layers.
        input_norm: normalise the input (the paper's code). False: no layer there (an identity,
            so that the layers keep their indices), for inputs already on a common scale, where
            standardising each of many redundant observation features would drown the action's
            few (the lidar model's choice: :class:`~tmrl.driving.models.LidarCrossQActorCritic`).
    """

    def __init__(
        self,
        observation_space: Any,
        action_space: Any,
        hidden_sizes: Sequence[int] = (1024, 1024),
        activation: Callable[[], nn.Module] = nn.ReLU,
        bn_momentum: float = 0.01,
        renorm_warmup_steps: int = 100_000,
        bn_eps: float = 1e-3,
        input_norm: bool = True,
    ) -> None:
        super().__init__()
        norm = partial(BatchRenorm1d, momentum=bn_momentum, eps=bn_eps, warmup_steps=renorm_warmup_steps)
        width = space_dim(observation_space) + int(torch.Size(action_space.shape).numel())
        layers: list[nn.Module] = [norm(width) if input_norm else nn.Identity()]
        for size in hidden_sizes:
            layers += [nn.Linear(width, int(size)), activation(), norm(int(size))]
            width = int(size)
        layers.append(nn.Linear(width, 1))
        self.net = nn.Sequential(*layers)

    def forward(self, obs: Any, act: torch.Tensor) -> torch.Tensor:
        """Q values of shape ``(B,)``.

        Args:
            obs: a batched observation.
            act: actions ``(B, act_dim)``.
        """
        return self.net(self.critic_input(obs, act)).squeeze(-1)


class CrossQActorCritic(nn.Module):
    """CrossQ's actor-critic: SAC's :class:`~tmrl.models.SquashedGaussianMLPActor` (``.actor``, the
    policy the workers run) and ``n`` :class:`CrossQQFunction` critics (``.qs``).

    Args:
        observation_space: the observation space.
        action_space: the action space (a bounded Box).
        hidden_sizes: widths of the actor's hidden layers (the paper: 256, 256).
        activation: activation class.
        n: number of critics (the paper: 2).
        critic_hidden_sizes: widths of each critic's hidden layers (the paper: 2048, 2048; see the
            module's notes for the default).
        bn_momentum: momentum of the critics' normalisation layers.
        renorm_warmup_steps: critic updates of plain batch normalisation before renormalisation.
        critic_input_norm: a normalisation layer on each critic's input (the paper's code; see
            :class:`CrossQQFunction`).
    """

    def __init__(
        self,
        observation_space: Any,
        action_space: Any,
        hidden_sizes: Sequence[int] = (256, 256),
        activation: Callable[[], nn.Module] = nn.ReLU,
        n: int = 2,
        critic_hidden_sizes: Sequence[int] = (1024, 1024),
        bn_momentum: float = 0.01,
        renorm_warmup_steps: int = 100_000,
        critic_input_norm: bool = True,
    ) -> None:
        super().__init__()
        self.actor = SquashedGaussianMLPActor(observation_space, action_space, hidden_sizes, activation)
        self.qs = nn.ModuleList(
            CrossQQFunction(observation_space, action_space, critic_hidden_sizes, activation, bn_momentum,
                            renorm_warmup_steps, input_norm=critic_input_norm)
            for _ in range(int(n))
        )

    def act(self, obs: Any, test: bool = False) -> Any:
        """The actor's action for a batched observation, as a NumPy array.

        Args:
            obs: a batched observation.
            test: take the mean action instead of a sample.
        """
        return self.actor.act(obs, test)


def _cat_obs(first: Any, second: Any) -> Any:
    """Two batched observations of the same structure (a tensor, or nested tuples, lists and
    dicts of tensors) stacked along the batch axis."""
    if isinstance(first, torch.Tensor):
        return torch.cat((first, second), dim=0)
    if isinstance(first, dict):
        return {k: _cat_obs(v, second[k]) for k, v in first.items()}
    return tuple(_cat_obs(a, b) for a, b in zip(first, second))


_NORM_TYPES = (BatchRenorm1d, nn.modules.batchnorm._BatchNorm)


class CrossQAgent(SACAgent):
    """CrossQ. Takes every argument of :class:`~tmrl.algorithms.sac.SACAgent` but ``update_order``
    and ``fused`` (``model_cls`` defaults to :class:`CrossQActorCritic`; ``polyak`` is unused: no
    target networks; ``betas_actor``/``betas_critic`` None mean the paper's ``(0.5, 0.999)`` for
    Adam and AdamW) plus:

    Args:
        policy_delay: critic updates per actor (and entropy) update (the paper: 3).
        critic_width: width of the critics' two hidden layers, passed to ``model_cls`` as
            ``critic_hidden_sizes=(critic_width, critic_width)`` when it accepts it (the paper:
            2048; 1024 here, see the module's notes).
        bn_momentum: momentum of the critics' normalisation layers, passed as ``bn_momentum=``
            when accepted (PyTorch's convention: the paper's 0.99 is 0.01 here).
        renorm_warmup_steps: critic updates of plain batch normalisation before Batch
            Renormalization, passed as ``renorm_warmup_steps=`` when accepted.

    Raises:
        UserError: ``policy_delay < 1``, ``critic_width < 1``, ``bn_momentum`` not in ``(0, 1]``,
            ``renorm_warmup_steps < 0``, or a model whose critics have no batch normalisation;
            plus :class:`SACAgent`'s errors.
    """

    def __init__(
        self,
        observation_space: Any = None,
        action_space: Any = None,
        device: Any = None,
        model_cls: Callable[..., torch.nn.Module] = CrossQActorCritic,
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
        policy_delay: int = 3,
        critic_width: int = 1024,
        bn_momentum: float = 0.01,
        renorm_warmup_steps: int = 100_000,
    ) -> None:
        self.policy_delay = int(policy_delay)
        self.critic_width = int(critic_width)
        self.bn_momentum = float(bn_momentum)
        self.renorm_warmup_steps = int(renorm_warmup_steps)
        if self.policy_delay < 1:
            raise UserError(f"policy_delay={policy_delay} must be >= 1 (ALG.CROSSQ_POLICY_DELAY), typically 3")
        if self.critic_width < 1:
            raise UserError(f"critic_width={critic_width} must be >= 1 (ALG.CROSSQ_CRITIC_WIDTH)")
        if not 0.0 < self.bn_momentum <= 1.0:
            raise UserError(f"bn_momentum={bn_momentum} must lie in (0, 1] (ALG.CROSSQ_BN_MOMENTUM), typically 0.01")
        if self.renorm_warmup_steps < 0:
            raise UserError(f"renorm_warmup_steps={renorm_warmup_steps} must be >= 0 (ALG.CROSSQ_RENORM_WARMUP_STEPS)")
        self.i_update = 0

        def paper_betas(betas: Sequence[float] | None, optimizer: str) -> Sequence[float] | None:
            adam = str(optimizer).lower() in ("adam", "adamw")
            return PAPER_BETAS if betas is None and adam else betas

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
            betas_actor=paper_betas(betas_actor, optimizer_actor),
            betas_critic=paper_betas(betas_critic, optimizer_critic),
            l2_actor=l2_actor,
            l2_critic=l2_critic,
            compile=compile,
            update_order="sequential",  # the actor loss reads the critics after their step
            fused=False,
        )
        # No target networks: an empty module keeps SACAgent's checkpoint layout ("model_target": {}).
        self.model_target = nn.Module()
        self.critics_target = None  # type: ignore[assignment]
        self._target_params = []
        self._critic_modules: list[nn.Module] = self.critics.modules or [self.critics.ensemble]  # type: ignore[list-item]
        self._norm_buffers = [buf for c in self._critic_modules for m in c.modules() if isinstance(m, _NORM_TYPES)
                              for buf in m.buffers()]
        if not self._norm_buffers:
            name = getattr(model_cls, "__name__", type(self.model).__name__)
            raise UserError(
                f"CrossQ's critics need batch normalisation layers, and {name}'s have none: use "
                "tmrl.algorithms.crossq.CrossQActorCritic (or its CrossQQFunction) as the model"
            )

    def _make_model(self) -> torch.nn.Module:
        w = self.critic_width
        return _build_model(self.model_cls, self.observation_space, self.action_space, critic_hidden_sizes=(w, w),
                            bn_momentum=self.bn_momentum, renorm_warmup_steps=self.renorm_warmup_steps)

    @contextmanager
    def critics_mode(self, training: bool) -> Iterator[None]:
        """The critics in training (batch statistics, running statistics updated) or evaluation
        mode (running statistics) inside the block; training mode after it."""
        for c in self._critic_modules:
            c.train(training)
        try:
            yield
        finally:
            for c in self._critic_modules:
                c.train(True)

    # --- one update, top to bottom ------------------------------------------------------------

    def train(self, batch: tuple) -> dict[str, Any]:
        """One CrossQ update on ``batch`` (see the module's notes): the joint critic pass and
        target, the critics' step, then (when :meth:`policy_update_due`) the actor's and the
        entropy coefficient's step against the updated critics in evaluation mode
        (:meth:`_update_with`; with ``ALG.COMPILE`` on, its two loss functions compiled).

        Returns:
            The metrics of :meth:`SACAgent.train`.
        """
        if self._compile_state.mode != "off":
            return self._compiled_train(batch)
        return self._update_off(batch, self.policy_update_due())

    def _update_off(self, batch: tuple, update_policy: bool) -> dict[str, Any]:
        return self._update_with(self._eager_functions(), batch, update_policy)

    COMPILED = ("_critic_losses", "_policy_losses")
    """The two loss functions of an update (``ALG.COMPILE`` compiles both)."""

    def _critic_losses(self, b: Batch, alpha: torch.Tensor) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
        """The joint pass and the critics' loss: ``(loss_critic, stats)`` (``debug_q``,
        ``debug_backup``). Runs with the critics in training mode."""
        q, backup = self.joint_critic_pass(b, alpha)
        return self.critic_loss(q, backup), {"debug_q": q.detach().mean(), "debug_backup": backup.mean()}

    def _policy_losses(self, b: Batch, alpha: torch.Tensor) -> tuple[Any, ...]:
        """The actor's and the entropy coefficient's losses against the critics, as constants, in
        evaluation mode (the caller's): ``(loss_actor, loss_alpha, stats)`` (``debug_log_pi``)."""
        pi, logp_pi = self.actor(b.obs)
        q_pi_all = self.critics(b.obs, pi, detach_params=True)
        return self.actor_loss(alpha, logp_pi, q_pi_all), self.entropy_loss(logp_pi), {
            "debug_log_pi": logp_pi.detach().mean()}

    def _update_with(self, fns: dict[str, Callable[..., Any]], batch: tuple, update_policy: bool) -> dict[str, Any]:
        """One CrossQ update whose losses come from ``fns`` (eager or compiled); backward passes,
        the non-finite guard, the steps and the switches of the critics' mode run eager."""
        b = self._prepare_batch(Batch(*batch))
        g = self._begin_update(update_policy)
        alpha = self._entropy_coef()
        # Statistics of a non-finite pass would poison evaluation mode: kept to put back.
        saved = None if g.on_device else [buf.clone() for buf in self._norm_buffers]
        g.keep(self._norm_buffers)
        with self.critics_mode(training=True):
            loss_critic, stats = fns["_critic_losses"](b, alpha)
        self.q_optimizer.zero_grad(set_to_none=True)
        loss_critic.backward()
        if not g.check(loss_critic, self.critics.parameters()):
            with torch.no_grad():
                for buf, old in zip(self._norm_buffers, cast(list, saved)):
                    buf.copy_(old)
            return self.guard.skipped_metrics()
        if g.on_device:
            g.keep(stepped_tensors([self.q_optimizer]))
        self.q_optimizer.step()
        g.restore()  # on the device: the critics' step stands alone, before the policy reads them
        own = self._owned
        loss_critic = own(loss_critic)
        metrics: dict[str, Any] = {}
        if update_policy:
            with self.critics_mode(training=False):
                loss_actor, loss_alpha, policy_stats = fns["_policy_losses"](b, alpha)
            if not self._policy_step(loss_actor, loss_alpha, g):
                return self.guard.skipped_metrics()
            self.loss_pi = g.pick(own(loss_actor), self.loss_pi)
            if loss_alpha is not None:
                self.loss_alpha = g.pick(own(loss_alpha), self.loss_alpha)
            metrics.update((k, own(v)) for k, v in policy_stats.items())
        metrics = {"loss_actor": self.loss_pi, "loss_critic": loss_critic, "entropy_coef": own(alpha), **metrics}
        metrics.update((k, own(v)) for k, v in stats.items())
        if self.log_alpha is not None:
            metrics["loss_entropy_coef"] = self.loss_alpha
        return g.finish(metrics)

    # --- the steps that differ from SAC ---------------------------------------------------------

    def policy_update_due(self) -> bool:
        """Counts the update; true once every ``policy_delay`` of them (updates 3, 6, ... with the
        paper's delay of 3)."""
        self.i_update += 1
        return self.i_update % self.policy_delay == 0

    def joint_critic_pass(self, batch: Batch, alpha: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """``(Q_i(o, a), y)``: one pass of the critics in training mode over ``[(o, a); (o', a')]``,
        ``a' ~ pi(.|o')``, split in two; the target ``y`` from the detached second half.

        Args:
            batch: the training batch.
            alpha: the entropy coefficient.

        Returns:
            ``Q_i(o, a)`` of every critic ``(k, B)`` (with gradients) and the target ``(B,)``.
        """
        with torch.no_grad():
            a2, logp_a2 = self.actor(batch.next_obs)
        size = batch.act.shape[0]
        with self.critics_mode(training=True):
            q_all = self.critics(_cat_obs(batch.obs, batch.next_obs), torch.cat((batch.act, a2), dim=0))  # (k, 2B)
        q, q_next = q_all[:, :size], q_all[:, size:].detach()
        r, d = batch.rew.reshape(-1), batch.terminated.reshape(-1)
        return q, r + self.gamma * (1.0 - d) * (self.target_q_from(q_next) - alpha * logp_a2)

    def target_q_from(self, q_next_all: torch.Tensor) -> torch.Tensor:
        """The bootstrap value, shape ``(B,)``: the minimum over the critics (SAC's clipped double
        Q, on the online critics).

        Args:
            q_next_all: ``Q_i(o', a')`` of every critic from the joint pass, shape ``(k, B)``.
        """
        return q_next_all.min(0).values

    def target_q(self, next_obs: Any, next_act: torch.Tensor) -> torch.Tensor:
        """Not a CrossQ step: without target critics, the target comes from the joint pass
        (:meth:`joint_critic_pass`, :meth:`target_q_from`).

        Args:
            next_obs: unused.
            next_act: unused.

        Raises:
            NotImplementedError: always.
        """
        raise NotImplementedError("CrossQ has no target critics: see CrossQAgent.joint_critic_pass")

    def target_value(self, batch: Batch, alpha: torch.Tensor) -> torch.Tensor:
        """Not a CrossQ step: the target comes from the joint pass (:meth:`joint_critic_pass`).

        Args:
            batch: unused.
            alpha: unused.

        Raises:
            NotImplementedError: always.
        """
        raise NotImplementedError("CrossQ computes its target in the joint pass: see CrossQAgent.joint_critic_pass")

    # policy_q is SAC's: the minimum over the critics (the reference code's actor loss).

    def _policy_step(self, loss_actor: torch.Tensor, loss_alpha: torch.Tensor | None,
                     guard: GuardedUpdate | None = None) -> bool:
        """One backward pass through the actor's and the entropy coefficient's losses (their
        parameters are disjoint), then both steps; False (no step) when not finite and ``guard``
        (default: on the host) decides on the host. On the device the steps run and ``guard``
        puts their changes back unless the whole update was finite."""
        g = guard if guard is not None else GuardedUpdate(self.guard, False)
        loss = loss_actor if loss_alpha is None else loss_actor + loss_alpha
        optimizers = [self.pi_optimizer] + ([self.alpha_optimizer] if loss_alpha is not None else [])
        for opt in optimizers:
            opt.zero_grad(set_to_none=True)  # type: ignore[union-attr]
        loss.backward()
        params = list(self.actor.parameters()) + ([self.log_alpha] if self.log_alpha is not None else [])
        if not g.check(loss, params):
            return False
        if g.on_device:
            g.keep(stepped_tensors(cast(list[torch.optim.Optimizer], optimizers)))
        held = loss_alpha is not None and self._at_alpha_max(g.on_device)
        for opt in optimizers:
            opt.step()  # type: ignore[union-attr]
        self._hold_alpha(held)
        return True

    # --- checkpointing ------------------------------------------------------------------------

    def state_dict(self) -> dict[str, Any]:
        """:meth:`SACAgent.state_dict` (the model's includes the normalisation layers' running
        statistics; ``model_target`` is empty) plus the update counter and the losses of the
        latest policy update."""
        state = super().state_dict()
        state["i_update"] = self.i_update
        state["loss_actor"] = self.loss_pi
        state["loss_entropy_coef"] = self.loss_alpha
        return state

    def _load_extra_state(self, state: dict[str, Any]) -> None:
        self.i_update = int(state["i_update"])
        for attr, key in (("loss_pi", "loss_actor"), ("loss_alpha", "loss_entropy_coef")):
            setattr(self, attr, torch.as_tensor(state.get(key, 0.0), device=self.device).reshape(()))
