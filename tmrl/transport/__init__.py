"""The transport seam: how samples and weights cross the network, over tlspyo.

- :class:`RelayServer`: the relay (tmrl's server), in its own process.
- :class:`WorkerLink`: a worker's connection (send samples, receive the latest weights).
- :class:`TrainerLink`: the trainer's connection (receive samples, broadcast weights).
- :func:`ensure_credentials`: TLS key and self-signed certificate.
- :mod:`tmrl.transport.base`: the contract the roles use (:class:`WorkerTransport`,
  :class:`TrainerTransport`, :class:`RelayTransport`) and :data:`BACKENDS`, the transports that
  implement it: ``"tlspyo"`` (the default) and ``"nats"`` (NATS JetStream,
  :mod:`tmrl.transport.jetstream`; needs ``pip install ".[nats]" in the checkout of this project``).

Everything on the wire is :mod:`tmrl.wire` data; see docs/transport.md. Importing this package
imports neither Twisted nor tlspyo (they run in the network processes only) nor ``nats``
(imported by the NATS links' threads when they start).
"""

from tmrl.transport.base import Backend, RelayTransport, TrainerTransport, WorkerTransport
from tmrl.transport.credentials import CERT_FILE, KEY_FILE, ensure_credentials
from tmrl.transport.links import TrainerLink, WorkerLink
from tmrl.transport.jetstream import NatsRelay, NatsTrainerLink, NatsWorkerLink
from tmrl.transport.relay import RelayServer

BACKENDS: dict[str, Backend] = {
    "tlspyo": Backend(name="tlspyo", relay=RelayServer, worker=WorkerLink, trainer=TrainerLink),
    "nats": Backend(name="nats", relay=NatsRelay, worker=NatsWorkerLink, trainer=NatsTrainerLink),
}
"""The transport backends, by name: each builds a relay, a worker's and the trainer's link."""

__all__ = [
    "BACKENDS",
    "CERT_FILE",
    "KEY_FILE",
    "Backend",
    "NatsRelay",
    "NatsTrainerLink",
    "NatsWorkerLink",
    "RelayServer",
    "RelayTransport",
    "TrainerLink",
    "TrainerTransport",
    "WorkerLink",
    "WorkerTransport",
    "ensure_credentials",
]
