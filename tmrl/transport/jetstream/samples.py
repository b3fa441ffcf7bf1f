"""The NATS backend's samples channel: the worker's sending and the trainer's receiving.

- :class:`_SampleSender` (in :class:`~tmrl.transport.jetstream.worker.NatsWorkerLink`): publishes
  batches on ``tmrl.samples.<worker id>`` in order, pipelined (:data:`SEND_WINDOW`), keeps each
  until the stream acknowledged it and sends again what was not (same message id: the stream
  deduplicates): per-worker order, at least once.
- :class:`_SampleReceiver` (in :class:`~tmrl.transport.jetstream.trainer.NatsTrainerLink`): the
  durable pull consumer; holds at most :data:`RECEIVE_WINDOW` fetched batches, acknowledges them
  when :meth:`~_SampleReceiver.receive_samples` hands them over, counts what the stream discarded.

The tunables below are read here: set them on this module (``samples.ACK_TIMEOUT = ...``), not on
the re-export modules.
"""

from __future__ import annotations

import collections
import itertools
import json
import logging
import secrets
import threading
import time
from typing import Any

from tmrl import wire
from tmrl.errors import UserError
from tmrl.transport._nats_server import INBOX, SAMPLES_PREFIX
from tmrl.transport.jetstream.bridge import _Rate
from tmrl.transport.jetstream.connect import _NatsLink
from tmrl.transport.jetstream.layout import CONSUMER

logger = logging.getLogger("tmrl.transport.nats")

SEND_WINDOW = 64
"""A worker publishes up to this many batches before the server acknowledged the first of them
(the publications are pipelined), and ``send_samples`` blocks while this many wait."""
SEND_WINDOW_BYTES = 32 * 2**20
"""... and at most this many bytes of them (at least one batch, whatever its size)."""
ACK_TIMEOUT = 5.0
"""Seconds without any acknowledgement of the in-flight batches after which they are all sent
again (in order, with the same message ids: the stream deduplicates them), unless a ping to the
server still waits for its answer (:data:`ACK_PROBE`)."""
ACK_PROBE = 1.0
"""Seconds without any acknowledgement after which a worker asks its server (a ping) whether every
batch in flight reached it. Once the server said so, :data:`ACK_CONFIRMED_WAIT` more seconds without
an answer of the stream mean the stream lost them (its leader died with them) and they are sent
again. On a slow link the ping's answer waits behind the batches: a link busy carrying them
causes no copies."""
ACK_CONFIRMED_WAIT = 1.0
"""Seconds the stream may take to answer batches its server has (see :data:`ACK_PROBE`)."""
PING_TIMEOUT = 20.0
"""Seconds a worker waits for its server's answer to that ping before it sends its batches again."""
RECEIVE_WINDOW = 64
"""The trainer link holds at most this many unacknowledged batches (fetched, not yet returned)."""


class _SampleSender(_NatsLink):
    """The worker's end of the samples channel (mixed into the worker's link)."""

    def _init_sender(self, max_store: int, max_store_bytes: int) -> None:
        """The sending side's state (before the connection starts)."""
        self._outbox: collections.deque[tuple[int, bytes]] = collections.deque()
        self._outbox_bytes = 0
        self._out_cv = threading.Condition()
        self._max_store, self._max_store_bytes = int(max_store), int(max_store_bytes)
        self._seq = 0
        self.worker_id = secrets.token_hex(6)
        """This link's id: its samples go to ``tmrl.samples.<worker_id>``."""
        self.dropped = 0
        """Batches dropped because more than ``max_store`` waited while disconnected."""
        self.published = 0
        """Batches the server acknowledged."""
        self.transmissions = 0
        """Publications of batches, copies sent again included (``transmissions - published``
        batches were sent more than once or wait for their acknowledgement)."""
        self.max_in_flight = 0
        """The most batches that were in flight (published, unacknowledged) at once."""
        self._next_send = 1  # the seq of the next batch to publish; older ones are in flight
        self._acked: set[int] = set()  # acknowledged, but an older one is not yet
        self._retry_at = 0.0  # when to publish again from the oldest, after a refusal
        self._last_ack = time.monotonic()
        self._probe_round = 0  # bumped by every answer and resend: a ping of an older round says nothing
        self._probing = -1  # the round whose ping waits for the server's answer (-1: none)
        self._confirmed_at: float | None = None  # when the server confirmed it had them all
        self.fast_resends = 0
        """Windows sent again because the server had them and the stream did not answer (the
        :data:`ACK_PROBE` path), not after the whole :data:`ACK_TIMEOUT`."""
        self._drop_log = _Rate(logging.WARNING)
        self._send_wake: Any = None  # an asyncio.Event, made on the loop

    def send_samples(self, obj: Any) -> None:
        """Send one object (a packed sample buffer) to the trainer, at least once.

        Blocks while more than a few batches wait for the server's acknowledgement (the network
        cannot keep up); while disconnected it returns at once and the batch waits (bounded).

        Raises:
            TypeError: ``obj`` is not data ``tmrl.wire`` carries.
            UserError: the encoded batch is larger than the server's ``max_payload``.
            RuntimeError: the link is closed.
        """
        data = wire.encode(obj)
        nc = self._nc
        if nc is not None and nc.is_connected and len(data) > nc.max_payload:
            raise UserError(
                f"a sample batch of {len(data)} bytes exceeds the NATS server's max_payload ({nc.max_payload} "
                "bytes): raise NATS.MAX_PAYLOAD (max_payload of a server tmrl does not start) or send smaller "
                "batches"
            )
        with self._out_cv:
            if self._closed:
                raise RuntimeError("this link is closed")
            while len(self._outbox) >= SEND_WINDOW and self._is_connected and self._loop.thread.is_alive():
                self._out_cv.wait(0.5)
            self._seq += 1
            self._outbox.append((self._seq, data))
            self._outbox_bytes += len(data)
            while len(self._outbox) > self._max_store or (
                self._outbox_bytes > self._max_store_bytes and len(self._outbox) > 1
            ):
                _, old = self._outbox.popleft()
                self._outbox_bytes -= len(old)
                self.dropped += 1
                self._drop_log("worker link: %d sample batches dropped while the server was unreachable",
                               self.dropped)
        self._loop.call(self._send_wake.set)

    async def _sender(self) -> None:
        """Publish the waiting batches in order, up to :data:`SEND_WINDOW` of them (and
        :data:`SEND_WINDOW_BYTES`) before their acknowledgements: each carries a reply subject
        ``<inbox>.<seq>`` on which the stream answers. A batch leaves the outbox once it and every
        older one are acknowledged. After a reconnection, an error answer or :data:`ACK_TIMEOUT`
        seconds without any answer, every unacknowledged batch is published again, in order, with
        its message id ``<worker id>-<seq>`` (the stream's duplicate window drops the copies of
        those it had stored): per-worker order and at least once."""
        import asyncio

        subject = f"{SAMPLES_PREFIX}.{self.worker_id}"
        inbox = f"{INBOX[self._role]}.{self.worker_id}"
        subscribed_on: Any = None
        while True:
            try:
                await asyncio.wait_for(self._send_wake.wait(), 0.5)
            except asyncio.TimeoutError:
                pass
            self._send_wake.clear()
            if not self._is_connected:
                continue
            nc = self._nc
            try:
                if subscribed_on is not nc:  # nats-py subscribes again by itself after reconnections
                    await nc.subscribe(f"{inbox}.*", cb=self._on_ack)
                    subscribed_on = nc
                    self._resend_from_first()
                if self._retry_at:
                    if time.monotonic() < self._retry_at:
                        continue  # nothing published before the refused batch is again
                    self._retry_at = 0.0
                    self._resend_from_first()
                if self._inflight_seqs():
                    self._check_answers(nc)
                while self._is_connected:
                    with self._out_cv:
                        if not self._outbox:
                            break
                        first = self._outbox[0][0]
                        self._next_send = max(self._next_send, first)
                        index = self._next_send - first
                        if index >= len(self._outbox) or index >= SEND_WINDOW:
                            break
                        inflight_bytes = sum(len(d) for _, d in itertools.islice(self._outbox, 0, index))
                        seq, data = self._outbox[index]
                        if index > 0 and inflight_bytes + len(data) > SEND_WINDOW_BYTES:
                            break
                    if index == 0:
                        self._last_ack = time.monotonic()  # the timeout counts from the first in flight
                    if len(data) > nc.max_payload:
                        logger.error("worker link: dropped a sample batch larger than the server's max_payload")
                        self._next_send = seq + 1
                        self._settle(seq, ok=True)
                        continue
                    await nc.publish(subject, data, reply=f"{inbox}.{seq}",
                                     headers={"Nats-Msg-Id": f"{self.worker_id}-{seq}"})
                    self._next_send = seq + 1
                    self.transmissions += 1
                    self.max_in_flight = max(self.max_in_flight, index + 1)
            except Exception as e:  # noqa: BLE001 (kept and sent again: at least once)
                self._error_log("worker link: sample batches wait (%s: %s)", type(e).__name__, e)
                self._resend_from_first()
                await asyncio.sleep(0.2)
                self._send_wake.set()

    def _check_answers(self, nc: Any) -> None:
        """Batches are in flight: send them again when the stream is not answering (on the loop).

        After :data:`ACK_PROBE` seconds without an answer, the server is asked (a ping) whether it
        has every batch in flight. Once it said so, the batches are sent again when the stream
        still answered none :data:`ACK_CONFIRMED_WAIT` seconds later: a stream whose leader was
        killed drops what it was given, and its new leader is elected within seconds. While the
        ping is unanswered the link is still carrying the batches (a slow link) and nothing is
        sent again, for at most :data:`PING_TIMEOUT` seconds (a connection that silent is dead:
        nats-py's own pings end it, and the reconnection sends everything again). Without a
        ping (an answer came, then silence), everything again after :data:`ACK_TIMEOUT` seconds."""
        import asyncio

        now = time.monotonic()
        silent = now - self._last_ack
        if self._probing == self._probe_round:
            return  # the server has not read everything yet (or nats-py's own pings will find it gone)
        if self._confirmed_at is not None and now - self._confirmed_at > ACK_CONFIRMED_WAIT:
            self._error_log("worker link: the server has the %d batches in flight and the stream answered none "
                            "for %.1f s (a new stream leader?): sent again", len(self._inflight_seqs()), silent)
            self.fast_resends += 1
            self._resend_from_first()
        elif silent > ACK_TIMEOUT:
            self._error_log("worker link: no acknowledgement for %.0f s: the %d batches in flight are "
                            "sent again", ACK_TIMEOUT, len(self._inflight_seqs()))
            self._resend_from_first()
        elif silent > ACK_PROBE and self._confirmed_at is None and self._probing != self._probe_round:
            self._probing = self._probe_round
            asyncio.ensure_future(self._ask_server(nc, self._probe_round))

    async def _ask_server(self, nc: Any, round_: int) -> None:
        """Ping the server: its answer comes once it has read everything published before. An
        answer of an earlier round (an acknowledgement or a resend came since) says nothing."""
        try:
            await nc.flush(timeout=PING_TIMEOUT)
        except Exception as e:  # noqa: BLE001 (no answer: sent again, as after ACK_TIMEOUT)
            logger.debug("worker link: the server did not answer a ping (%s)", e)
            if self._probing == round_:
                self._probing = -1
                self._last_ack = min(self._last_ack, time.monotonic() - ACK_TIMEOUT)  # resent now
            self._send_wake.set()
            return
        if self._probing == round_ and round_ == self._probe_round:
            self._probing = -1
            self._confirmed_at = time.monotonic()
        self._send_wake.set()

    def _on_disconnected(self) -> None:
        # nats-py replays on reconnection what it had not written to the lost socket yet: sample
        # batches published then would overtake older ones lost in the socket. They are dropped
        # here; the sender publishes every unacknowledged batch again, in order.
        nc = self._nc
        if nc is not None and isinstance(getattr(nc, "_pending", None), list):
            nc._pending = []
            nc._pending_data_size = 0

    def _inflight_seqs(self) -> range:
        with self._out_cv:
            first = self._outbox[0][0] if self._outbox else self._next_send
            return range(first, max(first, self._next_send))

    def _resend_from_first(self) -> None:
        """Publish again every batch not acknowledged yet, from the oldest (on the loop)."""
        with self._out_cv:
            self._next_send = self._outbox[0][0] if self._outbox else self._seq + 1
        self._last_ack = time.monotonic()
        self._probe_round += 1
        self._confirmed_at = None
        if self._send_wake is not None:
            self._send_wake.set()

    async def _on_ack(self, msg: Any) -> None:
        """The stream's answer to the publication of batch ``<seq>`` (the last token of the subject)."""
        try:
            seq = int(msg.subject.rsplit(".", 1)[1])
        except ValueError:
            return
        ok = False
        error = ""
        if msg.headers and msg.headers.get("Status"):  # e.g. 503: no responders (JetStream not ready)
            error = f"status {msg.headers.get('Status')} {msg.headers.get('Description', '')}".strip()
        else:
            try:
                answer = json.loads(msg.data or b"{}")
                ok = isinstance(answer, dict) and "stream" in answer and "error" not in answer
                error = "" if ok else str(answer.get("error") if isinstance(answer, dict) else answer)
            except ValueError as e:
                error = f"an answer that is not JSON ({e})"
        if ok:
            self._settle(seq, ok=True)
        else:
            self._error_log("worker link: the stream refused sample batch %d (%s); sent again", seq, error)
            self._retry_at = time.monotonic() + 0.2  # every unacknowledged one, from the oldest, soon
            self._send_wake.set()

    def _settle(self, seq: int, ok: bool) -> None:
        """Batch ``seq`` is stored: the acknowledged head of the outbox leaves it."""
        with self._out_cv:
            self._last_ack = time.monotonic()
            self._confirmed_at = None  # the stream answers
            self._probe_round += 1
            if not self._outbox or seq < self._outbox[0][0]:
                return  # an older copy's answer
            self._acked.add(seq)
            while self._outbox and self._outbox[0][0] in self._acked:
                done, data = self._outbox.popleft()
                self._acked.discard(done)
                self._outbox_bytes -= len(data)
                self.published += 1
            first = self._outbox[0][0] if self._outbox else self._seq + 1
            self._acked = {s for s in self._acked if s >= first}
            self._out_cv.notify_all()
        self._send_wake.set()

    def _flush(self, budget: float) -> None:
        deadline = time.monotonic() + budget
        with self._out_cv:
            while self._outbox and self._is_connected and time.monotonic() < deadline:
                self._out_cv.wait(min(0.2, max(deadline - time.monotonic(), 0.01)))


class _SampleReceiver(_NatsLink):
    """The trainer's end of the samples channel (mixed into the trainer's link)."""

    def _init_receiver(self, ack_wait: float) -> None:
        """The receiving side's state (before the connection starts)."""
        self._inbox: collections.deque[Any] = collections.deque()
        self._inbox_lock = threading.Lock()
        self._ack_wait = float(ack_wait)
        self._stalled = False
        self._psub: Any = None
        self._js: Any = None
        self._last_seq: int | None = None
        self.dropped = 0
        """Batches the stream discarded (its bounds) before this trainer got them (not those in
        flight when a connection dropped: the stream still holds them and delivers them again)."""
        self.acked = 0
        """Batches acknowledged (and confirmed by the server)."""
        self._room: Any = None  # an asyncio.Event, made on the loop
        self._drop_log = _Rate(logging.WARNING)

    async def _open_consumer(self, js: Any, first: bool) -> None:
        """Create the durable pull consumer of the samples stream, or resume the existing one
        (``first``: this link's first connection)."""
        import nats.js.errors as jse
        from nats.js import api

        config = api.ConsumerConfig(
            durable_name=CONSUMER,
            ack_policy=api.AckPolicy.EXPLICIT,
            ack_wait=self._ack_wait,
            deliver_policy=api.DeliverPolicy.ALL,
            filter_subject=f"{SAMPLES_PREFIX}.>",
            max_ack_pending=4 * RECEIVE_WINDOW,
            max_deliver=-1,
        )
        try:
            info = await js.consumer_info(self._stream, CONSUMER)
        except jse.NotFoundError:
            info = None
        if info is not None and first and (info.num_ack_pending or 0) > 0:
            # A trainer that died holding batches: they go to this one now, not after ack_wait.
            # Acknowledged batches left the (work-queue) stream, so the new consumer starts at the
            # first batch no trainer acknowledged.
            logger.info("trainer link: %d sample batches a previous trainer did not acknowledge are delivered "
                        "again", info.num_ack_pending)
            await js.delete_consumer(self._stream, CONSUMER)
            info = None
        if info is None:
            await js.add_consumer(self._stream, config)
            if first:
                self._last_seq = None  # batches acknowledged before left the stream: no gap to count
        elif first:
            self._last_seq = info.delivered.stream_seq if info.delivered is not None else None

    async def _bind_consumer(self, js: Any) -> None:
        """Subscribe to the consumer (once: nats-py binds it again after reconnections)."""
        if self._psub is None:
            self._psub = await js.pull_subscribe_bind(
                durable=CONSUMER, stream=self._stream, inbox_prefix=(INBOX["trainer"] + ".").encode()
            )

    async def _fetcher(self) -> None:
        import asyncio

        import nats.errors

        while True:
            with self._inbox_lock:
                room = RECEIVE_WINDOW - len(self._inbox)
            if room <= 0 or not self._is_connected or self._psub is None:
                self._room.clear()
                try:
                    await asyncio.wait_for(self._room.wait(), 1.0)
                except asyncio.TimeoutError:
                    pass
                continue
            try:
                msgs = await self._psub.fetch(batch=room, timeout=1.0)
            except (nats.errors.TimeoutError, asyncio.TimeoutError):
                continue
            except Exception as e:  # noqa: BLE001 (a disconnection: fetched again after it)
                if self._closed:
                    return
                self._error_log("trainer link: fetching samples failed (%s: %s)", type(e).__name__, e)
                await asyncio.sleep(0.2)
                continue
            kept = []
            for m in msgs:
                try:
                    seq = m.metadata.sequence.stream
                except Exception as e:  # noqa: BLE001 (not a JetStream message: ignore it)
                    logger.debug("trainer link: ignored a message that is not from the stream (%s)", e)
                    continue
                if self._last_seq is not None and seq > self._last_seq + 1 and m.metadata.num_delivered == 1:
                    gap = await self._discarded(self._last_seq + 1, seq - 1)
                    if gap:
                        self.dropped += gap
                        self._drop_log("trainer link: the samples stream discarded %d batches (its bounds); "
                                       "%d so far", gap, self.dropped)
                self._last_seq = max(self._last_seq or 0, seq)
                kept.append(m)
            with self._inbox_lock:
                self._inbox.extend(kept)

    async def _discarded(self, first: int, last: int) -> int:
        """How many of the stream's batches ``first..last``, skipped by a delivery, the stream no
        longer holds. It discards the oldest, so those are the ones below its first sequence; the
        others were in flight when a connection dropped and come again after ``ack_wait``. The
        whole span when the stream cannot be asked."""
        try:
            held_from = (await self._js.stream_info(self._stream)).state.first_seq
        except Exception as e:  # noqa: BLE001 (disconnected again: count the span, as before)
            logger.debug("trainer link: stream state unknown (%s): the skipped batches count as discarded", e)
            return last - first + 1
        return max(0, min(last, held_from - 1) - first + 1)

    async def _keep_alive(self) -> None:
        """Tell the server the batches waiting in this process are being worked on, so that it
        does not deliver them again while the trainer is busy."""
        import asyncio

        while True:
            await asyncio.sleep(max(self._ack_wait / 3, 0.5))
            with self._inbox_lock:
                held = list(self._inbox)
            for m in held:
                try:
                    await m.in_progress()
                except Exception as e:  # noqa: BLE001 (acknowledged meanwhile, or disconnected)
                    logger.debug("trainer link: in-progress not sent (%s)", e)

    def receive_samples(self) -> list[Any]:
        """Every object received since the last call, oldest first; never blocks. The batches
        returned are acknowledged now (they reached this process). Batches that cannot be decoded
        are logged, acknowledged and skipped."""
        if self._stalled:
            return []
        with self._inbox_lock:
            msgs = list(self._inbox)
            self._inbox.clear()
        if not msgs:
            return []
        out = []
        for m in msgs:
            try:
                out.append(wire.decode(m.data))
            except Exception as e:  # noqa: BLE001 (one bad object must not lose the others)
                logger.error("dropped a sample batch that could not be decoded: %s", e)
        self._loop.call(self._schedule_acks, msgs)
        return out

    def _schedule_acks(self, msgs: list[Any]) -> None:
        import asyncio

        asyncio.ensure_future(self._ack(msgs))
        self._room.set()

    async def _ack(self, msgs: list[Any]) -> None:
        try:
            for m in msgs:
                await m.ack()
            await self._nc.flush(timeout=5)  # the server has them once the flush returns
            self.acked += len(msgs)
        except Exception as e:  # noqa: BLE001 (lost with the connection: delivered again, at least once)
            self._error_log("trainer link: acknowledgements lost (%s: %s)", type(e).__name__, e)
