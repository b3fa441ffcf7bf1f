"""The NATS backend's trainer link: the trainer's connection (receives samples, writes weights)."""

from __future__ import annotations

import logging
from typing import Any

from tmrl.transport.jetstream.layout import _ensure_layout
from tmrl.transport.jetstream.samples import _SampleReceiver
from tmrl.transport.jetstream.weights import _WeightsWriter

logger = logging.getLogger("tmrl.transport.nats")


class NatsTrainerLink(_SampleReceiver, _WeightsWriter):
    """The trainer's connection over NATS JetStream: receives sample batches, broadcasts weights.

    The link creates (or updates) the samples stream and the weights buckets, and consumes the
    stream through the durable pull consumer ``tmrl-trainer``. It holds at most 64 fetched
    batches; :meth:`receive_samples` returns them and acknowledges them then, so a trainer killed
    before that gets them again when it restarts (a new link resumes from the last acknowledged
    batch). :meth:`broadcast_weights` returns at once; the newest weights are uploaded in the
    background (older ones not uploaded yet are skipped).

    Same arguments as :class:`~tmrl.transport.jetstream.worker.NatsWorkerLink` (``credentials`` or
    ``keys_dir/nats/trainer.json`` being the trainer's), plus ``ack_wait``: seconds after which
    the server delivers again a batch the trainer has not acknowledged (the link renews it while
    the batch waits in its hands).
    """

    _role = "trainer"

    def __init__(self, *args: Any, ack_wait: float = 30.0, **kwargs: Any):
        self._init_receiver(ack_wait)
        self._init_writer()
        self._fresh = True
        super().__init__(*args, **kwargs)

    async def _start(self) -> None:
        import asyncio

        self._room = asyncio.Event()
        self._weights_wake = asyncio.Event()
        await super()._start()
        self._tasks.append(asyncio.ensure_future(self._fetcher()))
        self._tasks.append(asyncio.ensure_future(self._broadcaster()))
        self._tasks.append(asyncio.ensure_future(self._keep_alive()))

    async def _on_connected(self, reconnect: bool) -> None:
        import asyncio

        while True:
            try:
                await self._setup(first=self._fresh)
                break
            except Exception as e:  # noqa: BLE001 (e.g. JetStream not ready yet after a restart)
                self._error_log("trainer link: setting up the stream failed (%s: %s); trying again",
                                type(e).__name__, e)
                if self._nc.is_closed:
                    return
                await asyncio.sleep(0.5)
        self._fresh = False
        await super()._on_connected(reconnect)
        self._room.set()
        self._weights_wake.set()

    async def _setup(self, first: bool) -> None:
        js = self._js = self._nc.jetstream(timeout=5)
        await _ensure_layout(js, self._stream, self._bucket, self._max_bytes, self._max_msgs, self._replicas)
        await self._open_consumer(js, first)
        if first:
            try:
                await self._clean_objects(js)
            except Exception as e:  # noqa: BLE001 (leftovers only cost space)
                logger.debug("trainer link: old weights objects not cleaned (%s)", e)
        await self._bind_consumer(js)

    # -- faults, for the tests ---------------------------------------------------------------------

    def _stall(self) -> None:
        """Stop handing out and acknowledging batches (fetching goes on), without disconnecting."""
        self._stalled = True

    def _crash(self) -> None:
        """Die without a goodbye: no acknowledgement, no flush, the socket cut."""
        self._stalled = True

        def cut() -> None:
            try:
                self._nc._transport._io_writer.transport.abort()
            except Exception as e:  # noqa: BLE001
                logger.debug("trainer link: socket not cut (%s)", e)
            self._loop.loop.stop()

        self._closed = True
        self._loop.call(cut)
        self._loop.thread.join(5)
        self._set_connected(False)
