"""Models for driving observations: the CNN actor-critic for image histories, and the MLP wiring
for lidar observations.

Full observations (after :func:`tmrl.driving.preprocessors.preprocess_full_obs`) are
``(speed, gear, rpm, images (hist, h, w), *act_buf)``. A convolution stack reads the image
history (the history is the channel dimension), its flattened features are concatenated with the
other elements (scalars and the action buffer, and the action for a critic), and an MLP finishes.
The layer sizes default to tmrl 0.7's ``VanillaCNN`` (channels 64, 64, 128, 128, kernels 8, 4, 4,
4, strides 2, MLP 256-256) but are arguments, and the input size comes from the observation space
(``IMG_HIST_LEN``, ``IMG_HEIGHT``, ``IMG_WIDTH``), where the original hard-codes them.

Lidar observations are flat vectors once preprocessed. :class:`LidarActorCritic` is tmrl's MLP
actor-critic with one change: speed (km/h) and lidar distances (pixels) are multiplied by 0.01
inside the networks, so that every input is of order one (raw lidar values reach 400, which slows
SAC down several times over on the simulator). Observations, samples and memories keep the
original units. The other algorithms' lidar models (:data:`LIDAR_MODELS`: DroQ, TQC, CrossQ) are
their MLP actor-critics with the same scaling: :class:`LidarActor` as the actor, each critic
wrapped in a :class:`ScaledCritic`.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np
import torch
from torch import nn

from tmrl.actor import TorchActorModule
from tmrl.algorithms.bro import BROActorCritic
from tmrl.algorithms.crossq import CrossQActorCritic
from tmrl.algorithms.droq import DroQMLPActorCritic
from tmrl.algorithms.simbav2 import SimbaV2ActorCritic
from tmrl.algorithms.tqc import TQCActorCritic
from tmrl.errors import UserError
from tmrl.models import (
    EnsembleQFunction,
    MLPActorCritic,
    SquashedGaussianMLPActor,
    mlp,
    space_dim,
    split_image_obs,
    squashed_gaussian,
)

__all__ = [
    "DEFAULT_CNN",
    "LIDAR_MODELS",
    "CNNActorCritic",
    "CNNQFunction",
    "ImageEncoder",
    "LidarActor",
    "LidarActorCritic",
    "LidarCrossQActorCritic",
    "LidarDroQActorCritic",
    "LidarQFunctions",
    "LidarSimbaV2ActorCritic",
    "LidarTQCActorCritic",
    "LidarBROActorCritic",
    "REDQCNNActorCritic",
    "ScaledCritic",
    "SquashedGaussianCNNActor",
    "VanillaCNN",
    "conv2d_out_dims",
    "lidar_actor_critic",
    "lidar_model_cls",
    "lidar_obs_scales",
    "num_flat_features",
]

DEFAULT_CNN: dict[str, tuple[int, ...]] = {
    "channels": (64, 64, 128, 128),
    "kernels": (8, 4, 4, 4),
    "strides": (2, 2, 2, 2),
    "hidden_sizes": (256, 256),
}
"""tmrl 0.7's VanillaCNN sizes."""



def _split_space(observation_space: Any, image_index: int) -> tuple[tuple[int, ...], int]:
    """Image shape ``(hist, h, w)`` and the number of other scalars in the observation."""
    elements = list(getattr(observation_space, "spaces", ()))
    if not elements or not 0 <= image_index < len(elements):
        raise UserError(
            f"the CNN model needs a Tuple observation space with images at position {image_index}, "
            f"got {observation_space}: use the full (image) interface or an MLP model"
        )
    shape = tuple(int(s) for s in elements[image_index].shape)
    if len(shape) != 3:
        raise UserError(
            f"the CNN model reads grayscale image histories of shape (hist, height, width), got {shape}: "
            "set ENV.IMG_GRAYSCALE to true"
        )
    others = sum(space_dim(s) for i, s in enumerate(elements) if i != image_index)
    return shape, others


def _split_obs(obs: Sequence[torch.Tensor], image_index: int) -> tuple[torch.Tensor, torch.Tensor]:
    imgs, scalars = split_image_obs(obs, image_index)
    if imgs.dtype == torch.uint8:  # raw frames: apply the preprocessor's scaling
        imgs = imgs.to(torch.float32) / 256.0
    return imgs.to(torch.float32), scalars


class ImageEncoder(nn.Module):
    """Convolutions over an image history (the history is the channel dimension), each followed
    by a ReLU, flattened. No padding: each layer maps a side ``s`` to ``(s - kernel) // stride + 1``.

    Args:
        image_shape: ``(hist, height, width)`` of the images it reads.
        channels: output channels of each convolution layer.
        kernels: square kernel size of each layer (same length as ``channels``).
        strides: stride of each layer (same length as ``channels``).

    Attributes:
        out_dim: the number of features per image history (``forward``'s second dimension).

    Raises:
        UserError: lists of different lengths, or images too small for the layers.
    """

    def __init__(self, image_shape: tuple[int, int, int], channels: Sequence[int] = DEFAULT_CNN["channels"],
                 kernels: Sequence[int] = DEFAULT_CNN["kernels"], strides: Sequence[int] = DEFAULT_CNN["strides"]) -> None:
        super().__init__()
        if not len(channels) == len(kernels) == len(strides) >= 1:
            raise UserError("CNN channels, kernels and strides must be lists of the same length (>= 1)")
        hist, h, w = image_shape
        layers: list[nn.Module] = []
        in_ch = hist
        for out_ch, k, s in zip(channels, kernels, strides):
            h, w = (h - k) // s + 1, (w - k) // s + 1
            if h < 1 or w < 1:
                raise UserError(
                    f"images of {image_shape[1]}x{image_shape[2]} are too small for the CNN layers "
                    f"(kernels {list(kernels)}, strides {list(strides)}): use larger images or fewer layers"
                )
            # In-place ReLU: a convolution's backward needs its input, not its output, so the
            # activation can overwrite the output instead of allocating another tensor that size.
            layers += [nn.Conv2d(in_ch, int(out_ch), int(k), stride=int(s)), nn.ReLU(inplace=True)]
            in_ch = int(out_ch)
        self.convs = nn.Sequential(*layers)
        self.out_dim = in_ch * h * w

    CHANNELS_LAST_FROM = 16
    """Batches at least this large run channels-last (NHWC): oneDNN's convolutions are then about
    1.5x faster forward and 1.7x forward plus backward on CPU; below it (a worker's batch of
    one) the default layout is faster. The weights keep the default layout either way."""

    def forward(self, imgs: torch.Tensor) -> torch.Tensor:
        """The features of a batch of image histories.

        Args:
            imgs: float images of shape ``(B, hist, height, width)``.

        Returns:
            Features of shape ``(B, out_dim)``.
        """
        if imgs.shape[0] >= self.CHANNELS_LAST_FROM:
            imgs = imgs.contiguous(memory_format=torch.channels_last)
        # With NHWC strides, flatten copies into the NCHW order of the features.
        return self.convs(imgs).flatten(1)


class SquashedGaussianCNNActor(TorchActorModule):
    """SAC's squashed Gaussian policy on image-history observations.

    Args:
        observation_space: Tuple space with the image history at ``image_index``.
        action_space: bounded Box.
        channels: output channels of each convolution layer (see :data:`DEFAULT_CNN`).
        kernels: kernel size of each convolution layer.
        strides: stride of each convolution layer.
        hidden_sizes: widths of the MLP after the convolutions.
        image_index: position of the images in the observation (3 for the full interfaces).
        device: where :meth:`act_` collates observations.

    Raises:
        UserError: the observation has no image history of shape ``(hist, h, w)`` at
            ``image_index``, or the images are too small for the layers.
    """

    def __init__(self, observation_space: Any, action_space: Any, channels: Sequence[int] = DEFAULT_CNN["channels"],
                 kernels: Sequence[int] = DEFAULT_CNN["kernels"], strides: Sequence[int] = DEFAULT_CNN["strides"],
                 hidden_sizes: Sequence[int] = DEFAULT_CNN["hidden_sizes"], image_index: int = 3,
                 device: Any = "cpu") -> None:
        super().__init__(observation_space, action_space, device=device)
        shape, others = _split_space(observation_space, image_index)
        self.image_index = image_index
        self.encoder = ImageEncoder(shape, channels, kernels, strides)
        dim_act = int(np.prod(action_space.shape))
        # As tmrl 0.7's VanillaCNN trunk: ReLU between the hidden layers, none after the last one.
        self.net = mlp([self.encoder.out_dim + others, *hidden_sizes], nn.ReLU)
        self.mu_layer = nn.Linear(hidden_sizes[-1], dim_act)
        self.log_std_layer = nn.Linear(hidden_sizes[-1], dim_act)
        low = np.asarray(action_space.low, dtype=np.float32).reshape(-1)
        high = np.asarray(action_space.high, dtype=np.float32).reshape(-1)
        self.register_buffer("act_scale", torch.from_numpy((high - low) / 2.0), persistent=False)
        self.register_buffer("act_offset", torch.from_numpy((high + low) / 2.0), persistent=False)

    def forward(self, obs: Any, test: bool = False, with_logprob: bool = True) -> tuple[torch.Tensor, torch.Tensor | None]:
        """Sample (or, with ``test``, take the mean of) the squashed Gaussian policy.

        Args:
            obs: a batched observation; ``uint8`` images are scaled by 1/256 here.
            test: use the Gaussian's mean instead of a sample.
            with_logprob: also return the log-density of the returned action.

        Returns:
            ``(action, logp)``: actions ``(B, act_dim)`` within the action space's bounds, and
            log-densities ``(B,)`` (or None).
        """
        imgs, scalars = _split_obs(obs, self.image_index)
        h = self.net(torch.cat((self.encoder(imgs), scalars), dim=-1))
        return squashed_gaussian(self.mu_layer(h), self.log_std_layer(h), self.act_scale, self.act_offset,
                                 test, with_logprob)

    def act(self, obs: Any, test: bool = False) -> np.ndarray:
        """Action for a batched observation as a NumPy array, without gradients.

        Args:
            obs: a batched observation.
            test: take the mean action instead of a sample.

        Returns:
            ``(B, act_dim)`` actions, or ``(act_dim,)`` for a batch of one.
        """
        with torch.no_grad():
            a, _ = self.forward(obs, test, False)
        return (a[0] if a.shape[0] == 1 else a).cpu().numpy()


class CNNQFunction(nn.Module):
    """``Q(obs, act)`` on image-history observations: its own convolutions, then an MLP over the
    features, the other observation elements and the action.

    Args:
        observation_space: Tuple space with the image history at ``image_index``.
        action_space: the action space (a Box).
        channels: output channels of each convolution layer (see :data:`DEFAULT_CNN`).
        kernels: kernel size of each convolution layer.
        strides: stride of each convolution layer.
        hidden_sizes: widths of the MLP's hidden layers (its output is one value).
        image_index: position of the images in the observation.
    """

    def __init__(self, observation_space: Any, action_space: Any, channels: Sequence[int] = DEFAULT_CNN["channels"],
                 kernels: Sequence[int] = DEFAULT_CNN["kernels"], strides: Sequence[int] = DEFAULT_CNN["strides"],
                 hidden_sizes: Sequence[int] = DEFAULT_CNN["hidden_sizes"], image_index: int = 3) -> None:
        super().__init__()
        shape, others = _split_space(observation_space, image_index)
        self.image_index = image_index
        self.encoder = ImageEncoder(shape, channels, kernels, strides)
        dim_act = int(np.prod(action_space.shape))
        self.net = mlp([self.encoder.out_dim + others + dim_act, *hidden_sizes, 1], nn.ReLU)

    def features(self, obs: Any) -> torch.Tensor:
        """The convolution features of the images and the other observation elements, ``(B, F)``.

        Args:
            obs: a batched observation.
        """
        imgs, scalars = _split_obs(obs, self.image_index)
        return torch.cat((self.encoder(imgs), scalars), dim=-1)

    def head(self, features: torch.Tensor, act: torch.Tensor) -> torch.Tensor:
        """Q values ``(B,)`` from :meth:`features` and actions (SAC uses the split to read the
        images once for ``Q(o, a)`` and ``Q(o, pi)``).

        Args:
            features: the output of :meth:`features`, ``(B, F)``.
            act: actions ``(B, act_dim)``.
        """
        x = torch.cat((features, act.reshape(act.shape[0], -1).to(torch.float32)), dim=-1)
        return self.net(x).squeeze(-1)

    def forward(self, obs: Any, act: torch.Tensor) -> torch.Tensor:
        """Q values of shape ``(B,)``.

        Args:
            obs: a batched observation.
            act: actions ``(B, act_dim)``.
        """
        return self.head(self.features(obs), act)


class CNNActorCritic(nn.Module):
    """SAC's actor-critic for image histories: ``.actor`` and ``n`` critics in ``.qs`` (also
    ``.q1``, ``.q2``), each with its own convolutions, as in tmrl 0.7.

    Args:
        observation_space: the (preprocessed) observation space, images at ``image_index``.
        action_space: the action space (a bounded Box).
        channels: output channels of each convolution layer (see :data:`DEFAULT_CNN`).
        kernels: kernel size of each convolution layer.
        strides: stride of each convolution layer.
        hidden_sizes: widths of the MLP of the actor and of each critic.
        n: number of critics (2 for SAC).
        image_index: position of the images in the observation.

    Raises:
        UserError: ``n`` < 1, or an observation space the CNN cannot read.
    """

    def __init__(self, observation_space: Any, action_space: Any, channels: Sequence[int] = DEFAULT_CNN["channels"],
                 kernels: Sequence[int] = DEFAULT_CNN["kernels"], strides: Sequence[int] = DEFAULT_CNN["strides"],
                 hidden_sizes: Sequence[int] = DEFAULT_CNN["hidden_sizes"], n: int = 2, image_index: int = 3) -> None:
        super().__init__()
        if int(n) < 1:
            raise UserError(f"an actor-critic needs at least one critic, got n={n}")
        sizes = {"channels": channels, "kernels": kernels, "strides": strides, "hidden_sizes": hidden_sizes,
                 "image_index": image_index}
        self.actor = SquashedGaussianCNNActor(observation_space, action_space, **sizes)
        self.qs = nn.ModuleList(CNNQFunction(observation_space, action_space, **sizes) for _ in range(int(n)))

    @property
    def q1(self) -> CNNQFunction:
        """The first critic."""
        return self.qs[0]  # type: ignore[return-value]

    @property
    def q2(self) -> CNNQFunction:
        """The second critic."""
        return self.qs[1]  # type: ignore[return-value]

    def act(self, obs: Any, test: bool = False) -> np.ndarray:
        """The actor's action for a batched observation, as a NumPy array.

        Args:
            obs: a batched observation.
            test: take the mean action instead of a sample.
        """
        return self.actor.act(obs, test)


class REDQCNNActorCritic(CNNActorCritic):
    """:class:`CNNActorCritic` with 10 critics by default, for REDQ-SAC.

    Args:
        observation_space: see :class:`CNNActorCritic`.
        action_space: see :class:`CNNActorCritic`.
        n: number of critics.
        **kwargs: the layer sizes and ``image_index`` of :class:`CNNActorCritic`.
    """

    def __init__(self, observation_space: Any, action_space: Any, n: int = 10, **kwargs: Any) -> None:
        super().__init__(observation_space, action_space, n=n, **kwargs)


def conv2d_out_dims(conv_layer: nn.Conv2d, h_in: int, w_in: int) -> tuple[int, int]:
    """Height and width of a convolution's output (tmrl 0.7's helper).

    Args:
        conv_layer: the layer; its padding, dilation, kernel size and stride are read.
        h_in: input height.
        w_in: input width.

    Raises:
        UserError: the layer's padding is a string (``"same"``), not numbers.
    """
    pad, dil, ker, stride = (tuple(getattr(conv_layer, a)) for a in ("padding", "dilation", "kernel_size", "stride"))
    if not all(isinstance(p, int) for p in pad):
        raise UserError(f"conv2d_out_dims needs numeric padding, got {conv_layer.padding!r}")
    h_out = (h_in + 2 * pad[0] - dil[0] * (ker[0] - 1) - 1) // stride[0] + 1
    w_out = (w_in + 2 * pad[1] - dil[1] * (ker[1] - 1) - 1) // stride[1] + 1
    return h_out, w_out


def num_flat_features(x: torch.Tensor) -> int:
    """Values per sample of a batched tensor (the product of all dimensions but the first).

    Args:
        x: a tensor whose first dimension is the batch.
    """
    return int(math.prod(x.shape[1:]))


class VanillaCNN(nn.Module):
    """tmrl 0.7's ``VanillaCNN`` network for full observations: the image history through an
    :class:`ImageEncoder`, then an MLP over ``(speed, gear, rpm, image features, *previous
    actions[, action])``, concatenated in that order.

    Args:
        q_net: a critic (the action is an input too, one output) or an actor's trunk (outputs
            ``hidden_sizes[-1]`` features).
        image_shape: ``(hist, height, width)`` of the image history.
        act_dim: size of an action.
        act_buf_len: previous actions in the observation.
        channels: output channels of each convolution layer (see :data:`DEFAULT_CNN`).
        kernels: kernel size of each convolution layer.
        strides: stride of each convolution layer.
        hidden_sizes: widths of the MLP's hidden layers.
    """

    def __init__(self, q_net: bool, image_shape: tuple[int, int, int] = (4, 64, 64), act_dim: int = 3,
                 act_buf_len: int = 2, channels: Sequence[int] = DEFAULT_CNN["channels"],
                 kernels: Sequence[int] = DEFAULT_CNN["kernels"], strides: Sequence[int] = DEFAULT_CNN["strides"],
                 hidden_sizes: Sequence[int] = DEFAULT_CNN["hidden_sizes"]) -> None:
        super().__init__()
        self.q_net = bool(q_net)
        self.encoder = ImageEncoder(image_shape, channels, kernels, strides)
        n_in = self.encoder.out_dim + 3 + act_dim * (act_buf_len + (1 if self.q_net else 0))
        self.mlp = mlp([n_in, *hidden_sizes, *((1,) if self.q_net else ())], nn.ReLU)

    def forward(self, x: Sequence[torch.Tensor]) -> torch.Tensor:
        """The critic's values ``(B, 1)`` or the actor trunk's features ``(B, hidden_sizes[-1])``.

        Args:
            x: ``(speed, gear, rpm, images, *actions)``, each batched (the previous actions, then
                for a critic the action evaluated).
        """
        speed, gear, rpm, images, *acts = x
        feats = self.encoder(images.to(torch.float32))
        return self.mlp(torch.cat((speed, gear, rpm, feats, *acts), dim=-1))


LIDAR_INPUT_SCALE = 0.01
"""Input scale of speeds (km/h) and lidar distances (pixels) in the lidar models."""


def lidar_obs_scales(observation_space: Any) -> tuple[float, ...]:
    """Per-element input scales for lidar observations: speed (the first element) and lidar
    histories (elements whose size is a multiple of 19) by :data:`LIDAR_INPUT_SCALE`, the others
    (progress, actions) by 1.

    Args:
        observation_space: the preprocessed lidar observation space (a Tuple, or one space).

    Returns:
        One scale per element of the observation.
    """
    elements = list(getattr(observation_space, "spaces", [observation_space]))
    scales = []
    for i, space in enumerate(elements):
        dim = space_dim(space)
        lidar = dim >= 19 and dim % 19 == 0
        scales.append(LIDAR_INPUT_SCALE if i == 0 or lidar else 1.0)
    return tuple(scales)


def _scaled(obs: Any, scales: tuple[float, ...]) -> Any:
    if not isinstance(obs, (tuple, list)):
        return obs * scales[0]
    return tuple(o * s if s != 1.0 else o for o, s in zip(obs, scales)) + tuple(obs[len(scales):])


class LidarActor(SquashedGaussianMLPActor):
    """:class:`tmrl.models.SquashedGaussianMLPActor` whose inputs are scaled by
    :func:`lidar_obs_scales`.

    Args:
        observation_space: the preprocessed lidar observation space.
        action_space: a bounded Box.
        hidden_sizes: widths of the hidden layers.
        activation: activation class.
        device: where :meth:`act_` collates observations.
        obs_scales: one input scale per observation element, instead of
            :func:`lidar_obs_scales`'s.
    """

    def __init__(self, observation_space: Any, action_space: Any, hidden_sizes: Sequence[int] = (256, 256),
                 activation: Callable[[], nn.Module] = nn.ReLU, device: Any = "cpu",
                 obs_scales: Sequence[float] | None = None) -> None:
        super().__init__(observation_space, action_space, hidden_sizes, activation, device=device)
        self.obs_scales = tuple(float(s) for s in (obs_scales or lidar_obs_scales(observation_space)))

    def forward(self, obs: Any, test: bool = False, with_logprob: bool = True) -> tuple[torch.Tensor, torch.Tensor | None]:
        """As :meth:`tmrl.models.SquashedGaussianMLPActor.forward`, on scaled inputs.

        Args:
            obs: a batched observation, in the environment's units.
            test: use the Gaussian's mean instead of a sample.
            with_logprob: also return the log-density of the action.
        """
        return super().forward(_scaled(obs, self.obs_scales), test, with_logprob)


class LidarQFunctions(EnsembleQFunction):
    """:class:`tmrl.models.EnsembleQFunction` whose observation inputs are scaled by
    :func:`lidar_obs_scales`.

    Args:
        observation_space: the preprocessed lidar observation space.
        action_space: the action space (a Box).
        hidden_sizes: widths of the hidden layers.
        activation: activation class.
        n: number of Q functions.
        obs_scales: one input scale per observation element, instead of
            :func:`lidar_obs_scales`'s.
    """

    def __init__(self, observation_space: Any, action_space: Any, hidden_sizes: Sequence[int] = (256, 256),
                 activation: Callable[[], nn.Module] = nn.ReLU, n: int = 2,
                 obs_scales: Sequence[float] | None = None) -> None:
        super().__init__(observation_space, action_space, hidden_sizes, activation, n=n)
        self.obs_scales = tuple(float(s) for s in (obs_scales or lidar_obs_scales(observation_space)))

    def forward(self, obs: Any, act: torch.Tensor, members: Any = None, detach_params: bool = False) -> torch.Tensor:
        """As :meth:`tmrl.models.EnsembleQFunction.forward`, on scaled observations.

        Args:
            obs: a batched observation, in the environment's units.
            act: actions ``(B, act_dim)``.
            members: indices of the Q functions to evaluate (all when None).
            detach_params: use the weights as constants (for the actor's loss).

        Returns:
            Q values of shape ``(k, B)``, ``k`` = number of members evaluated.
        """
        return super().forward(_scaled(obs, self.obs_scales), act, members=members, detach_params=detach_params)


class LidarActorCritic(MLPActorCritic):
    """The lidar actor-critic: :class:`tmrl.models.MLPActorCritic` with scaled inputs
    (:class:`LidarActor`, :class:`LidarQFunctions`).

    Args:
        observation_space: the preprocessed lidar observation space.
        action_space: a bounded Box.
        hidden_sizes: widths of the hidden layers of the actor and of each critic.
        activation: activation class.
        n: number of critics (2 for SAC, 10 for REDQ).
    """

    def __init__(self, observation_space: Any, action_space: Any, hidden_sizes: Sequence[int] = (256, 256),
                 activation: Callable[[], nn.Module] = nn.ReLU, n: int = 2) -> None:
        super().__init__(observation_space, action_space, hidden_sizes, activation, n=n)
        self.actor = LidarActor(observation_space, action_space, hidden_sizes, activation)
        self.qs = LidarQFunctions(observation_space, action_space, hidden_sizes, activation, n=n)


def lidar_actor_critic(observation_space: Any, action_space: Any, hidden_sizes: Sequence[int] = (256, 256),
                       n: int = 2, activation: Callable[[], nn.Module] = nn.ReLU) -> LidarActorCritic:
    """The lidar models (:class:`LidarActorCritic`), built with keyword arguments.

    Args:
        observation_space: the preprocessed lidar observation space.
        action_space: a bounded Box.
        hidden_sizes: widths of the hidden layers.
        n: number of critics (2 for SAC, 10 for REDQ).
        activation: activation class.
    """
    return LidarActorCritic(observation_space, action_space, hidden_sizes=hidden_sizes, activation=activation, n=n)


# --- the lidar models of DroQ, TQC and CrossQ ---------------------------------------------------


class ScaledCritic(nn.Module):
    """A critic ``Q(obs, act)`` that reads observations scaled per element (as
    :class:`LidarActor` does) and is otherwise ``critic`` itself.

    Args:
        critic: any module called as ``critic(obs, act)``.
        obs_scales: one input scale per observation element.
    """

    def __init__(self, critic: nn.Module, obs_scales: Sequence[float]) -> None:
        super().__init__()
        self.critic = critic
        self.obs_scales = tuple(float(s) for s in obs_scales)

    # What tmrl.models.StackedCritics needs to evaluate several of them together: the wrapped
    # critic's network, on its input from the scaled observation.

    @property
    def net(self) -> nn.Module | None:
        """The wrapped critic's network (None when it has none, or no ``critic_input``)."""
        net = getattr(self.critic, "net", None)
        return net if isinstance(net, nn.Module) and callable(getattr(self.critic, "critic_input", None)) else None

    @property
    def squeeze_output(self) -> bool:
        """Whether the wrapped critic drops its output's last axis."""
        return bool(getattr(self.critic, "squeeze_output", True))

    @property
    def input_key(self) -> tuple:
        """Critics with equal keys read the same input (same scales, same kind of critic)."""
        return self.obs_scales, type(self.critic), getattr(self.critic, "input_key", None)

    def critic_input(self, obs: Any, act: torch.Tensor) -> torch.Tensor:
        """The wrapped critic's network input from the scaled observation.

        Args:
            obs: a batched observation, in the environment's units.
            act: actions ``(B, act_dim)``.
        """
        return self.critic.critic_input(_scaled(obs, self.obs_scales), act)  # type: ignore[operator]

    def forward(self, obs: Any, act: torch.Tensor) -> torch.Tensor:
        """``critic(scaled obs, act)``.

        Args:
            obs: a batched observation, in the environment's units.
            act: actions ``(B, act_dim)``.
        """
        return self.critic(_scaled(obs, self.obs_scales), act)


def _wire_lidar(model: nn.Module, observation_space: Any, action_space: Any, hidden_sizes: Sequence[int],
                activation: Callable[[], nn.Module]) -> None:
    """Give an MLP actor-critic with a ``ModuleList`` of critics (``.qs``) the lidar scaling: its
    actor becomes a :class:`LidarActor` of the same sizes (same parameter names: the workers'
    policy loads its weights), each critic reads scaled observations."""
    scales = lidar_obs_scales(observation_space)
    model.actor = LidarActor(observation_space, action_space, hidden_sizes, activation, obs_scales=scales)
    model.qs = nn.ModuleList(ScaledCritic(q, scales) for q in model.qs)  # type: ignore[union-attr]


class LidarDroQActorCritic(DroQMLPActorCritic):
    """DroQ's actor-critic (:class:`~tmrl.algorithms.droq.DroQMLPActorCritic`) for lidar
    observations: :class:`LidarActor` and dropout critics on inputs scaled by
    :func:`lidar_obs_scales`. Arguments as :class:`~tmrl.algorithms.droq.DroQMLPActorCritic`'s.
    """

    def __init__(self, observation_space: Any, action_space: Any, hidden_sizes: Sequence[int] = (256, 256),
                 activation: Callable[[], nn.Module] = nn.ReLU, n: int = 2, dropout_rate: float = 0.01) -> None:
        super().__init__(observation_space, action_space, hidden_sizes, activation, n=n, dropout_rate=dropout_rate)
        _wire_lidar(self, observation_space, action_space, hidden_sizes, activation)


class LidarTQCActorCritic(TQCActorCritic):
    """TQC's actor-critic (:class:`~tmrl.algorithms.tqc.TQCActorCritic`) for lidar observations:
    :class:`LidarActor` and quantile critics on inputs scaled by :func:`lidar_obs_scales`.
    Arguments as :class:`~tmrl.algorithms.tqc.TQCActorCritic`'s.
    """

    def __init__(self, observation_space: Any, action_space: Any, hidden_sizes: Sequence[int] = (256, 256),
                 activation: Callable[[], nn.Module] = nn.ReLU, n: int = 5, n_quantiles: int = 25,
                 critic_hidden_sizes: Sequence[int] = (512, 512, 512)) -> None:
        super().__init__(observation_space, action_space, hidden_sizes, activation, n=n, n_quantiles=n_quantiles,
                         critic_hidden_sizes=critic_hidden_sizes)
        _wire_lidar(self, observation_space, action_space, hidden_sizes, activation)


class LidarCrossQActorCritic(CrossQActorCritic):
    """CrossQ's actor-critic (:class:`~tmrl.algorithms.crossq.CrossQActorCritic`) for lidar
    observations: :class:`LidarActor` and batch-normalised critics on inputs scaled by
    :func:`lidar_obs_scales`, with no normalisation layer on the input by default
    (``critic_input_norm=False``): the scaling already puts the inputs on a common scale, and
    standardising each of the 76 redundant lidar features drowned the 3 action features (the
    critics barely told full gas from full brake, and the car never moved on 2 of 5 seeds of
    ``oval``; docs/benchmarks.md). Other arguments as
    :class:`~tmrl.algorithms.crossq.CrossQActorCritic`'s.
    """

    def __init__(self, observation_space: Any, action_space: Any, hidden_sizes: Sequence[int] = (256, 256),
                 activation: Callable[[], nn.Module] = nn.ReLU, n: int = 2,
                 critic_hidden_sizes: Sequence[int] = (1024, 1024), bn_momentum: float = 0.01,
                 renorm_warmup_steps: int = 100_000, critic_input_norm: bool = False) -> None:
        super().__init__(observation_space, action_space, hidden_sizes, activation, n=n,
                         critic_hidden_sizes=critic_hidden_sizes, bn_momentum=bn_momentum,
                         renorm_warmup_steps=renorm_warmup_steps, critic_input_norm=critic_input_norm)
        _wire_lidar(self, observation_space, action_space, hidden_sizes, activation)


class LidarBROActorCritic(BROActorCritic):
    """BRO's actor-critic (:class:`~tmrl.algorithms.bro.BROActorCritic`) for lidar observations:
    :class:`LidarActor` and BroNet quantile critics on inputs scaled by :func:`lidar_obs_scales`.
    Arguments as :class:`~tmrl.algorithms.bro.BROActorCritic`'s.
    """

    def __init__(self, observation_space: Any, action_space: Any, hidden_sizes: Sequence[int] = (256, 256),
                 activation: Callable[[], nn.Module] = nn.ReLU, n: int = 2, n_quantiles: int = 25,
                 critic_width: int = 256, critic_blocks: int = 1) -> None:
        super().__init__(observation_space, action_space, hidden_sizes, activation, n=n, n_quantiles=n_quantiles,
                         critic_width=critic_width, critic_blocks=critic_blocks)
        _wire_lidar(self, observation_space, action_space, hidden_sizes, activation)


class LidarSimbaV2ActorCritic(SimbaV2ActorCritic):
    """SimbaV2's actor-critic (:class:`~tmrl.algorithms.simbav2.SimbaV2ActorCritic`) for lidar
    observations: :class:`LidarActor` (SAC's MLP actor of ``hidden_sizes``, the workers' policy)
    and hyperspherical distributional critics on inputs scaled by :func:`lidar_obs_scales`.
    Arguments as :class:`~tmrl.algorithms.simbav2.SimbaV2ActorCritic`'s.
    """

    def __init__(self, observation_space: Any, action_space: Any, hidden_sizes: Sequence[int] = (256, 256),
                 activation: Callable[[], nn.Module] = nn.ReLU, n: int = 2, n_atoms: int = 101, v_max: float = 5.0,
                 critic_width: int = 128, critic_blocks: int = 1) -> None:
        super().__init__(observation_space, action_space, hidden_sizes, activation, n=n, n_atoms=n_atoms,
                         v_max=v_max, critic_width=critic_width, critic_blocks=critic_blocks)
        _wire_lidar(self, observation_space, action_space, hidden_sizes, activation)


LIDAR_MODELS: dict[str, type] = {
    "SAC": LidarActorCritic,
    "REDQSAC": LidarActorCritic,
    "DROQ": LidarDroQActorCritic,
    "TQC": LidarTQCActorCritic,
    "CROSSQ": LidarCrossQActorCritic,
    "BRO": LidarBROActorCritic,
    "SIMBAV2": LidarSimbaV2ActorCritic,
}
"""The actor-critic each ``ALG.ALGORITHM`` trains on the lidar interfaces (``SIMLIDAR``,
``SIMLIDARPROGRESS``, ``TM20LIDAR``, ``TM20LIDARPROGRESS``); the actor of each is a
:class:`LidarActor`, the policy the workers run. The agent passes its own model arguments (REDQ's
``n``, DroQ's ``dropout_rate``, TQC's ``n`` and ``n_quantiles``, CrossQ's, BRO's and SimbaV2's critic
sizes)."""


def lidar_model_cls(algorithm: str) -> type:
    """The lidar actor-critic of an algorithm (:data:`LIDAR_MODELS`).

    Args:
        algorithm: an ``ALG.ALGORITHM`` value; case, ``-`` and ``_`` are ignored (``"redq-sac"``).

    Raises:
        UserError: unknown algorithm.
    """
    key = str(algorithm).upper().replace("-", "").replace("_", "")
    if key not in LIDAR_MODELS:
        raise UserError(f"no lidar model for algorithm {algorithm!r}: use one of {', '.join(LIDAR_MODELS)}")
    return LIDAR_MODELS[key]
