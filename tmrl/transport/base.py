"""The transport contract: what the roles (:mod:`tmrl.networking`) use from a transport.

A transport backend provides three things, registered in :data:`tmrl.transport.BACKENDS` as a
:class:`Backend`: a relay (the server), a worker's connection and the trainer's connection. The
roles call exactly the members listed in the protocols below, nothing else; the second transport
(NATS JetStream, :mod:`tmrl.transport.jetstream`) is an addition that implements them, not a
fork of the roles.

Semantics, as the tlspyo backend implements them (and the contract tests in
tests/test_transport_contract.py check for every backend):

- **Samples** (worker to trainer) are delivered **at least once**, in order per worker. A worker
  keeps what it sent until the relay acknowledged it and sends it again after a reconnection;
  the relay keeps what it sent to the trainer until the trainer's link acknowledged it (once the
  object reached the trainer process) and queues it again, first, when the trainer disconnects
  before that. The receiver may therefore see a second copy (the roles number payloads per worker
  and drop second copies: :class:`tmrl.networking.PayloadOrder`). Queues are bounded: beyond
  their bounds the oldest batches are dropped and counted.
- **Weights** (trainer to workers) are a broadcast of which **only the newest** is kept: a
  worker that connects later gets the last broadcast only, and a worker reading late gets the
  newest one (older unread broadcasts are dropped).
- **Connection state**: ``connected`` says whether the link is connected now;
  ``wait_connected`` blocks until it is (True) or the timeout passed or the link closed (False).
  A link reconnects on its own after a lost connection.
- **Closing**: ``close(timeout)`` (links) and ``stop(timeout)`` (relay) flush what they can, then
  stop every process or thread the transport started, within ``timeout`` seconds; both are
  idempotent.

What the tlspyo links also offer and the roles do not use (``refused``: the relay's last refusal
reason, ``pid``: the network process) is not part of the contract.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Protocol, runtime_checkable


@runtime_checkable
class Link(Protocol):
    """Connection state and closing, common to a worker's and the trainer's transport."""

    @property
    def connected(self) -> bool:
        """Whether the link is connected to the relay right now."""
        ...

    def wait_connected(self, timeout: float | None = None) -> bool:
        """Block until connected (True) or ``timeout`` seconds passed / the link closed (False)."""
        ...

    def close(self, timeout: float = 15.0) -> None:
        """Flush what was sent, disconnect and stop within ``timeout`` seconds. Idempotent."""
        ...


@runtime_checkable
class WorkerTransport(Link, Protocol):
    """A rollout worker's transport: sends sample batches, receives the latest weights."""

    def send_samples(self, obj: Any) -> None:
        """Send one object (a packed sample buffer) to the trainer, at least once.

        Blocks while the network cannot keep up; while disconnected, keeps it (bounded: the oldest
        unsent ones are dropped) and sends it on reconnection.
        """
        ...

    def latest_weights(self, block: bool = False, timeout: float | None = None) -> bytes | None:
        """The newest weights broadcast since the last call (older unread ones dropped), or None;
        with ``block``, wait up to ``timeout`` seconds for them."""
        ...


@runtime_checkable
class TrainerTransport(Link, Protocol):
    """The trainer's transport: receives sample batches, broadcasts weights."""

    def receive_samples(self) -> list[Any]:
        """Every object received since the last call, oldest first; never blocks. Reading them
        acknowledges nothing more: an object is acknowledged once it reached this process."""
        ...

    def broadcast_weights(self, data: bytes) -> None:
        """Send ``data`` to every connected worker and to every worker that connects later (only
        the newest broadcast is kept)."""
        ...


@runtime_checkable
class RelayTransport(Protocol):
    """The relay (tmrl's server) between the workers and the trainer."""

    @property
    def running(self) -> bool:
        """Whether the relay is running."""
        ...

    def stop(self, timeout: float = 15.0) -> None:
        """Close every connection (after flushing) and stop within ``timeout`` seconds; frees the
        port. Idempotent."""
        ...


@dataclass(frozen=True)
class Backend:
    """How to build a transport's three parts.

    Attributes:
        name: the backend's name (a key of :data:`tmrl.transport.BACKENDS`).
        relay: ``relay(port, password, **options)``: a :class:`RelayTransport`; its ``port``
            attribute is the port it listens on.
        worker: ``worker(server_ip, server_port, password, **options)``: a
            :class:`WorkerTransport`.
        trainer: ``trainer(server_ip, server_port, password, **options)``: a
            :class:`TrainerTransport`.
    """

    name: str
    relay: Callable[..., RelayTransport]
    worker: Callable[..., WorkerTransport]
    trainer: Callable[..., TrainerTransport]


#: Members the roles use, per protocol (checked against each backend's classes by the tests).
MEMBERS: dict[str, tuple[str, ...]] = {
    "WorkerTransport": ("connected", "wait_connected", "close", "send_samples", "latest_weights"),
    "TrainerTransport": ("connected", "wait_connected", "close", "receive_samples", "broadcast_weights"),
    "RelayTransport": ("running", "stop"),
}
