"""MLP models for SAC and REDQ-SAC: a squashed Gaussian actor and ensembles of Q functions.

Observations are tuples (or any nested tuple/list/dict) of tensors with a leading batch
dimension; every element is flattened and the pieces are concatenated in order.

The critics of an actor-critic are one :class:`EnsembleQFunction`: the weights of all ``n``
Q networks are stacked, and one batched matrix product per layer evaluates them all, instead of
a Python loop over ``n`` separate networks.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Callable, Iterator, Mapping, Sequence
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from tmrl.actor import TorchActorModule
from tmrl.errors import UserError

__all__ = [
    "LOG_STD_MAX",
    "LOG_STD_MIN",
    "EnsembleQFunction",
    "MLPActorCritic",
    "MLPQFunction",
    "QMember",
    "REDQMLPActorCritic",
    "SquashedGaussianMLPActor",
    "flatten_obs",
    "mlp",
    "space_dim",
]

LOG_STD_MIN = -20.0
LOG_STD_MAX = 2.0
_HALF_LOG_2PI = 0.5 * math.log(2.0 * math.pi)
_LOG_2 = math.log(2.0)


def mlp(
    sizes: Sequence[int],
    activation: Callable[[], nn.Module],
    output_activation: Callable[[], nn.Module] = nn.Identity,
) -> nn.Sequential:
    """A stack of ``nn.Linear`` layers of the given sizes, ``activation`` between them and
    ``output_activation`` after the last one."""
    layers: list[nn.Module] = []
    for j in range(len(sizes) - 1):
        layers.append(nn.Linear(sizes[j], sizes[j + 1]))
        layers.append(activation() if j < len(sizes) - 2 else output_activation())
    return nn.Sequential(*layers)


def space_dim(space: Any) -> int:
    """Number of scalars in one observation of ``space`` once flattened.

    ``Tuple`` and ``Dict`` spaces are summed over their elements; any other space counts the
    product of its shape.

    Raises:
        UserError: the space has no shape (for example a Text space).
    """
    if isinstance(space, Mapping) or hasattr(space, "spaces"):
        subspaces = space.spaces if hasattr(space, "spaces") else space
        values = subspaces.values() if isinstance(subspaces, Mapping) else subspaces
        return sum(space_dim(s) for s in values)
    if isinstance(space, (tuple, list)):
        return sum(space_dim(s) for s in space)
    shape = getattr(space, "shape", None)
    if shape is None:
        raise UserError(
            f"observation space {space!r} has no shape: MLP models need Box-like spaces "
            "(or Tuple/Dict of them); write an obs_preprocessor or a custom model"
        )
    return int(np.prod(shape, dtype=np.int64))


def flatten_obs(obs: Any) -> torch.Tensor:
    """Flatten a batched observation to a float32 tensor of shape ``(B, D)``.

    Args:
        obs: a tensor with a leading batch dimension, or a nested tuple/list/dict of them (dict
            values are taken in the dict's order).
    """
    if isinstance(obs, torch.Tensor):
        return obs.reshape(obs.shape[0], -1).to(torch.float32)
    parts: list[torch.Tensor] = []
    _collect(obs, parts)
    return parts[0] if len(parts) == 1 else torch.cat(parts, dim=-1)


def _collect(obs: Any, out: list[torch.Tensor]) -> None:
    if isinstance(obs, torch.Tensor):
        out.append(obs.reshape(obs.shape[0], -1).to(torch.float32))
    elif isinstance(obs, Mapping):
        for value in obs.values():
            _collect(value, out)
    else:
        for value in obs:
            _collect(value, out)


def _action_bounds(action_space: Any) -> tuple[np.ndarray, np.ndarray]:
    low = np.asarray(action_space.low, dtype=np.float32).reshape(-1)
    high = np.asarray(action_space.high, dtype=np.float32).reshape(-1)
    if not (np.all(np.isfinite(low)) and np.all(np.isfinite(high))):
        raise UserError(
            f"action space {action_space} is unbounded: squashed Gaussian actors need finite low/high "
            "(rescale actions in the environment or a wrapper)"
        )
    return low, high


def squashed_gaussian(mu: torch.Tensor, log_std: torch.Tensor, act_scale: torch.Tensor, act_offset: torch.Tensor,
                      test: bool = False, with_logprob: bool = True) -> tuple[torch.Tensor, torch.Tensor | None]:
    """SAC's squashed Gaussian policy from its head's outputs: ``(action, log pi or None)``.

    Args:
        mu: the Gaussian's mean ``(B, act_dim)``.
        log_std: its log standard deviation before clamping to ``[LOG_STD_MIN, LOG_STD_MAX]``.
        act_scale: half the width of the action space's bounds (``tanh``'s ``(-1, 1)`` scaled).
        act_offset: the middle of the bounds.
        test: the mean instead of a sample (one ``torch.randn_like(mu)`` draw otherwise).
        with_logprob: also return the log-density ``(B,)`` of the action.
    """
    log_std = torch.clamp(log_std, LOG_STD_MIN, LOG_STD_MAX)
    if test:
        u = mu
        eps = None
    else:
        eps = torch.randn_like(mu)
        u = mu + log_std.exp() * eps  # reparameterised sample
    logp = None
    if with_logprob:
        # Gaussian log-density at u: (u - mu) / std is exactly eps, no need to recompute it.
        sq = 0.0 if eps is None else 0.5 * eps.square()
        logp = (-(sq + log_std) - _HALF_LOG_2PI).sum(-1)
        # tanh change of variables, log(1 - tanh(u)^2) in a stable form (SAC paper, app. C);
        # the constant log(scale) term is left out, as in the original implementation.
        logp = logp - (2.0 * (_LOG_2 - u - F.softplus(-2.0 * u))).sum(-1)
    return torch.tanh(u) * act_scale + act_offset, logp


def _compute_dtype(value: str | torch.dtype | None) -> torch.dtype | None:
    if value is None or value in ("float32", torch.float32):
        return None
    if value in ("bfloat16", torch.bfloat16):
        return torch.bfloat16
    raise UserError(f"compute_dtype={value!r} is not supported: use None (float32) or 'bfloat16'")


class SquashedGaussianMLPActor(TorchActorModule):
    """SAC's policy: an MLP outputs the mean and log-std of a Gaussian, a sample is squashed
    by ``tanh`` and scaled to the action space's bounds.

    Args:
        observation_space: the observation space (Box, or Tuple/Dict of Boxes).
        action_space: a bounded Box; actions are mapped to ``[low, high]`` per dimension.
        hidden_sizes: widths of the hidden layers.
        activation: activation class applied after every hidden layer.
        device: where :meth:`act_` collates observations.
    """

    act_scale: torch.Tensor
    act_offset: torch.Tensor

    def __init__(
        self,
        observation_space: Any,
        action_space: Any,
        hidden_sizes: Sequence[int] = (256, 256),
        activation: Callable[[], nn.Module] = nn.ReLU,
        device: Any = "cpu",
    ) -> None:
        super().__init__(observation_space, action_space, device=device)
        dim_obs = space_dim(observation_space)
        dim_act = int(np.prod(action_space.shape))
        self.net = mlp([dim_obs, *hidden_sizes], activation, activation)
        self.mu_layer = nn.Linear(hidden_sizes[-1], dim_act)
        self.log_std_layer = nn.Linear(hidden_sizes[-1], dim_act)
        low, high = _action_bounds(action_space)
        # Not persistent: the bounds come from the action space, not from the weights file.
        self.register_buffer("act_scale", torch.from_numpy((high - low) / 2.0), persistent=False)
        self.register_buffer("act_offset", torch.from_numpy((high + low) / 2.0), persistent=False)
        self.act_limit = float(high[0])  # the original's scalar bound, kept for compatibility

    def forward(
        self, obs: Any, test: bool = False, with_logprob: bool = True
    ) -> tuple[torch.Tensor, torch.Tensor | None]:
        """Sample (or, with ``test``, take the mean of) the squashed Gaussian policy.

        Args:
            obs: a batched observation.
            test: use the Gaussian's mean instead of a sample.
            with_logprob: also return the log-density of the returned (squashed) action.

        Returns:
            ``(action, logp)``: actions ``(B, act_dim)`` within the bounds, and log-densities
            ``(B,)`` (or None).
        """
        h = self.net(flatten_obs(obs))
        return squashed_gaussian(self.mu_layer(h), self.log_std_layer(h), self.act_scale, self.act_offset,
                                 test, with_logprob)

    def act(self, obs: Any, test: bool = False) -> np.ndarray:
        """Action for a batched observation, as a NumPy array, without gradients.

        Args:
            obs: a batched observation (tensors with a leading batch dimension).
            test: take the Gaussian's mean (deterministic) instead of a sample.

        Returns:
            ``(B, act_dim)`` actions, or ``(act_dim,)`` for a batch of one.
        """
        with torch.no_grad():
            a, _ = self.forward(obs, test, False)
        if a.shape[0] == 1:
            a = a[0]
        return a.cpu().numpy()


class EnsembleQFunction(nn.Module):
    """``n`` MLP Q functions ``Q_i(obs, act)`` with stacked weights, evaluated together.

    Layer ``l`` holds ``weights[l]`` of shape ``(n, in, out)`` and ``biases[l]`` of shape
    ``(n, 1, out)``; each member is initialised like ``nn.Linear``.

    Args:
        observation_space: the observation space.
        action_space: the action space (a Box).
        hidden_sizes: widths of the hidden layers.
        activation: activation class applied after every hidden layer (elementwise).
        n: number of Q functions.
        compute_dtype: None (float32 throughout) or ``"bfloat16"``: the hidden layers' matrix
            products run in bfloat16 (float32 accumulation, float32 weights and optimizer state,
            float32 output layer). Several times faster on CPUs with AVX512-BF16 or AMX and on
            recent GPUs, at the cost of about 3 significant digits in hidden activations.
    """

    def __init__(
        self,
        observation_space: Any,
        action_space: Any,
        hidden_sizes: Sequence[int] = (256, 256),
        activation: Callable[[], nn.Module] = nn.ReLU,
        n: int = 2,
        compute_dtype: str | torch.dtype | None = None,
    ) -> None:
        super().__init__()
        if n < 1:
            raise UserError(f"an ensemble needs at least one Q function, got n={n}: set n >= 1")
        self.n = int(n)
        self.compute_dtype = _compute_dtype(compute_dtype)
        sizes = [space_dim(observation_space) + int(np.prod(action_space.shape)), *hidden_sizes, 1]
        self.weights = nn.ParameterList()
        self.biases = nn.ParameterList()
        for fan_in, fan_out in itertools.pairwise(sizes):
            bound = 1.0 / math.sqrt(fan_in)
            self.weights.append(nn.Parameter(torch.empty(self.n, fan_in, fan_out).uniform_(-bound, bound)))
            self.biases.append(nn.Parameter(torch.empty(self.n, 1, fan_out).uniform_(-bound, bound)))
        self.activation = activation()

    def forward(
        self,
        obs: Any,
        act: torch.Tensor,
        members: torch.Tensor | Sequence[int] | None = None,
        detach_params: bool = False,
    ) -> torch.Tensor:
        """Evaluate the Q functions on one batch.

        Args:
            obs: a batched observation (B rows).
            act: actions ``(B, act_dim)``.
            members: indices of the Q functions to evaluate (all when None).
            detach_params: use the weights as constants: gradients still flow to ``obs`` and
                ``act`` but not to the parameters (for the actor's loss).

        Returns:
            Q values of shape ``(k, B)``, ``k`` = number of members evaluated.
        """
        x = flatten_obs((obs, act))  # the observation then the action, as one (B, D) float32 input
        weights: list[torch.Tensor] = list(self.weights)
        biases: list[torch.Tensor] = list(self.biases)
        if members is not None:
            idx = torch.as_tensor(members, dtype=torch.long, device=weights[0].device)
            weights = [w.index_select(0, idx) for w in weights]
            biases = [b.index_select(0, idx) for b in biases]
        if detach_params:
            weights = [w.detach() for w in weights]
            biases = [b.detach() for b in biases]
        k = weights[0].shape[0]
        low = self.compute_dtype
        if low is not None:
            # Hidden layers in low precision; the output layer (256 -> 1) stays float32.
            x = x.to(low)
            weights = [w.to(low) for w in weights[:-1]] + weights[-1:]
            biases = [b.to(low) for b in biases[:-1]] + biases[-1:]
        # The input is shared by all members: broadcast it instead of copying it k times.
        h = torch.baddbmm(biases[0], x.unsqueeze(0).expand(k, -1, -1), weights[0])
        # A plain ReLU overwrites each layer's output (baddbmm's backward needs its inputs only):
        # one pass less over (k, B, width) activations, which outgrow the L2 cache for REDQ.
        relu_inplace = type(self.activation) is nn.ReLU
        last = len(weights) - 1
        for i, (w, b) in enumerate(zip(weights[1:], biases[1:]), start=1):
            h = torch.relu_(h) if relu_inplace else self.activation(h)
            if h.dtype != w.dtype:
                h = h.to(w.dtype)
            if i == last:
                return _ScalarOutput.apply(h, w, b)
            h = torch.baddbmm(b, h, w)
        return h.squeeze(-1)  # no hidden layer: the input layer is the output layer

    def __len__(self) -> int:
        return self.n

    def __getitem__(self, i: int) -> QMember:
        if not -self.n <= i < self.n:
            raise IndexError(f"Q function {i} out of range for an ensemble of {self.n}")
        return QMember(self, i % self.n)

    def __iter__(self) -> Iterator[QMember]:  # type: ignore[override]
        return (QMember(self, i) for i in range(self.n))


class _ScalarOutput(torch.autograd.Function):
    """The output layer of an ensemble: ``q[k, b] = h[k, b, :] . w[k, :, 0] + bias[k]``.

    The same numbers as ``baddbmm(bias, h, w).squeeze(-1)``, computed with vector operations:
    a batched matrix product with a single output column is a slow case for CPU BLAS (about
    0.42 ms forward and 1 ms backward for 10 critics at batch 256, against 0.08 and 0.08 ms).
    """

    @staticmethod
    def forward(ctx: Any, h: torch.Tensor, w: torch.Tensor, bias: torch.Tensor) -> torch.Tensor:
        ctx.save_for_backward(h, w)
        return torch.linalg.vecdot(h, w.transpose(1, 2)) + bias.reshape(-1, 1)

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx: Any, grad: torch.Tensor) -> tuple[torch.Tensor | None, ...]:
        h, w = ctx.saved_tensors
        grad_h = grad_w = grad_bias = None
        if ctx.needs_input_grad[0]:
            grad_h = grad.unsqueeze(-1) * w.transpose(1, 2)
        if ctx.needs_input_grad[1]:
            grad_w = torch.bmm(grad.unsqueeze(1), h).transpose(1, 2)
        if ctx.needs_input_grad[2]:
            grad_bias = grad.sum(1).reshape(-1, 1, 1)
        return grad_h, grad_w, grad_bias


class QMember:
    """One Q function of an ensemble, callable as ``q(obs, act) -> (B,)`` (like the original
    tmrl's separate critics ``q1``, ``q2``, ``qs[i]``). It holds no parameters of its own: train
    the ensemble's parameters.

    Args:
        ensemble: the :class:`EnsembleQFunction` it is a view of.
        index: which of the ensemble's ``n`` Q functions, from 0.
    """

    def __init__(self, ensemble: EnsembleQFunction, index: int) -> None:
        self.ensemble = ensemble
        self.index = index

    def __call__(self, obs: Any, act: torch.Tensor) -> torch.Tensor:
        """Q values of shape ``(B,)``.

        Args:
            obs: a batched observation.
            act: actions ``(B, act_dim)``.
        """
        return self.ensemble(obs, act, members=[self.index])[0]

    forward = __call__


class MLPQFunction(nn.Module):
    """One MLP Q function ``Q(obs, act) -> (B,)``, for models composed by hand (tmrl 0.7's
    ``MLPQFunction``; the built-in actor-critics use :class:`EnsembleQFunction` instead).

    Args:
        observation_space: the observation space.
        action_space: the action space (a Box).
        hidden_sizes: widths of the hidden layers.
        activation: activation class.
    """

    def __init__(self, observation_space: Any, action_space: Any, hidden_sizes: Sequence[int] = (256, 256),
                 activation: Callable[[], nn.Module] = nn.ReLU) -> None:
        super().__init__()
        dim_in = space_dim(observation_space) + int(np.prod(action_space.shape))
        self.q = mlp([dim_in, *hidden_sizes, 1], activation)

    def forward(self, obs: Any, act: torch.Tensor) -> torch.Tensor:
        """Q values of shape ``(B,)``.

        Args:
            obs: a batched observation.
            act: actions ``(B, act_dim)``.
        """
        x = flatten_obs((obs, act))  # the observation then the action, as one (B, D) float32 input
        return self.q(x).squeeze(-1)


class MLPActorCritic(nn.Module):
    """SAC's actor-critic: a :class:`SquashedGaussianMLPActor` (``.actor``) and twin Q
    functions as one :class:`EnsembleQFunction` (``.qs``, members also reachable as ``.q1`` and
    ``.q2``).

    Args:
        observation_space: the observation space.
        action_space: the action space (a bounded Box).
        hidden_sizes: widths of the hidden layers of the actor and of each critic.
        activation: activation class.
        n: number of critics (2 for SAC).
        critic_dtype: the critics' ``compute_dtype`` (None: float32; ``"bfloat16"``: see
            :class:`EnsembleQFunction`).
    """

    def __init__(
        self,
        observation_space: Any,
        action_space: Any,
        hidden_sizes: Sequence[int] = (256, 256),
        activation: Callable[[], nn.Module] = nn.ReLU,
        n: int = 2,
        critic_dtype: str | torch.dtype | None = None,
    ) -> None:
        super().__init__()
        self.actor = SquashedGaussianMLPActor(observation_space, action_space, hidden_sizes, activation)
        self.qs = EnsembleQFunction(
            observation_space, action_space, hidden_sizes, activation, n=n, compute_dtype=critic_dtype
        )

    @property
    def n(self) -> int:
        """Number of Q functions."""
        return self.qs.n

    @property
    def q1(self) -> QMember:
        """The first Q function (a view into ``qs``)."""
        return self.qs[0]

    @property
    def q2(self) -> QMember:
        """The second Q function (a view into ``qs``)."""
        return self.qs[1]

    def act(self, obs: Any, test: bool = False) -> np.ndarray:
        """The actor's action for a batched observation, as a NumPy array (see
        :meth:`SquashedGaussianMLPActor.act`).

        Args:
            obs: a batched observation.
            test: take the mean action instead of a sample.
        """
        return self.actor.act(obs, test)


class REDQMLPActorCritic(MLPActorCritic):
    """REDQ-SAC's actor-critic: like :class:`MLPActorCritic` with ``n`` critics (default 10).

    Args:
        observation_space: the observation space.
        action_space: the action space (a bounded Box).
        hidden_sizes: widths of the hidden layers.
        activation: activation class.
        n: number of critics.
        critic_dtype: as in :class:`MLPActorCritic`.
    """

    def __init__(
        self,
        observation_space: Any,
        action_space: Any,
        hidden_sizes: Sequence[int] = (256, 256),
        activation: Callable[[], nn.Module] = nn.ReLU,
        n: int = 10,
        critic_dtype: str | torch.dtype | None = None,
    ) -> None:
        super().__init__(
            observation_space, action_space, hidden_sizes, activation, n=n, critic_dtype=critic_dtype
        )
