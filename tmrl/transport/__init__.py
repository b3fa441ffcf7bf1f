"""The transport seam: how samples and weights cross the network, over tlspyo.

- :class:`RelayServer`: the relay (tmrl's server), in its own process.
- :class:`WorkerLink`: a worker's connection (send samples, receive the latest weights).
- :class:`TrainerLink`: the trainer's connection (receive samples, broadcast weights).
- :func:`ensure_credentials`: TLS key and self-signed certificate.

Everything on the wire is :mod:`tmrl.wire` data; see docs/transport.md. Importing this package
imports neither Twisted nor tlspyo: they run in the network processes only.
"""

from tmrl.transport.credentials import CERT_FILE, KEY_FILE, ensure_credentials
from tmrl.transport.links import TrainerLink, WorkerLink
from tmrl.transport.relay import RelayServer

__all__ = ["CERT_FILE", "KEY_FILE", "RelayServer", "TrainerLink", "WorkerLink", "ensure_credentials"]
