"""DrQ: SAC on image observations with a shared convolutional encoder and random shifts.

Three papers shape this agent:

- Kostrikov, Yarats, Fergus, 2020, "Image Augmentation Is All You Need: Regularizing Deep
  Reinforcement Learning from Pixels" (DrQ, arXiv:2004.13649);
- Yarats, Fergus, Lazaric, Pinto, 2021, "Mastering Visual Continuous Control: Improved
  Data-Augmented Reinforcement Learning" (DrQ-v2, arXiv:2107.09645);
- Yarats, Zhang, Kostrikov, Amos, Pineau, Fergus, 2019, "Improving Sample Efficiency in
  Model-free Reinforcement Learning from Images" (SAC-AE, arXiv:1910.01741).

The model (:class:`DrQActorCritic`). One encoder ``f`` (:class:`DrQEncoder`): convolutions over
the frame history, then a linear projection, layer normalisation and tanh (SAC-AE's encoder, which
DrQ reuses). The actor and the ``n`` critics are MLP heads on ``(f(o), other observation
elements)``; the actor holds the *same* encoder module (``actor.encoder is encoder``), so its state
dict, the weights the workers receive, carries the encoder and a worker acts from the broadcast
weights alone. The frames stay uint8 from the worker to the batch
(:func:`tmrl.driving.preprocessors.preprocess_full_obs_uint8`,
:class:`tmrl.driving.memories.RawImageMemory`); the encoder divides them by 255.

One update (SAC's :meth:`~tmrl.algorithms.sac.SACAgent.train` on :meth:`DrQAgent._prepare_batch`, the
shifts, and :meth:`DrQAgent._update_losses`, the losses), step by step, with the equation of the
papers each implements:

- augmentation ``aug``, DrQ's random shift (the image transformation of that paper, whose
  parameter is the offset): each sampled ``o`` and, independently, each ``o'`` is padded by
  ``image_pad`` pixels on every side, repeating the edge pixels, and cropped back to its size at a
  random offset: one offset per sample, the same for every frame of its history
  (:func:`random_shift`). Only the trainer's batches are shifted: the actor never shifts what it
  is given, so workers and test episodes see the frames as they are;
- target, DrQ's soft target averaged over ``K`` shifts of ``o'``, here with ``K = 1`` as in
  DrQ-v2: ``y = r + gamma (1 - terminated) (min_i Qbar_i(fbar(aug(o')), a') - alpha
  log pi(a'|f(aug(o'))))``, ``a' ~ pi(.|f(aug(o')))``, where ``fbar`` and ``Qbar_i`` are the
  target encoder and target critics (SAC-AE and DrQ keep a target copy of the encoder with the
  critics'; :meth:`DrQAgent.target_q`) and the actor reads the online encoder, as SAC's
  :meth:`~tmrl.algorithms.sac.SACAgent.target_value` does;
- critics, DrQ's Q regression averaged over ``M`` shifts of ``o``, here ``M = 1``:
  ``mean_i (Q_i(f(aug(o)), a) - y)^2`` (SAC's :meth:`~tmrl.algorithms.sac.SACAgent.critic_loss`).
  This is the only loss whose gradient reaches the encoder: SAC-AE found that letting the actor's
  gradient into a shared encoder made learning from pixels unstable, and DrQ keeps that rule;
- actor, SAC's policy objective on the features with their gradient stopped, ``sg(f(aug(o)))``:
  ``mean(alpha log pi(a~|sg(f)) - min_i Q_i(sg(f), a~))``, the critics' weights held constant;
  then SAC v2's entropy-coefficient loss on the same ``log pi``;
- one backward pass through the three losses and the three optimizers' steps (SAC's
  "simultaneous" order), then Polyak averaging of the target encoder and the target critics with
  the same factor (``ALG.POLYAK``): ``theta_bar <- polyak theta_bar + (1 - polyak) theta``.

Departures from the papers, each for this project's setting: the actor and the critics share the
projection, normalisation and tanh as well as the convolutions (DrQ gives the actor its own
projection on the shared convolutions; DrQ-v2 gives each head its own) so that one encoder pass
per batch serves both; the policy and the targets are updated at every update (DrQ: every second
update, with a target factor of 0.99); the other observation elements (speed, gear, rpm, previous
actions) join the features before the heads.

Random numbers, drawn from the global torch generator in every update in this order: the shifts of
``o``, the shifts of ``o'`` (``torch.randint(0, 2 * image_pad + 1, (B, 2))`` each, columns
``(dy, dx)``), the policy's noise at ``o``, the policy's noise at ``o'``.
"""

from __future__ import annotations

import contextlib
from collections.abc import Callable, Iterator, Sequence
from typing import Any

import numpy as np
import torch
from torch import nn

from tmrl.actor import TorchActorModule
from tmrl.algorithms.sac import SACAgent, _build_model, make_optimizer
from tmrl.batch import Batch
from tmrl.errors import UserError
from tmrl.models import mlp, space_dim, split_image_obs, squashed_gaussian, stacked_mlp, stacked_plan

__all__ = ["DRQ_CNN", "DrQActor", "DrQActorCritic", "DrQAgent", "DrQCritics", "DrQEncoder", "random_shift"]

DRQ_CNN: dict[str, Any] = {
    "channels": (32, 32, 32, 32),
    "kernels": (3, 3, 3, 3),
    "strides": (2, 1, 1, 1),
    "feature_dim": 50,
    "hidden_sizes": (256, 256),
}
"""The sizes of SAC-AE's and DrQ's networks (convolutions, feature size, head widths; DrQ uses
1024-unit heads, 256 here for a CPU)."""



def random_shift(imgs: torch.Tensor, pad: int, generator: torch.Generator | None = None) -> torch.Tensor:
    """DrQ's random shift of a batch of frame histories: each sample padded by ``pad`` pixels on
    every side with its edge pixels repeated, then cropped back to ``(h, w)`` at a random offset.

    The offset is drawn once per sample (``torch.randint(0, 2 * pad + 1, (B, 2))``, columns
    ``(dy, dx)``) and applied to every frame of that sample. The dtype is kept (uint8 frames stay
    uint8); nothing is interpolated.

    Args:
        imgs: ``(B, hist, h, w)`` frames.
        pad: the padding, in pixels (0: a copy of ``imgs``).
        generator: where the offsets come from (None: the global torch generator).

    Returns:
        The shifted frames, same shape and dtype.
    """
    if pad <= 0:
        return imgs.clone()
    b, _, h, w = imgs.shape
    # Drawn on the CPU; sent to the device without waiting for it (from pinned memory: a copy from
    # pageable memory would wait for the device's queue first).
    offsets = torch.randint(0, 2 * pad + 1, (b, 2), generator=generator)
    if imgs.device.type == "cuda":
        offsets = offsets.pin_memory()
    offsets = offsets.to(imgs.device, non_blocking=True)
    # Padding with repeated edges then cropping at (dy, dx) reads row i of the output from row
    # clamp(i + dy - pad) of the input (and likewise for columns).
    rows = (torch.arange(h, device=imgs.device) + offsets[:, :1] - pad).clamp_(0, h - 1)  # (B, h)
    cols = (torch.arange(w, device=imgs.device) + offsets[:, 1:] - pad).clamp_(0, w - 1)  # (B, w)
    picked = imgs.gather(2, rows[:, None, :, None].expand(b, imgs.shape[1], h, w))
    return picked.gather(3, cols[:, None, None, :].expand(b, imgs.shape[1], h, w))


def _image_layout(observation_space: Any, image_index: int) -> tuple[tuple[int, int, int], int]:
    """``(hist, h, w)`` of the frames and the number of other scalars, or a one-line error."""
    elements = list(getattr(observation_space, "spaces", ()))
    if not elements or not 0 <= image_index < len(elements) or len(elements[image_index].shape) != 3:
        got = getattr(observation_space, "shape", None) if not elements else [tuple(e.shape) for e in elements]
        raise UserError(
            f'ALG.ALGORITHM "DRQ" learns from frame histories (hist, height, width) at position {image_index} of '
            f"the observation, got {got}: use ENV.RTGYM_INTERFACE SIMFULL or TM20FULL with ENV.IMG_GRAYSCALE true"
        )
    hist, h, w = (int(s) for s in elements[image_index].shape)
    others = sum(space_dim(s) for i, s in enumerate(elements) if i != image_index)
    return (hist, h, w), others


class DrQEncoder(nn.Module):
    """SAC-AE's image encoder: convolutions (ReLU after each, no padding), a linear projection,
    layer normalisation, tanh.

    Args:
        image_shape: ``(hist, h, w)`` of the frame histories.
        channels: output channels of each convolution.
        kernels: square kernel size of each convolution.
        strides: stride of each convolution.
        feature_dim: size of the features (the projection's output).

    Raises:
        UserError: lists of different lengths, or frames too small for the convolutions.
    """

    def __init__(self, image_shape: tuple[int, int, int], channels: Sequence[int] = DRQ_CNN["channels"],
                 kernels: Sequence[int] = DRQ_CNN["kernels"], strides: Sequence[int] = DRQ_CNN["strides"],
                 feature_dim: int = DRQ_CNN["feature_dim"]) -> None:
        super().__init__()
        if not len(channels) == len(kernels) == len(strides) >= 1:
            raise UserError("DrQ's channels, kernels and strides must be lists of the same length (>= 1)")
        hist, h, w = image_shape
        layers: list[nn.Module] = []
        in_ch = int(hist)
        for out_ch, k, s in zip(channels, kernels, strides):
            h, w = (h - int(k)) // int(s) + 1, (w - int(k)) // int(s) + 1
            if h < 1 or w < 1:
                raise UserError(
                    f"frames of {image_shape[1]}x{image_shape[2]} are too small for DrQ's convolutions "
                    f"(kernels {list(kernels)}, strides {list(strides)}): use larger ENV.IMG_HEIGHT and ENV.IMG_WIDTH"
                )
            layers += [nn.Conv2d(in_ch, int(out_ch), int(k), stride=int(s)), nn.ReLU()]
            in_ch = int(out_ch)
        self.convs = nn.Sequential(*layers)
        self.conv_dim = in_ch * h * w
        self.feature_dim = int(feature_dim)
        self.projection = nn.Linear(self.conv_dim, self.feature_dim)
        self.norm = nn.LayerNorm(self.feature_dim)

    CHANNELS_LAST_FROM = 16
    """Batches at least this large run channels-last (NHWC), faster for oneDNN's convolutions on a
    CPU (as :class:`tmrl.driving.models.ImageEncoder` does); a worker's batch of one keeps NCHW."""

    def forward(self, imgs: torch.Tensor) -> torch.Tensor:
        """Features ``(B, feature_dim)`` in ``(-1, 1)``.

        Args:
            imgs: ``(B, hist, h, w)`` frames: uint8 (divided by 255 here) or floats in ``[0, 1]``.
        """
        x = imgs.to(torch.float32) / 255.0 if imgs.dtype == torch.uint8 else imgs.to(torch.float32)
        if x.shape[0] >= self.CHANNELS_LAST_FROM:
            x = x.contiguous(memory_format=torch.channels_last)
        # With NHWC strides, flatten copies into the NCHW order the projection's weights expect.
        return torch.tanh(self.norm(self.projection(self.convs(x).flatten(1))))


class DrQActor(TorchActorModule):
    """The policy the workers run: a :class:`DrQEncoder` and SAC's squashed Gaussian head on
    ``(features, other observation elements)``.

    Args:
        observation_space: a Tuple space with ``(hist, h, w)`` frames at ``image_index``.
        action_space: a bounded Box.
        channels: the encoder's convolution channels (see :data:`DRQ_CNN`).
        kernels: the encoder's kernel sizes.
        strides: the encoder's strides.
        feature_dim: the encoder's feature size.
        hidden_sizes: widths of the head's hidden layers.
        image_index: position of the frames in the observation (3 for the full interfaces).
        device: where :meth:`act_` collates observations.
        encoder: an encoder to use instead of building one (the actor-critic passes its shared one).

    Raises:
        UserError: an observation without frame histories (one line naming ``ALG.ALGORITHM``).
    """

    def __init__(self, observation_space: Any, action_space: Any, channels: Sequence[int] = DRQ_CNN["channels"],
                 kernels: Sequence[int] = DRQ_CNN["kernels"], strides: Sequence[int] = DRQ_CNN["strides"],
                 feature_dim: int = DRQ_CNN["feature_dim"], hidden_sizes: Sequence[int] = DRQ_CNN["hidden_sizes"],
                 image_index: int = 3, device: Any = "cpu", encoder: DrQEncoder | None = None) -> None:
        super().__init__(observation_space, action_space, device=device)
        shape, others = _image_layout(observation_space, image_index)
        self.image_index = int(image_index)
        self.encoder = encoder if encoder is not None else DrQEncoder(shape, channels, kernels, strides, feature_dim)
        dim_act = int(np.prod(action_space.shape))
        self.net = mlp([self.encoder.feature_dim + others, *hidden_sizes], nn.ReLU, nn.ReLU)
        self.mu_layer = nn.Linear(int(hidden_sizes[-1]), dim_act)
        self.log_std_layer = nn.Linear(int(hidden_sizes[-1]), dim_act)
        low = np.asarray(action_space.low, dtype=np.float32).reshape(-1)
        high = np.asarray(action_space.high, dtype=np.float32).reshape(-1)
        self.register_buffer("act_scale", torch.from_numpy((high - low) / 2.0), persistent=False)
        self.register_buffer("act_offset", torch.from_numpy((high + low) / 2.0), persistent=False)

    def head_parameters(self) -> list[nn.Parameter]:
        """The parameters of the head, the encoder's excluded (what the actor's optimizer steps)."""
        shared = {id(p) for p in self.encoder.parameters()}
        return [p for p in self.parameters() if id(p) not in shared]

    def head(self, features: torch.Tensor, others: torch.Tensor, test: bool = False,
             with_logprob: bool = True) -> tuple[torch.Tensor, torch.Tensor | None]:
        """The policy on given features: ``(action (B, act_dim), log pi (B,) or None)``.

        Args:
            features: the encoder's features ``(B, feature_dim)`` (the trainer passes them detached).
            others: the other observation elements, ``(B, k)``.
            test: the Gaussian's mean instead of a sample.
            with_logprob: also return the log-density of the action.
        """
        h = self.net(torch.cat((features, others), dim=-1))
        return squashed_gaussian(self.mu_layer(h), self.log_std_layer(h), self.act_scale, self.act_offset,
                                 test, with_logprob)

    def forward(self, obs: Any, test: bool = False,
                with_logprob: bool = True) -> tuple[torch.Tensor, torch.Tensor | None]:
        """The policy on a batched observation, its frames as given (never shifted here).

        Args:
            obs: a batched observation.
            test: the Gaussian's mean instead of a sample.
            with_logprob: also return the log-density of the action.
        """
        imgs, others = split_image_obs(obs, self.image_index)
        return self.head(self.encoder(imgs), others, test, with_logprob)

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


class DrQCritics(nn.ModuleList):
    """``n`` Q heads on ``(features, other observation elements, action)``, each an MLP; on a GPU
    evaluated together (one batched product per layer, :func:`~tmrl.models.stacked_mlp`), on a CPU
    one by one (faster there, as :class:`~tmrl.algorithms.critics.CriticSet` explains).

    Args:
        in_dim: features plus other observation elements.
        act_dim: size of an action.
        hidden_sizes: widths of each head's hidden layers.
        n: number of critics.
    """

    def __init__(self, in_dim: int, act_dim: int, hidden_sizes: Sequence[int], n: int) -> None:
        super().__init__(mlp([in_dim + act_dim, *hidden_sizes, 1], nn.ReLU) for _ in range(int(n)))
        self.kinds = stacked_plan(list(self))  # type: ignore[arg-type]
        self.stack: bool | None = None
        """Evaluate the heads together: True, False, or None (when the input is not on a CPU)."""

    def values(self, features: torch.Tensor, others: torch.Tensor, act: torch.Tensor) -> torch.Tensor:
        """Q values ``(n, B)``.

        Args:
            features: the encoder's features ``(B, feature_dim)``.
            others: the other observation elements ``(B, k)``.
            act: actions ``(B, act_dim)``.
        """
        x = torch.cat((features, others, act.reshape(act.shape[0], -1).to(torch.float32)), dim=-1)
        stack = self.stack if self.stack is not None else x.device.type != "cpu"
        if self.kinds is None or not stack:  # one by one
            return torch.stack([q(x).squeeze(-1) for q in self])
        return stacked_mlp(list(self), x, self.kinds).squeeze(-1)  # type: ignore[arg-type]

    @contextlib.contextmanager
    def frozen(self) -> Iterator[None]:
        """The heads' weights as constants inside the block (no gradient reaches them)."""
        params = list(self.parameters())
        flags = [p.requires_grad for p in params]
        for p in params:
            p.requires_grad_(False)
        try:
            yield
        finally:
            for p, f in zip(params, flags):
                p.requires_grad_(f)


class DrQActorCritic(nn.Module):
    """DrQ's actor-critic: one :class:`DrQEncoder` (``.encoder``), the actor (``.actor``, a
    :class:`DrQActor` holding that same encoder) and ``n`` Q heads (``.qs``).

    Args:
        observation_space: a Tuple space with ``(hist, h, w)`` frames at ``image_index``.
        action_space: a bounded Box.
        channels: the encoder's convolution channels (see :data:`DRQ_CNN`).
        kernels: the encoder's kernel sizes.
        strides: the encoder's strides.
        feature_dim: the encoder's feature size.
        hidden_sizes: widths of the actor's and each critic's hidden layers.
        n: number of critics.
        image_index: position of the frames in the observation.

    Raises:
        UserError: ``n < 1``, or an observation without frame histories.
    """

    def __init__(self, observation_space: Any, action_space: Any, channels: Sequence[int] = DRQ_CNN["channels"],
                 kernels: Sequence[int] = DRQ_CNN["kernels"], strides: Sequence[int] = DRQ_CNN["strides"],
                 feature_dim: int = DRQ_CNN["feature_dim"], hidden_sizes: Sequence[int] = DRQ_CNN["hidden_sizes"],
                 n: int = 2, image_index: int = 3) -> None:
        super().__init__()
        if int(n) < 1:
            raise UserError(f"an actor-critic needs at least one critic, got n={n}")
        shape, others = _image_layout(observation_space, image_index)
        self.image_index = int(image_index)
        self.encoder = DrQEncoder(shape, channels, kernels, strides, feature_dim)
        self.actor = DrQActor(observation_space, action_space, feature_dim=feature_dim, hidden_sizes=hidden_sizes,
                              image_index=image_index, encoder=self.encoder)
        self.qs = DrQCritics(self.encoder.feature_dim + others, int(np.prod(action_space.shape)), hidden_sizes, n)

    def act(self, obs: Any, test: bool = False) -> np.ndarray:
        """The actor's action for a batched observation, as a NumPy array.

        Args:
            obs: a batched observation.
            test: take the mean action instead of a sample.
        """
        return self.actor.act(obs, test)


class DrQAgent(SACAgent):
    """DrQ (see the module's notes). Takes every argument of :class:`~tmrl.algorithms.sac.SACAgent`
    but ``update_order`` and ``fused`` (``model_cls`` defaults to :class:`DrQActorCritic`) plus:

    Args:
        image_pad: the random shift's padding in pixels (the papers: 4; 0 turns augmentation off).

    Raises:
        UserError: ``image_pad < 0``, or a model without a shared encoder (``.encoder``, the
            actor's own ``.encoder``) and Q heads (``.qs`` with ``values``); plus
            :class:`SACAgent`'s errors.
    """

    def __init__(
        self,
        observation_space: Any = None,
        action_space: Any = None,
        device: Any = None,
        model_cls: Callable[..., torch.nn.Module] = DrQActorCritic,
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
        image_pad: int = 4,
    ) -> None:
        self.image_pad = int(image_pad)
        if self.image_pad < 0:
            raise UserError(f"image_pad={image_pad} must be >= 0 (ALG.DRQ_IMAGE_PAD), typically 4")
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
            update_order="simultaneous",
            fused=False,
            compile=compile,
        )
        self.image_index = int(getattr(self.model, "image_index", 3))

    def _make_model(self) -> torch.nn.Module:
        model = _build_model(self.model_cls, self.observation_space, self.action_space)
        encoder = getattr(model, "encoder", None)
        actor = getattr(model, "actor", None)
        if not (isinstance(encoder, nn.Module) and getattr(actor, "encoder", None) is encoder
                and callable(getattr(getattr(model, "qs", None), "values", None))):
            name = getattr(self.model_cls, "__name__", type(model).__name__)
            raise UserError(
                f"DrQ needs an encoder shared by the actor and the critics, and {name} has none: use "
                "tmrl.algorithms.drq.DrQActorCritic as the model"
            )
        return model

    def _make_optimizers(self) -> None:
        # The encoder belongs to the critics' optimizer only: the actor's steps its head.
        self.pi_optimizer = make_optimizer(
            self.optimizer_actor, self.model.actor.head_parameters(), self.lr_actor, self.betas_actor, self.l2_actor,
            "optimizer_actor",
        )
        critic_params = list(self.model.encoder.parameters()) + list(self.model.qs.parameters())
        self.q_optimizer = make_optimizer(
            self.optimizer_critic, critic_params, self.lr_critic, self.betas_critic, self.l2_critic, "optimizer_critic",
        )

    # --- one update, top to bottom ------------------------------------------------------------

    def augment(self, obs: Sequence[torch.Tensor]) -> tuple:
        """The observation with its frames shifted by :func:`random_shift` (the trainer's batches
        only; one offset per sample).

        Args:
            obs: a batched observation, frames at the model's ``image_index``.
        """
        obs = tuple(obs)
        i = self.image_index
        return obs[:i] + (random_shift(obs[i], self.image_pad),) + obs[i + 1:]

    def losses(self, batch: tuple) -> dict[str, Any]:
        """The update's losses on ``batch`` (augmented here), before any backward pass:
        ``loss_critic``, ``loss_actor``, ``loss_alpha`` (None when alpha is fixed), and ``alpha``,
        ``q`` ``(n, B)``, ``backup`` ``(B,)``, ``logp_pi`` ``(B,)`` for the metrics.

        Args:
            batch: a :class:`~tmrl.batch.Batch` or any 6-tuple ``(obs, act, rew, next_obs,
                terminated, truncated)``.
        """
        return self._losses_on(self._prepare_batch(Batch(*batch)))

    def _prepare_batch(self, b: Batch) -> Batch:
        """The random shifts of ``o`` then ``o'`` (:meth:`augment`), eager in every mode: their
        offsets come from the CPU generator, before the policy's noise."""
        return b._replace(obs=self.augment(b.obs), next_obs=self.augment(b.next_obs))

    def _losses_on(self, b: Batch) -> dict[str, Any]:
        """:meth:`losses` on a batch already augmented."""
        alpha = self._entropy_coef()
        imgs, others = split_image_obs(b.obs, self.image_index)
        features = self.model.encoder(imgs)  # the critics' path: the encoder learns from it
        # The actor reads the features detached: no actor gradient reaches the encoder.
        pi, logp_pi = self.actor.head(features.detach(), others)
        backup = self.target_value(b, alpha)
        q = self.model.qs.values(features, others, b.act)
        with self.model.qs.frozen():
            q_pi_all = self.model.qs.values(features.detach(), others, pi)
        return {
            "loss_critic": self.critic_loss(q, backup),
            "loss_actor": self.actor_loss(alpha, logp_pi, q_pi_all),
            "loss_alpha": self.entropy_loss(logp_pi),
            "alpha": alpha, "q": q, "backup": backup, "logp_pi": logp_pi,
        }

    def _update_losses(self, b: Batch, update_policy: bool) -> tuple[Any, ...]:
        """:meth:`losses` on the augmented batch in :meth:`SACAgent._update_losses
        <tmrl.algorithms.sac.SACAgent._update_losses>`'s form: what :meth:`train` (SAC's: one
        backward pass, the three optimizers' steps, Polyak averaging of the target encoder and
        critics) runs, and what ``ALG.COMPILE`` compiles. DrQ updates its policy at every update.

        Args:
            b: the batch, augmented (:meth:`_prepare_batch`).
            update_policy: always True for DrQ.
        """
        out = self._losses_on(b)
        stats = {"debug_log_pi": out["logp_pi"].detach().mean(), "debug_q": out["q"].detach().mean(),
                 "debug_backup": out["backup"].mean()}
        return out["alpha"], out["loss_critic"], out["loss_actor"], out["loss_alpha"], stats

    # --- the steps that differ from SAC ---------------------------------------------------------

    def target_q(self, next_obs: Any, next_act: torch.Tensor) -> torch.Tensor:
        """``min_i Qbar_i(fbar(o'), a')``, shape ``(B,)``: the target critics on the target
        encoder's features (called by SAC's ``target_value`` without gradients).

        Args:
            next_obs: the (augmented) next observations ``o'``.
            next_act: actions ``a'`` drawn from the current policy at ``o'``.
        """
        target = self.model_target
        imgs, others = split_image_obs(next_obs, self.image_index)
        return target.qs.values(target.encoder(imgs), others, next_act).min(0).values

    # target_value, critic_loss, actor_loss, policy_q and entropy_loss are SAC's.
