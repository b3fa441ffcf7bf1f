"""The second transport backend: NATS JetStream (``"TRANSPORT": "nats"``).

- :class:`NatsRelay`: starts and supervises a local ``nats-server -js`` (or, given the URLs of an
  existing NATS cluster, starts nothing).
- :class:`NatsWorkerLink`: a worker's connection: publishes sample batches on
  ``tmrl.samples.<worker id>`` (at least once, in order) and reads the latest weights.
- :class:`NatsTrainerLink`: the trainer's connection: a durable pull consumer of the samples
  stream that acknowledges a batch once :meth:`~NatsTrainerLink.receive_samples` handed it over,
  and the writer of the weights (an object-store bucket, chunked by NATS, plus a key-value entry
  ``latest`` whose revision is the weights' version).

They implement the contract of :mod:`tmrl.transport.base`. The client library (``nats-py``) is
asyncio: each link runs its event loop in a background thread behind the synchronous contract.
Payloads are :mod:`tmrl.wire` bytes, as with tlspyo; nothing is ever unpickled. Importing this
package imports neither ``nats`` nor starts anything: ``pip install ".[nats]" in the checkout of this project`` brings both the
client and the ``nats-server`` program. See docs/scale-out.md.

**Bounds.** The samples stream keeps at most ``max_msgs`` batches and ``max_bytes`` bytes and
discards the **oldest** beyond them (discard-old): real-time workers never block on a trainer that
fell behind or is down, the trainer gets the freshest samples, and the trainer link counts what
was dropped (:attr:`NatsTrainerLink.dropped`, from the gaps in stream sequence numbers). This is
the contract's "beyond their bounds the oldest batches are dropped and counted".

The modules, one job each (lower ones never import higher ones):

- :mod:`~tmrl.transport.jetstream.bridge`: the event loop thread behind the synchronous contract,
  and a rate-limited log;
- :mod:`~tmrl.transport.jetstream.layout`: the stream's and buckets' names, bounds and creation;
- :mod:`~tmrl.transport.jetstream.connect`: URLs, TLS, and the connection both links share;
- :mod:`~tmrl.transport.jetstream.samples`: the samples channel (the worker's sending, the
  trainer's receiving);
- :mod:`~tmrl.transport.jetstream.weights`: the weights channel (the trainer's writing, the
  workers' reading);
- :mod:`~tmrl.transport.jetstream.worker`, :mod:`~tmrl.transport.jetstream.trainer`: the two
  links, each one sample end and one weights end over the connection;
- :mod:`~tmrl.transport.jetstream.server`: the relay (the local ``nats-server``).
"""

from tmrl.transport._nats_server import write_credentials
from tmrl.transport.jetstream.server import NatsRelay
from tmrl.transport.jetstream.trainer import NatsTrainerLink
from tmrl.transport.jetstream.worker import NatsWorkerLink

__all__ = ["NatsRelay", "NatsTrainerLink", "NatsWorkerLink", "write_credentials"]
