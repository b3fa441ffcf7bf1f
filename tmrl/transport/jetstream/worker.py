"""The NATS backend's worker link: a rollout worker's connection (sends samples, reads weights)."""

from __future__ import annotations

from typing import Any

from tmrl.transport.jetstream.samples import _SampleSender
from tmrl.transport.jetstream.weights import _WeightsReader


class NatsWorkerLink(_SampleSender, _WeightsReader):
    """A rollout worker's connection over NATS JetStream: sends sample batches, receives the
    latest weights.

    Sample batches are published on ``tmrl.samples.<worker id>`` in order, pipelined: up to
    :data:`~tmrl.transport.jetstream.samples.SEND_WINDOW` batches
    (:data:`~tmrl.transport.jetstream.samples.SEND_WINDOW_BYTES` bytes) are in flight before the
    server acknowledged them (stored in the stream). A batch is kept until acknowledged; after a
    reconnection, a refusal, or a silence of the stream once the server confirmed it has the
    batches (:data:`~tmrl.transport.jetstream.samples.ACK_PROBE`), every unacknowledged batch is
    published again, in order, with the same message id, which the stream deduplicates. While disconnected, at most
    ``max_store`` batches / ``max_store_bytes`` bytes wait (beyond that the oldest is dropped and
    counted in :attr:`dropped`).

    Args:
        server_ip, server_port: the NATS server (ignored when ``urls`` is given).
        password: the shared PASSWORD; the worker's NATS password is derived from it unless
            ``credentials`` (or ``keys_dir/nats/worker.json``, written by ``--install``) exists.
        local_port, header_size, max_frame_bytes, trainer_key: accepted for the tlspyo links'
            signature, unused.
        security: ``"TLS"`` to require TLS (with ``tls="auto"``, TLS is on anyway for a server
            that is not on this machine).
        keys_dir: folder of ``certificate.pem`` (tmrl's self-signed certificate) and ``nats/``.
        hostname: the name in tmrl's certificate.
        allow_pickle: has no effect (logged): this transport never uses pickle.
        allow_plain_tcp: allow plain TCP to a server on another machine.
        urls: NATS server URLs (a comma-separated string or a list), e.g. a cluster's.
        credentials: path of this role's credentials file (``{"user": ..., "password": ...}``).
        tls: ``"auto"`` (default), ``"on"`` or ``"off"``.
        stream, bucket: names of the samples stream and of the weights buckets.
        max_bytes, max_msgs: the samples stream's bounds (used by the trainer, which creates it).
        replicas: copies of the stream and buckets in a NATS cluster (used by the trainer).
        recon_delay: seconds between reconnection attempts.
        max_store, max_store_bytes: bound of what waits while disconnected.

    Raises:
        UserError: invalid arguments, a credentials file that is not valid, or plain TCP to a
            remote server.
    """

    _role = "worker"

    def __init__(self, *args: Any, max_store: int = 256, max_store_bytes: int = 512 * 2**20, **kwargs: Any):
        self._init_sender(max_store, max_store_bytes)
        self._init_reader()
        super().__init__(*args, **kwargs)

    async def _start(self) -> None:
        import asyncio

        self._send_wake = asyncio.Event()
        self._weights_wake = asyncio.Event()
        await super()._start()
        self._tasks.append(asyncio.ensure_future(self._sender()))
        self._tasks.append(asyncio.ensure_future(self._weights_reader()))

    async def _on_connected(self, reconnect: bool) -> None:
        await super()._on_connected(reconnect)
        self._relookup = True  # the server may be a new one, with a new store
        self._resend_from_first()  # what was in flight may have been lost with the connection
        self._weights_wake.set()  # a reconnecting worker gets the latest weights at once
