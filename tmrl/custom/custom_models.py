"""Compatibility names of the original ``tmrl.custom.custom_models`` (no logic here).

The MLP models come from :mod:`tmrl.models`, the CNN models for full (image) observations from
:mod:`tmrl.driving.models`: ``SquashedGaussianVanillaCNNActor``, ``VanillaCNNQFunction`` and
``VanillaCNNActorCritic`` are :class:`~tmrl.driving.models.SquashedGaussianCNNActor`,
:class:`~tmrl.driving.models.CNNQFunction` and :class:`~tmrl.driving.models.CNNActorCritic`
(same layer sizes as tmrl 0.7; ``python -m tmrl --import-weights`` converts the original's
weights files). ``VanillaCNN(q_net)`` reads the image size and history length from
``config.json`` when built, as the original did.
"""

from __future__ import annotations

from typing import Any

from tmrl.driving.models import (
    CNNActorCritic as VanillaCNNActorCritic,
    CNNQFunction as VanillaCNNQFunction,
    REDQCNNActorCritic,
    SquashedGaussianCNNActor as SquashedGaussianVanillaCNNActor,
    VanillaCNN as _VanillaCNN,
    conv2d_out_dims,
    num_flat_features,
)
from tmrl.models import (
    LOG_STD_MAX,
    LOG_STD_MIN,
    EnsembleQFunction,
    MLPActorCritic,
    MLPQFunction,
    REDQMLPActorCritic,
    SquashedGaussianMLPActor,
    mlp,
)

__all__ = [
    "LOG_STD_MAX",
    "LOG_STD_MIN",
    "EnsembleQFunction",
    "MLPActorCritic",
    "MLPQFunction",
    "REDQCNNActorCritic",
    "REDQMLPActorCritic",
    "SquashedGaussianMLPActor",
    "SquashedGaussianVanillaCNNActor",
    "VanillaCNN",
    "VanillaCNNActorCritic",
    "VanillaCNNQFunction",
    "conv2d_out_dims",
    "mlp",
    "num_flat_features",
]


class VanillaCNN(_VanillaCNN):
    """:class:`tmrl.driving.models.VanillaCNN` sized from ``config.json`` (``ENV.IMG_HIST_LEN``,
    ``IMG_HEIGHT``, ``IMG_WIDTH``, the action buffer length), like tmrl 0.7's."""

    def __init__(self, q_net: bool, **kwargs: Any) -> None:
        from tmrl.config import config_constants as cfg

        kwargs.setdefault("image_shape", (cfg.IMG_HIST_LEN, cfg.IMG_HEIGHT, cfg.IMG_WIDTH))
        kwargs.setdefault("act_buf_len", cfg.ACT_BUF_LEN)
        super().__init__(q_net, **kwargs)
