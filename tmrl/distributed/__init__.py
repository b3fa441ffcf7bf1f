"""The distributed pipeline: a :class:`Server` relays the samples of every :class:`RolloutWorker`
to the :class:`Trainer` and the trainer's weights back to the workers.

Everything crosses the network through :mod:`tmrl.transport` as data only (:mod:`tmrl.wire`), never
pickle. Two payloads travel:

- **Samples** (worker -> trainer): a :class:`~tmrl.distributed.buffer.Buffer` packed column by
  column (:func:`~tmrl.distributed.buffer.pack_buffer`), stamped with the worker's random source
  id, a sequence number, its episode statistics and the run it acts for.
- **Weights** (trainer -> workers): the bytes of the file written by ``actor.save`` in a signed
  envelope that describes the actor's spaces (:mod:`tmrl.distributed.weights`), so that a worker
  built for another environment fails with a clear error instead of loading nonsense.

One module per job:

- :mod:`~tmrl.distributed.buffer`: the samples' buffer and its payload;
- :mod:`~tmrl.distributed.weights`: the weights envelope and where a worker installs weights;
- :mod:`~tmrl.distributed.server`: the relay;
- :mod:`~tmrl.distributed.trainer_interface`: the trainer's side of the network (receive, check,
  drop duplicates, broadcast);
- :mod:`~tmrl.distributed.trainer`: the training loop of a run (epochs, checkpoints, wandb);
- :mod:`~tmrl.distributed.worker`: the rollout worker.

Nothing here reads the configuration at import: defaults that come from ``config.json`` are
resolved when an object is built. :mod:`tmrl.networking` (tmrl 0.7's path) re-exports these names;
its ``Trainer`` also takes its training class from ``config.json`` when given none.
"""

from __future__ import annotations

from tmrl.distributed._common import FROM_CONFIG, NOT_GIVEN, STOP_TIMEOUT
from tmrl.distributed.buffer import Buffer, pack_buffer, unpack_buffer
from tmrl.distributed.server import Server
from tmrl.distributed.trainer import Trainer
from tmrl.distributed.trainer_interface import PayloadOrder, TrainerInterface
from tmrl.distributed.weights import WeightsInstaller, WeightsRejected, pack_weights, unpack_weights
from tmrl.distributed.worker import EpisodeLog, Pace, RolloutWorker

__all__ = [
    "FROM_CONFIG",
    "NOT_GIVEN",
    "STOP_TIMEOUT",
    "Buffer",
    "EpisodeLog",
    "Pace",
    "PayloadOrder",
    "RolloutWorker",
    "Server",
    "Trainer",
    "TrainerInterface",
    "WeightsInstaller",
    "WeightsRejected",
    "pack_buffer",
    "pack_weights",
    "unpack_buffer",
    "unpack_weights",
]
