"""MLP models for SAC and REDQ-SAC: a squashed Gaussian actor and ensembles of Q functions.

Observations are tuples (or any nested tuple/list/dict) of tensors with a leading batch
dimension; every element is flattened and the pieces are concatenated in order.

The critics of an actor-critic are one :class:`EnsembleQFunction`: the weights of all ``n``
Q networks are stacked, and one batched matrix product per layer evaluates them all, instead of
a Python loop over ``n`` separate networks. Critics kept as separate modules (DroQ's, TQC's,
CrossQ's, DrQ's heads, whose parameter names checkpoints hold) are evaluated the same way by
:class:`StackedCritics`: their weights stacked at each call, one batched product per layer.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Callable, Iterator, Mapping, Sequence
from typing import Any, cast

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
    "FlatInputCritic",
    "MLPActorCritic",
    "MLPQFunction",
    "QMember",
    "REDQMLPActorCritic",
    "SquashedGaussianMLPActor",
    "StackedCritics",
    "flatten_obs",
    "mlp",
    "space_dim",
    "split_image_obs",
    "stacked_mlp",
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


def split_image_obs(obs: Sequence[torch.Tensor], image_index: int) -> tuple[torch.Tensor, torch.Tensor]:
    """The frames of a batched image observation, as given, and its other elements flattened into
    one float32 ``(B, k)`` tensor (``k`` may be 0).

    Args:
        obs: the batched observation's elements.
        image_index: position of the frames among them.
    """
    imgs = obs[image_index]
    b = imgs.shape[0]
    rest = [o.reshape(b, -1).to(torch.float32) for i, o in enumerate(obs) if i != image_index]
    return imgs, torch.cat(rest, dim=-1) if rest else imgs.new_zeros((b, 0), dtype=torch.float32)


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
            # A subset drawn on the CPU (REDQ's) reaches the device without waiting for it.
            idx = torch.as_tensor(members, dtype=torch.long).to(weights[0].device, non_blocking=True)
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


# --- critics kept as separate modules, evaluated together ---------------------------------------

_ELEMENTWISE = (nn.ReLU, nn.Tanh, nn.ELU, nn.LeakyReLU, nn.SiLU, nn.GELU, nn.Sigmoid, nn.Softplus, nn.Mish,
                nn.Identity)
"""Parameter-free layers that act on each element alone: applied to the stacked activations as they are."""


def _layer_kind(layers: Sequence[nn.Module]) -> str | None:
    """How the layers at one position of ``k`` networks are evaluated together (None: they cannot be)."""
    first = layers[0]
    kind = type(first)
    if any(type(layer) is not kind for layer in layers):
        return None
    if kind is nn.Linear:
        with_bias = first.bias is not None
        same = all(layer.weight.shape == first.weight.shape and (layer.bias is not None) == with_bias
                   for layer in layers)
        return "linear" if same and with_bias else None
    if kind is nn.Dropout:
        return "dropout" if all(layer.p == first.p for layer in layers) else None
    if kind is nn.LayerNorm:
        same = all(layer.normalized_shape == first.normalized_shape and layer.eps == first.eps
                   and layer.weight is not None and layer.bias is not None for layer in layers)
        return "layernorm" if same and len(first.normalized_shape) == 1 else None
    if kind in _ELEMENTWISE:
        return "elementwise" if all(repr(layer) == repr(first) for layer in layers) else None
    stacked = getattr(kind, "stacked_forward", None)
    if callable(stacked) and getattr(kind, "stacks_with", lambda a, b: True)(first, layers):
        return "custom"
    return None


def stacked_plan(nets: Sequence[nn.Sequential]) -> list[str] | None:
    """The kind of each position of ``nets`` (``nn.Sequential`` networks of one architecture) for
    :func:`stacked_mlp`, or None when they cannot be evaluated together: different lengths or
    layers, or a layer other than ``Linear`` (with a bias), ``Dropout``, ``LayerNorm`` over the
    last axis (affine), an elementwise activation, or a layer class with a ``stacked_forward``
    classmethod (``tmrl.algorithms.crossq.BatchRenorm1d``)."""
    if not nets or any(not isinstance(net, nn.Sequential) or len(net) != len(nets[0]) for net in nets):
        return None
    kinds = [_layer_kind([net[j] for net in nets]) for j in range(len(nets[0]))]
    if any(kind is None for kind in kinds) or "linear" not in kinds:
        return None
    return cast(list[str], kinds)


def _dropout_masks(layers: list[list[nn.Module]], kinds: list[str], x: torch.Tensor) -> dict[int, torch.Tensor]:
    """The scaled dropout masks of every network, drawn in the order a loop over the networks
    draws them (network by network, layer by layer), each as ``F.dropout`` does on a CPU: a
    Bernoulli(1 - p) draw divided by 1 - p. Stacked per position: ``{j: (k, B, width)}``."""
    rows = x.shape[-2]
    width = x.shape[-1]
    widths: dict[int, int] = {}
    for j, kind in enumerate(kinds):
        if kind == "linear":
            width = cast(nn.Linear, layers[0][j]).out_features
        elif kind == "dropout":
            widths[j] = width
    if not widths:
        return {}
    drawn: dict[int, list[torch.Tensor | None]] = {j: [] for j in widths}
    for net in layers:
        for j, w in widths.items():
            layer = cast(nn.Dropout, net[j])
            p = float(layer.p)
            if not layer.training or p == 0.0:
                drawn[j].append(None)
            elif p == 1.0:
                drawn[j].append(x.new_zeros((rows, w)))
            else:
                drawn[j].append(x.new_empty((rows, w)).bernoulli_(1.0 - p).div_(1.0 - p))
    masks: dict[int, torch.Tensor] = {}
    for j, per_net in drawn.items():
        if all(m is None for m in per_net):
            continue
        ones = x.new_ones((rows, widths[j]))
        masks[j] = torch.stack([ones if m is None else m for m in per_net])
    return masks


def stacked_mlp(nets: Sequence[nn.Sequential], x: torch.Tensor, kinds: Sequence[str] | None = None,
                detach_params: bool = False) -> torch.Tensor:
    """``torch.stack([net(x) for net in nets])`` with one batched matrix product per layer.

    The weights of each layer are stacked at the call (gradients flow back to each network's own
    parameters, whose names and shapes stay those of separate modules). Dropout masks are drawn
    in the order of the loop (see :func:`_dropout_masks`), so that with the same generator state
    both draw the same masks; normalisation layers with running statistics update each network's
    own.

    Args:
        nets: ``k`` networks of one architecture (:func:`stacked_plan` accepts them).
        x: their input: ``(B, D)`` shared by every network, or ``(k, B, D)``.
        kinds: :func:`stacked_plan`'s result for ``nets`` (computed when None).
        detach_params: use the weights as constants (no gradient reaches them).

    Returns:
        ``(k, B, out)``.

    Raises:
        ValueError: the networks cannot be evaluated together.
    """
    kinds = list(kinds) if kinds is not None else stacked_plan(nets)
    if kinds is None:
        raise ValueError("these networks cannot be evaluated together (stacked_plan)")
    layers = [list(net) for net in nets]
    k = len(layers)
    masks = _dropout_masks(layers, kinds, x)
    # The input is shared by all networks: broadcast it instead of copying it k times.
    h = x.unsqueeze(0).expand(k, -1, -1) if x.dim() == 2 else x
    last_linear = max(j for j, kind in enumerate(kinds) if kind == "linear")
    for j, kind in enumerate(kinds):
        at = [net[j] for net in layers]
        if kind == "linear":
            w = torch.stack([cast(nn.Linear, layer).weight for layer in at])  # (k, out, in)
            b = torch.stack([cast(torch.Tensor, cast(nn.Linear, layer).bias) for layer in at]).unsqueeze(1)
            if detach_params:
                w, b = w.detach(), b.detach()
            scalar_out = (w.shape[1] == 1 and j == last_linear
                          and all(kd == "elementwise" and isinstance(layers[0][i], nn.Identity)
                                  for i, kd in enumerate(kinds[j + 1:], start=j + 1)))
            if scalar_out:
                h = _ScalarOutput.apply(h, w.transpose(1, 2), b).unsqueeze(-1)
            else:
                h = torch.baddbmm(b, h, w.transpose(1, 2))
        elif kind == "dropout":
            if j in masks:
                h = h * masks[j]
        elif kind == "layernorm":
            norm = cast(nn.LayerNorm, at[0])
            h = F.layer_norm(h, norm.normalized_shape, None, None, norm.eps)
            gamma = torch.stack([cast(torch.Tensor, cast(nn.LayerNorm, layer).weight) for layer in at]).unsqueeze(1)
            beta = torch.stack([cast(torch.Tensor, cast(nn.LayerNorm, layer).bias) for layer in at]).unsqueeze(1)
            if detach_params:
                gamma, beta = gamma.detach(), beta.detach()
            h = h * gamma + beta
        elif kind == "elementwise":
            h = at[0](h)
        else:
            h = type(at[0]).stacked_forward(at, h, detach_params)  # type: ignore[attr-defined]
    return h


class StackedCritics:
    """``k`` critics of one architecture, kept as separate modules, evaluated together by
    :func:`stacked_mlp`: ``Q(obs, act)`` of all of them in one batched product per layer.

    A critic takes part when it has ``net`` (an ``nn.Sequential`` that :func:`stacked_plan`
    accepts), ``critic_input(obs, act)`` (the ``(B, D)`` input of ``net``, the same for every
    critic) and ``squeeze_output`` (whether its forward drops the last axis): DroQ's, TQC's and
    CrossQ's critics, their lidar wrappers. Build it with :meth:`of`.

    Args:
        modules: the critics.
        kinds: :func:`stacked_plan` of their networks.
    """

    def __init__(self, modules: Sequence[nn.Module], kinds: list[str]) -> None:
        self.modules = list(modules)
        self.kinds = kinds
        self.squeeze = bool(getattr(modules[0], "squeeze_output", True))

    @classmethod
    def of(cls, modules: Sequence[nn.Module]) -> StackedCritics | None:
        """:class:`StackedCritics` of ``modules``, or None when they cannot be evaluated together
        (then evaluate them one by one)."""
        if not modules:
            return None
        first = modules[0]
        for m in modules:
            if (type(m) is not type(first) or not callable(getattr(m, "critic_input", None))
                    or not isinstance(getattr(m, "net", None), nn.Sequential)
                    or getattr(m, "input_key", None) != getattr(first, "input_key", None)
                    or getattr(m, "squeeze_output", True) != getattr(first, "squeeze_output", True)):
                return None
        kinds = stacked_plan([cast(nn.Sequential, m.net) for m in modules])
        return None if kinds is None else cls(modules, kinds)

    def __call__(self, obs: Any, act: torch.Tensor, members: Sequence[int] | torch.Tensor | None = None,
                 detach_params: bool = False) -> torch.Tensor:
        """Values ``(k, B)`` (``(k, B, out)`` for critics that keep their last axis) of the
        selected critics (all when ``members`` is None).

        Args:
            obs: a batched observation.
            act: actions ``(B, act_dim)``.
            members: indices of the critics to evaluate (all when None).
            detach_params: use the weights as constants (for the actor's loss).
        """
        mods = self.modules if members is None else [self.modules[int(i)] for i in members]
        x = mods[0].critic_input(obs, act)  # type: ignore[operator]
        out = stacked_mlp([cast(nn.Sequential, m.net) for m in mods], x, self.kinds, detach_params)
        return out.squeeze(-1) if self.squeeze else out


class FlatInputCritic:
    """What :class:`StackedCritics` reads of a critic whose ``net`` takes the observation then the
    action as one flat vector: :meth:`critic_input` and :attr:`squeeze_output`. Mixed into
    :class:`MLPQFunction` and the DroQ, TQC and CrossQ critics."""

    squeeze_output = True
    """Whether :meth:`forward` drops the output's last axis (a critic with several outputs per
    sample, TQC's quantiles, sets it False)."""

    def critic_input(self, obs: Any, act: torch.Tensor) -> torch.Tensor:
        """The input of the critic's network: the observation then the action, as one ``(B, D)``
        float32 tensor.

        Args:
            obs: a batched observation.
            act: actions ``(B, act_dim)``.
        """
        return flatten_obs((obs, act))


class MLPQFunction(FlatInputCritic, nn.Module):
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

    @property
    def net(self) -> nn.Sequential:
        """The network (``q``, tmrl 0.7's name), for :class:`StackedCritics`."""
        return self.q

    def forward(self, obs: Any, act: torch.Tensor) -> torch.Tensor:
        """Q values of shape ``(B,)``.

        Args:
            obs: a batched observation.
            act: actions ``(B, act_dim)``.
        """
        return self.q(self.critic_input(obs, act)).squeeze(-1)


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
