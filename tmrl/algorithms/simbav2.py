"""SimbaV2-style critics for SAC (after Lee, Lee, Hwang, Kim, Choo, Sung, Oh, Hwang, ICML 2025,
"Hyperspherical Normalization for Scalable Deep Reinforcement Learning").

SAC's update (:meth:`tmrl.algorithms.sac.SACAgent.train`, the simultaneous order) with SimbaV2's
critic, its distributional loss and its reward scaling; the actor stays SAC's squashed Gaussian
MLP, the policy the workers run.

The critic (:class:`SimbaV2Critic`), every hidden vector on the unit hypersphere:

- input: ``x = [obs, act, c]`` (the *shift*: a constant feature ``c``, so that the direction of
  ``x`` keeps the input's norm), ``x <- x / ||x||``;
- embedding: ``h = normalize(s_0 * (W_0 x))``, ``W_0`` a :class:`HyperLinear` (no bias, each row of
  the weight kept at norm 1: the rows are projected back onto the sphere after every optimizer
  step, :meth:`SimbaV2Agent._after_step`), ``s_0`` a learnable per-unit :class:`Scaler`;
- ``blocks`` residual blocks: ``m = normalize(W_2 relu(s_1 * (W_1 h)))`` (``W_1``: width to 4x
  width, ``W_2`` back), then the LERP ``h <- normalize(h + alpha * (m - h))`` with a learnable
  per-unit ``alpha``;
- output: a categorical distribution over a fixed support of ``n_atoms`` atoms evenly spaced on
  ``[-v_max, v_max]``: logits ``W_4 (s_3 * (W_3 h)) + b``; the critic returns the logits.

The update, read against SAC:

- target: ``a' ~ pi(.|o')``; of the two (``n``) target critics, the one whose distribution at
  ``(o', a')`` has the smaller mean (clipped double Q on the means) gives the probabilities
  ``p_j`` of the atoms ``z_j``; the atoms move to ``r~ + gamma (1 - terminated) (z_j - alpha log
  pi(a'|o'))`` (the entropy term shifts the support, as it shifts SAC's target; ``r~`` is the
  scaled reward) and their mass is projected back onto the support (:func:`categorical_projection`,
  C51's projection) (:meth:`SimbaV2Agent.target_value`). Truncated episodes bootstrap;
- critics: the cross-entropy of each critic's distribution against the projected target,
  averaged over critics and batch (:meth:`SimbaV2Agent.critic_loss`);
- policy: SAC's loss on ``min_n E[Z_n(o, a~)]``, the smaller of the critics' means
  (:meth:`SimbaV2Agent.policy_q`); the entropy coefficient as SAC v2's; Polyak-averaged targets;
- after every step of the critics' optimizer, the rows of every :class:`HyperLinear` weight of the
  online critics are projected back to norm 1 (the targets, Polyak averages of unit rows, are
  left as they are).

Reward scaling (:class:`ReturnScaler`): rewards are divided by
``max(sqrt(var(G) + eps), max|G| / g_max)``, ``G`` the running discounted return ``G_t = r_t +
gamma (1 - done_{t-1}) G_{t-1}``, its variance a running estimate over every ``G`` seen and
``max|G|`` the largest seen (the paper's scaling: the return's spread, but never so little that a
return leaves ``[-g_max, g_max]``, inside the support). An agent of this project sees batches,
not episodes: the stream the scaler reads is the sequence of the transitions of the batches it
trains on, in batch order (updated after each successful step, from the next update on). A
uniform replay batch is a shuffle of the memory's transitions, so ``G`` there is a discounted sum
of rewards drawn at random between episode ends (``terminated`` or ``truncated``): its mean is the
return's, its spread misses the correlation of the rewards within an episode, and ``max|G|``
carries the scale for rewards of one sign. The scaler's state is in the checkpoint.

Left out of SimbaV2: its hyperspherical actor (the workers run SAC's MLP actor and load its
weights by name), the running observation normalisation (the lidar models scale their inputs
instead), the learning-rate decay, and its settings of the keys SAC shares (the paper: learning
rate 1e-4 decayed to 3e-5, critic width 512 and 2 blocks, batch 256); the keys SAC shares keep
SAC's class defaults, as TQC's do. Defaults sized for a CPU: critic width 128, 1 block, 2 critics,
101 atoms on ``[-5, 5]``, ``g_max = 5``. The critics are evaluated one by one
(:class:`~tmrl.algorithms.critics.CriticSet`: their ``net`` is not an ``nn.Sequential``).

Lidar observations: :class:`tmrl.driving.models.LidarSimbaV2ActorCritic`.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from typing import Any

import torch
import torch.nn.functional as F
from torch import nn

from tmrl.algorithms.guard import GuardedUpdate
from tmrl.algorithms.sac import SACAgent, _build_model
from tmrl.batch import Batch
from tmrl.errors import UserError
from tmrl.models import FlatInputCritic, SquashedGaussianMLPActor, space_dim

__all__ = [
    "HyperLinear",
    "LerpBlock",
    "ReturnScaler",
    "Scaler",
    "SimbaV2ActorCritic",
    "SimbaV2Agent",
    "SimbaV2Critic",
    "categorical_projection",
    "l2_normalize",
]

NORM_EPS = 1e-8
"""The smallest norm :func:`l2_normalize` and :meth:`HyperLinear.project_` divide by."""


def l2_normalize(x: torch.Tensor) -> torch.Tensor:
    """``x / ||x||`` along the last axis (onto the unit hypersphere)."""
    return x / x.norm(dim=-1, keepdim=True).clamp_min(NORM_EPS)


def categorical_projection(probs: torch.Tensor, atoms: torch.Tensor, v_min: float, v_max: float) -> torch.Tensor:
    """C51's projection: the masses ``probs`` at the positions ``atoms`` onto the fixed support of
    ``A`` atoms evenly spaced on ``[v_min, v_max]``.

    A position between two support atoms splits its mass between them in proportion to its
    nearness to each; a position beyond the support puts its mass on the end atom.

    Args:
        probs: masses ``(B, A)``.
        atoms: their positions ``(B, A)``.
        v_min: the first support atom.
        v_max: the last support atom.

    Returns:
        The projected distribution ``(B, A)`` on the support (rows sum as ``probs`` do).
    """
    n = probs.shape[-1]
    dz = (v_max - v_min) / (n - 1)
    b = (atoms.clamp(v_min, v_max) - v_min) / dz  # fractional index on the support, in [0, n - 1]
    # a NaN position (a NaN reward) takes index 0 and keeps its NaN weights: the loss is NaN and the
    # non-finite guard skips the update, where a NaN index would fail the scatter
    lower = b.floor().clamp(0, n - 1).nan_to_num(0.0)
    upper = (lower + 1).clamp(max=n - 1)
    w_up = b - lower  # 0 at the last atom, where lower == upper
    out = torch.zeros_like(probs)
    out.scatter_add_(-1, lower.long(), probs * (1.0 - w_up))
    out.scatter_add_(-1, upper.long(), probs * w_up)
    return out


class HyperLinear(nn.Module):
    """A linear layer ``y = W x (+ b)`` whose weight rows are kept on the unit hypersphere:
    initialised orthogonal then normalised, and projected back by :meth:`project_` (after every
    optimizer step).

    Args:
        dim_in: input width.
        dim_out: output width.
        bias: add a learnable bias (zeros at first).
    """

    def __init__(self, dim_in: int, dim_out: int, bias: bool = False) -> None:
        super().__init__()
        self.weight = nn.Parameter(torch.empty(int(dim_out), int(dim_in)))
        nn.init.orthogonal_(self.weight)
        self.bias = nn.Parameter(torch.zeros(int(dim_out))) if bias else None
        self.project_()

    @torch.no_grad()
    def project_(self) -> None:
        """Every row of the weight back to norm 1, in place."""
        self.weight.div_(self.weight.norm(dim=1, keepdim=True).clamp_min(NORM_EPS))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return F.linear(x, self.weight, self.bias)


class Scaler(nn.Module):
    """A learnable per-unit scale ``s * x``, ``s`` stored as ``p * (init / scale)`` with ``p``
    starting at ``scale`` (so ``s`` starts at ``init``; ``scale`` sets the size of the stored
    parameter, hence how far an optimizer step moves ``s``).

    Args:
        dim: number of units.
        init: initial scale.
        scale: magnitude of the stored parameter.
    """

    def __init__(self, dim: int, init: float = 1.0, scale: float = 1.0) -> None:
        super().__init__()
        self.factor = float(init) / float(scale)
        self.param = nn.Parameter(torch.full((int(dim),), float(scale)))

    def value(self) -> torch.Tensor:
        """The scale ``s`` of each unit."""
        return self.param * self.factor

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return x * self.value()


class LerpBlock(nn.Module):
    """A residual block on the sphere: ``m = normalize(W_2 relu(s * (W_1 h)))``, then
    ``h <- normalize(h + alpha * (m - h))``.

    Args:
        width: the width of ``h``.
        expansion: the hidden width is ``expansion * width``.
        alpha_init: initial ``alpha`` (each unit).
        alpha_scale: magnitude of ``alpha``'s stored parameter (:class:`Scaler`).
        scaler_init: initial hidden scale ``s``.
        scaler_scale: magnitude of ``s``'s stored parameter.
    """

    def __init__(self, width: int, expansion: int = 4, alpha_init: float = 0.5, alpha_scale: float = 1.0,
                 scaler_init: float = 1.0, scaler_scale: float = 1.0) -> None:
        super().__init__()
        self.w1 = HyperLinear(width, expansion * width)
        self.s1 = Scaler(expansion * width, scaler_init, scaler_scale)
        self.w2 = HyperLinear(expansion * width, width)
        self.alpha = Scaler(width, alpha_init, alpha_scale)

    def mlp(self, h: torch.Tensor) -> torch.Tensor:
        """``normalize(W_2 relu(s * (W_1 h)))``."""
        return l2_normalize(self.w2(torch.relu(self.s1(self.w1(h)))))

    def forward(self, h: torch.Tensor) -> torch.Tensor:
        return l2_normalize(h + self.alpha.value() * (self.mlp(h) - h))


class SimbaV2Critic(FlatInputCritic, nn.Module):
    """SimbaV2's distributional critic: logits ``(B, n_atoms)`` of the return's distribution on
    the support of :class:`SimbaV2Agent` (module docstring).

    Args:
        observation_space: the observation space.
        action_space: the action space (a Box).
        width: the width of the hidden vectors.
        blocks: number of :class:`LerpBlock` blocks.
        n_atoms: atoms of the support.
        shift: the constant feature appended to the input before it is normalised.
    """

    squeeze_output = False
    """:meth:`forward` keeps the output's last axis (the atoms)."""

    def __init__(self, observation_space: Any, action_space: Any, width: int = 128, blocks: int = 1,
                 n_atoms: int = 101, shift: float = 3.0) -> None:
        super().__init__()
        dim_in = space_dim(observation_space) + int(torch.Size(action_space.shape).numel())
        self.shift = float(shift)
        self.n_atoms = int(n_atoms)
        # The published code's scales, as we read them: sqrt(2 / width) for the scalers, and for
        # alpha 1 / (blocks + 1) at first, stored at magnitude 1 / sqrt(width).
        s = math.sqrt(2.0 / width)
        self.embed = HyperLinear(dim_in + 1, width)
        self.embed_scaler = Scaler(width, s, s)
        self.blocks = nn.ModuleList(
            LerpBlock(width, 4, 1.0 / (blocks + 1), 1.0 / math.sqrt(width), s, s) for _ in range(int(blocks))
        )
        self.head = HyperLinear(width, width)
        self.head_scaler = Scaler(width, s, s)
        self.out = HyperLinear(width, self.n_atoms, bias=True)

    def embedding(self, x: torch.Tensor) -> torch.Tensor:
        """The first hidden vector from the flat input ``x`` ``(B, D)``: shift, normalise, project,
        scale, normalise."""
        x = torch.cat([x, torch.full_like(x[:, :1], self.shift)], dim=-1)
        return l2_normalize(self.embed_scaler(self.embed(l2_normalize(x))))

    def forward(self, obs: Any, act: torch.Tensor) -> torch.Tensor:
        """Logits ``(B, n_atoms)``.

        Args:
            obs: a batched observation.
            act: actions ``(B, act_dim)``.
        """
        h = self.embedding(self.critic_input(obs, act))
        for block in self.blocks:
            h = block(h)
        return self.out(self.head_scaler(self.head(h)))


class SimbaV2ActorCritic(nn.Module):
    """SAC's :class:`~tmrl.models.SquashedGaussianMLPActor` (``.actor``, the workers' policy) and
    ``n`` :class:`SimbaV2Critic` critics (``.qs``).

    Args:
        observation_space: the observation space.
        action_space: the action space (a bounded Box).
        hidden_sizes: widths of the actor's hidden layers.
        activation: the actor's activation class.
        n: number of critics.
        n_atoms: atoms of each critic's support.
        v_max: the support is ``[-v_max, v_max]``.
        critic_width: width of the critics' hidden vectors.
        critic_blocks: residual blocks per critic.
    """

    def __init__(self, observation_space: Any, action_space: Any, hidden_sizes: Sequence[int] = (256, 256),
                 activation: Callable[[], nn.Module] = nn.ReLU, n: int = 2, n_atoms: int = 101, v_max: float = 5.0,
                 critic_width: int = 128, critic_blocks: int = 1) -> None:
        super().__init__()
        self.n_atoms = int(n_atoms)
        self.v_max = float(v_max)
        self.actor = SquashedGaussianMLPActor(observation_space, action_space, hidden_sizes, activation)
        self.qs = nn.ModuleList(
            SimbaV2Critic(observation_space, action_space, critic_width, critic_blocks, n_atoms) for _ in range(int(n))
        )

    def act(self, obs: Any, test: bool = False) -> Any:
        """The actor's action for a batched observation, as a NumPy array.

        Args:
            obs: a batched observation.
            test: take the mean action instead of a sample.
        """
        return self.actor.act(obs, test)


class ReturnScaler(nn.Module):
    """The reward scale of SimbaV2: ``max(sqrt(var(G) + eps), max|G| / g_max)`` over the running
    discounted returns ``G`` of a stream of transitions (module docstring). The state is buffers
    (a checkpoint's ``reward_scaler``): ``carry`` (what the next transition's ``G`` adds to its
    reward: ``gamma (1 - done) G`` of the last one), ``count``, ``mean`` and ``var`` of every ``G``
    seen (population variance; 1 before any, so that the scale starts at 1) and ``abs_max``.

    Args:
        gamma: the discount.
        g_max: the largest ``|G|`` after scaling.
        eps: added to the variance.
    """

    carry: torch.Tensor
    count: torch.Tensor
    mean: torch.Tensor
    var: torch.Tensor
    abs_max: torch.Tensor

    def __init__(self, gamma: float, g_max: float = 5.0, eps: float = 1e-8) -> None:
        super().__init__()
        self.gamma = float(gamma)
        self.g_max = float(g_max)
        self.eps = float(eps)
        for name, value in (("carry", 0.0), ("count", 0.0), ("mean", 0.0), ("var", 1.0), ("abs_max", 0.0)):
            self.register_buffer(name, torch.tensor(value))

    def scale(self) -> torch.Tensor:
        """The current scale (0-d)."""
        return torch.maximum(torch.sqrt(self.var + self.eps), self.abs_max / self.g_max)

    def forward(self, rew: torch.Tensor) -> torch.Tensor:
        """``rew`` divided by the current scale."""
        return rew / self.scale()

    def returns(self, rew: torch.Tensor, done: torch.Tensor) -> torch.Tensor:
        """The running returns ``G_t = r_t + gamma (1 - done_{t-1}) G_{t-1}`` of the stream
        ``rew`` (``G_{-1}`` term: :attr:`carry`), in one product: ``G = L r + c``, ``L[t, s] =
        gamma^(t - s)`` when ``s <= t`` in the same episode, ``c_t = gamma^t carry`` in the first.

        Args:
            rew: rewards ``(T,)``.
            done: 1 where an episode ended with the transition ``(T,)``.
        """
        t = torch.arange(rew.numel(), device=rew.device, dtype=rew.dtype)
        episode = torch.cumsum(done, 0) - done  # episode index of each transition
        lag = t[:, None] - t[None, :]
        same = (episode[:, None] == episode[None, :]) & (lag >= 0)
        lower = torch.where(same, torch.pow(self.gamma, lag.clamp(min=0)), torch.zeros_like(lag))
        first = (episode == 0).to(rew.dtype)
        return lower @ rew + first * torch.pow(self.gamma, t) * self.carry

    @torch.no_grad()
    def update(self, rew: torch.Tensor, terminated: torch.Tensor, truncated: torch.Tensor | None = None) -> None:
        """Read the transitions ``(rew, terminated, truncated)``, in order, into the running
        statistics (an episode ends on either flag)."""
        r = rew.detach().reshape(-1).to(self.mean.dtype)
        if r.numel() == 0:
            return
        done = terminated.detach().reshape(-1).to(r.dtype) != 0
        if truncated is not None:
            done = done | (truncated.detach().reshape(-1) != 0)
        done_f = done.to(r.dtype)
        g = self.returns(r, done_f)
        n = float(g.numel())
        b_mean = g.mean()
        b_var = g.var(unbiased=False)
        total = self.count + n
        delta = b_mean - self.mean
        m2 = self.var * self.count + b_var * n + delta.square() * self.count * n / total
        self.mean.add_(delta * n / total)
        self.var.copy_(m2 / total)
        self.count.copy_(total)
        self.abs_max.copy_(torch.maximum(self.abs_max, g.abs().max()))
        self.carry.copy_(self.gamma * (1.0 - done_f[-1]) * g[-1])


class SimbaV2Agent(SACAgent):
    """SAC with SimbaV2's critics (module docstring). Takes every argument of
    :class:`~tmrl.algorithms.sac.SACAgent` but ``update_order`` and ``fused`` (same meaning;
    ``model_cls`` defaults to :class:`SimbaV2ActorCritic`) plus:

    Args:
        n: number of critics; passed to ``model_cls`` as ``n=`` when it accepts it.
        n_atoms: atoms of the support (``n_atoms=``).
        v_max: the support is ``[-v_max, v_max]`` (``v_max=``).
        critic_width: width of the critics' hidden vectors (``critic_width=``).
        critic_blocks: residual blocks per critic (``critic_blocks=``).
        scale_rewards: divide the rewards by :class:`ReturnScaler`'s scale.
        reward_g_max: the scaler's ``g_max``.

    Raises:
        UserError: ``n < 1``, ``n_atoms < 2``, ``v_max <= 0``, ``critic_width < 1``,
            ``critic_blocks < 0``, ``reward_g_max <= 0``, or a model whose critics are not ``n``
            critics of ``n_atoms`` atoms on ``[-v_max, v_max]``; plus :class:`SACAgent`'s errors.
    """

    def __init__(
        self,
        observation_space: Any = None,
        action_space: Any = None,
        device: Any = None,
        model_cls: Callable[..., torch.nn.Module] = SimbaV2ActorCritic,
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
        n_atoms: int = 101,
        v_max: float = 5.0,
        critic_width: int = 128,
        critic_blocks: int = 1,
        scale_rewards: bool = True,
        reward_g_max: float = 5.0,
    ) -> None:
        self.n = int(n)
        self.n_atoms = int(n_atoms)
        self.v_max = float(v_max)
        self.critic_width = int(critic_width)
        self.critic_blocks = int(critic_blocks)
        self.scale_rewards = bool(scale_rewards)
        self.reward_g_max = float(reward_g_max)
        if self.n < 1:
            raise UserError(f"SimbaV2 needs at least one critic, got n={n}")
        if self.n_atoms < 2:
            raise UserError(f"SimbaV2's support needs at least 2 atoms, got n_atoms={n_atoms}")
        if not self.v_max > 0.0:
            raise UserError(f"v_max={v_max} must be > 0: the support is [-v_max, v_max]")
        if self.critic_width < 1 or self.critic_blocks < 0:
            raise UserError(f"SimbaV2's critics need critic_width >= 1 and critic_blocks >= 0, got "
                            f"critic_width={critic_width} and critic_blocks={critic_blocks}")
        if not self.reward_g_max > 0.0:
            raise UserError(f"reward_g_max={reward_g_max} must be > 0 (the largest scaled return)")
        self._pending: tuple[torch.Tensor, torch.Tensor, torch.Tensor] | None = None
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
        atoms = getattr(self.model, "n_atoms", None)
        v = getattr(self.model, "v_max", None)
        if len(self.critics) != self.n or atoms != self.n_atoms or v != self.v_max:
            raise UserError(
                f"SimbaV2 was asked for n={self.n} critics of {self.n_atoms} atoms on [-{self.v_max}, {self.v_max}] "
                f"but {getattr(model_cls, '__name__', type(self.model).__name__)} built {len(self.critics)} of "
                f"{atoms} on [-{v}, {v}]: give the model `n`, `n_atoms` and `v_max` arguments that match"
            )
        self.support = torch.linspace(-self.v_max, self.v_max, self.n_atoms, device=self.device)
        self.reward_scaler = ReturnScaler(self.gamma, self.reward_g_max).to(self.device)
        # the layers whose weight rows are projected back onto the sphere after each critic step
        self._hyper = [m for q in self.critics.modules for m in q.modules() if isinstance(m, HyperLinear)]

    def _make_model(self) -> torch.nn.Module:
        return _build_model(
            self.model_cls, self.observation_space, self.action_space, n=self.n, n_atoms=self.n_atoms,
            v_max=self.v_max, critic_width=self.critic_width, critic_blocks=self.critic_blocks,
        )

    # --- the steps that differ from SAC ---------------------------------------------------------

    def expected(self, logits: torch.Tensor) -> torch.Tensor:
        """The means of the distributions of ``logits`` ``(..., n_atoms)`` on the support."""
        return (logits.softmax(-1) * self.support).sum(-1)

    def target_q(self, next_obs: Any, next_act: torch.Tensor) -> torch.Tensor:
        """The target distribution at ``(o', a')``: the probabilities ``(B, n_atoms)`` of the
        target critic whose mean there is the smallest.

        Args:
            next_obs: the batch's next observations ``o'``.
            next_act: actions ``a'`` drawn from the current policy at ``o'``.
        """
        probs = self.critics_target(next_obs, next_act).softmax(-1)  # (N, B, A)
        pick = (probs * self.support).sum(-1).argmin(0)  # (B,): the critic of the smaller mean
        return probs.gather(0, pick.view(1, -1, 1).expand(1, *probs.shape[1:])).squeeze(0)

    def scaled_reward(self, rew: torch.Tensor) -> torch.Tensor:
        """``rew`` divided by the reward scale (unchanged when ``scale_rewards`` is off)."""
        return self.reward_scaler(rew) if self.scale_rewards else rew

    @torch.no_grad()
    def target_value(self, batch: Batch, alpha: torch.Tensor) -> torch.Tensor:
        """The projected target distribution ``(B, n_atoms)``: the atoms ``z_j`` of
        :meth:`target_q`'s distribution moved to ``r~ + gamma (1 - terminated) (z_j - alpha log
        pi(a'|o'))``, ``a' ~ pi(.|o')``, then projected onto the support
        (:func:`categorical_projection`). Truncated episodes bootstrap (as in SAC).

        Args:
            batch: the training batch.
            alpha: the entropy coefficient.
        """
        a2, logp_a2 = self.actor(batch.next_obs)
        r = self.scaled_reward(batch.rew.reshape(-1, 1))
        d = batch.terminated.reshape(-1, 1)
        atoms = r + self.gamma * (1.0 - d) * (self.support - alpha * logp_a2.unsqueeze(1))
        return categorical_projection(self.target_q(batch.next_obs, a2), atoms, -self.v_max, self.v_max)

    def critic_loss(self, q: torch.Tensor, backup: torch.Tensor) -> torch.Tensor:
        """The cross-entropy of each critic's distribution against the target, averaged over
        critics and batch.

        Args:
            q: the critics' logits, shape ``(N, B, n_atoms)``.
            backup: the projected target distribution ``(B, n_atoms)`` (:meth:`target_value`).
        """
        return -(backup * q.log_softmax(-1)).sum(-1).mean()

    def policy_q(self, q_pi_all: torch.Tensor) -> torch.Tensor:
        """The smaller of the critics' means at ``(o, a~)``, shape ``(B,)``.

        Args:
            q_pi_all: the critics' logits at ``(o, a~)``, shape ``(N, B, n_atoms)``.
        """
        return self.expected(q_pi_all).min(0).values

    # --- the weight projection and the reward scaler ----------------------------------------------

    def _prepare_batch(self, b: Batch) -> Batch:
        """Keep the batch's rewards and episode ends for the reward scaler (read after the step)."""
        self._pending = (b.rew, b.terminated, b.truncated)
        return b

    def _after_step(self, optimizers: list[torch.optim.Optimizer], guard: GuardedUpdate) -> None:
        """After the critics' step: their weight rows back onto the unit sphere (parameters the
        guard kept before the step, so a non-finite update decided on the device puts them back),
        then the reward scaler reads the batch (its buffers handed to the guard first)."""
        if not any(opt is self.q_optimizer for opt in optimizers):
            return
        for layer in self._hyper:
            layer.project_()
        pending, self._pending = self._pending, None
        if pending is not None:
            guard.keep(list(self.reward_scaler.buffers()))
            self.reward_scaler.update(*pending)

    def _checked_tensors(self) -> list[torch.Tensor]:
        """SAC's, plus the reward scaler's state."""
        return super()._checked_tensors() + list(self.reward_scaler.buffers())

    # --- checkpointing ------------------------------------------------------------------------

    def state_dict(self) -> dict[str, Any]:
        """:meth:`SACAgent.state_dict` plus the reward scaler's state (``reward_scaler``)."""
        state = super().state_dict()
        state["reward_scaler"] = self.reward_scaler.state_dict()
        return state

    def _load_extra_state(self, state: dict[str, Any]) -> None:
        self.reward_scaler.load_state_dict(state["reward_scaler"])
