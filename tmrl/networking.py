"""tmrl 0.7's path of the distributed pipeline: :class:`Server`, :class:`RolloutWorker`,
:class:`Trainer` and their :class:`Buffer` of samples.

The pipeline lives in :mod:`tmrl.distributed` (one module per job); this module re-exports it
under the names tmrl 0.7 scripts import, and adds the one thing that needs the configuration:
:class:`Trainer` built without ``training_cls`` trains ``config_objects.TRAINER``, the training
that ``config.json`` describes. Nothing is read at import.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from tmrl.distributed import trainer as _trainer
from tmrl.distributed._common import FROM_CONFIG, NOT_GIVEN, STOP_TIMEOUT, _make_link  # noqa: F401
from tmrl.distributed.buffer import Buffer, pack_buffer, unpack_buffer
from tmrl.distributed.server import Server
from tmrl.distributed.trainer_interface import PayloadOrder, TrainerInterface
from tmrl.distributed.weights import WeightsInstaller, WeightsRejected, pack_weights, unpack_weights  # noqa: F401
from tmrl.distributed.worker import EpisodeLog, Pace, RolloutWorker  # noqa: F401
from tmrl.spaces import (  # noqa: F401 (re-exported: their home was this module)
    PinnedSampleSchema,
    Rows,
    SampleRejected,
    SampleSchema,
    SpacesMismatchError,
    check_spaces,
    describe_spaces,
    finite_stat,
)
from tmrl.wire_buffers import PAYLOAD_VERSION, PayloadError  # noqa: F401 (re-exported)

__all__ = [
    "Buffer",
    "PayloadOrder",
    "RolloutWorker",
    "Server",
    "SpacesMismatchError",
    "Trainer",
    "TrainerInterface",
    "describe_spaces",
    "pack_buffer",
    "unpack_buffer",
]

class Trainer(_trainer.Trainer):
    __doc__ = _trainer.Trainer.__doc__

    @staticmethod
    def configured_training() -> Callable[[], Any]:
        """``config_objects.TRAINER``: the training that ``config.json`` describes (read now).

        Raises:
            tmrl.config.loader.ConfigError: the configuration is invalid.
        """
        from tmrl.config import config_objects

        return config_objects.TRAINER
