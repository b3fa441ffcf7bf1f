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
module imports neither ``nats`` nor starts anything: ``pip install "tmrl[nats]"`` brings both the
client and the ``nats-server`` program. See docs/scale-out.md.

**Bounds.** The samples stream keeps at most ``max_msgs`` batches and ``max_bytes`` bytes and
discards the **oldest** beyond them (discard-old): real-time workers never block on a trainer that
fell behind or is down, the trainer gets the freshest samples, and the trainer link counts what
was dropped (:attr:`NatsTrainerLink.dropped`, from the gaps in stream sequence numbers). This is
the contract's "beyond their bounds the oldest batches are dropped and counted".
"""

from __future__ import annotations

import collections
import concurrent.futures
import itertools
import json
import logging
import os
import re
import secrets
import ssl
import tempfile
import threading
import time
from pathlib import Path
from typing import Any
from urllib.parse import urlsplit

from tmrl import wire
from tmrl.errors import UserError
from tmrl.transport._nats_server import (
    DEFAULT_MAX_PAYLOAD,
    INBOX,
    NOTIFY_PREFIX,
    SAMPLES_PREFIX,
    ServerProcess,
    role_credentials,
    users_block,
    write_credentials,
)
from tmrl.transport._process import LOCAL_HOSTS, check_server_address
from tmrl.transport.credentials import CERT_FILE, DEFAULT_HOSTNAME, KEY_FILE

logger = logging.getLogger("tmrl.transport.nats")

__all__ = ["NatsRelay", "NatsTrainerLink", "NatsWorkerLink", "write_credentials"]

DEFAULT_STREAM = "tmrl-samples"
DEFAULT_BUCKET = "tmrl-weights"
DEFAULT_MAX_BYTES = 2**30
DEFAULT_MAX_MSGS = 100_000
CONSUMER = "tmrl-trainer"
WEIGHTS_OBJECT = "actor"
LATEST_KEY = "latest"
SEND_WINDOW = 64
"""A worker publishes up to this many batches before the server acknowledged the first of them
(the publications are pipelined), and ``send_samples`` blocks while this many wait."""
SEND_WINDOW_BYTES = 32 * 2**20
"""... and at most this many bytes of them (at least one batch, whatever its size)."""
ACK_TIMEOUT = 5.0
"""Seconds without any acknowledgement of the in-flight batches after which they are all sent
again (in order, with the same message ids: the stream deduplicates them)."""
RECEIVE_WINDOW = 64
"""The trainer link holds at most this many unacknowledged batches (fetched, not yet returned)."""
_NAME = re.compile(r"[A-Za-z0-9_-]{1,64}")
WEIGHTS_POLL = 2.0
"""Seconds between a worker's checks for new weights when it hears no announcement."""


class _Rate:
    """Logs one line per ``period`` seconds at most (with the count of the ones held back)."""

    def __init__(self, level: int, period: float = 10.0):
        self.level, self.period, self.last, self.held = level, period, 0.0, 0

    def __call__(self, msg: str, *args: Any) -> None:
        now = time.monotonic()
        if now - self.last >= self.period:
            extra = f" ({self.held} more like it)" if self.held else ""
            logger.log(self.level, msg + extra, *args)
            self.last, self.held = now, 0
        else:
            self.held += 1


class _Loop:
    """An asyncio event loop running in a daemon thread."""

    def __init__(self, name: str):
        import asyncio

        self.loop = asyncio.new_event_loop()
        self.thread = threading.Thread(target=self._run, daemon=True, name=name)
        self.thread.start()

    def _run(self) -> None:
        import asyncio

        asyncio.set_event_loop(self.loop)
        try:
            self.loop.run_forever()
        finally:
            tasks = asyncio.all_tasks(self.loop)
            for t in tasks:
                t.cancel()
            if tasks:
                self.loop.run_until_complete(asyncio.gather(*tasks, return_exceptions=True))
            self.loop.close()

    def submit(self, coro: Any) -> concurrent.futures.Future[Any]:
        """Run ``coro`` on the loop; a future of its result."""
        import asyncio

        return asyncio.run_coroutine_threadsafe(coro, self.loop)

    def call(self, fn: Any, *args: Any) -> None:
        """Call ``fn(*args)`` on the loop's thread, soon."""
        if not self.loop.is_closed():
            try:
                self.loop.call_soon_threadsafe(fn, *args)
            except RuntimeError:  # closed meanwhile
                pass

    def stop(self, timeout: float) -> None:
        """Cancel every task, stop the loop and join its thread."""
        self.call(self.loop.stop)
        self.thread.join(max(timeout, 0.1))


def _urls(server_ip: str, server_port: int, urls: Any) -> list[str]:
    if urls:
        items = [u.strip() for u in urls.split(",")] if isinstance(urls, str) else [str(u).strip() for u in urls]
        items = [u for u in items if u]
        for u in items:
            parts = urlsplit(u)
            if parts.scheme not in ("nats", "tls") or not parts.hostname:
                raise UserError(
                    f"NATS.URLS: {u!r} is not a NATS server URL (nats://host:4222 or tls://host:4222)"
                )
        if items:
            return items
    check_server_address(server_ip, server_port)
    host = f"[{server_ip}]" if ":" in server_ip else server_ip
    return [f"nats://{host}:{server_port}"]


def _require_client() -> None:
    """Raise a one-line error when the NATS client library is not installed."""
    import importlib.util

    if importlib.util.find_spec("nats") is None:
        raise UserError('TRANSPORT "nats" needs the NATS client: pip install "tmrl[nats]"')


def _check_names(stream: str, bucket: str) -> None:
    for key, name in (("NATS.STREAM", stream), ("NATS.BUCKET", bucket)):
        if not isinstance(name, str) or not _NAME.fullmatch(name):
            raise UserError(f"{key} must be letters, digits, - and _ only, not {name!r}")


def _check_tls_mode(tls: str) -> str:
    mode = str(tls).strip().lower()
    if mode not in ("auto", "on", "off"):
        raise UserError(f'NATS.TLS must be "auto", "on" or "off", not {tls!r}')
    return mode


def _client_tls(urls: list[str], security: str | None, tls: str, keys_dir: Any, hostname: str,
                allow_plain_tcp: bool) -> tuple[ssl.SSLContext | None, str | None]:
    """The TLS context (or None) of a link, and the host name its certificate is checked against."""
    mode = _check_tls_mode(tls)
    remote = [u for u in urls if (urlsplit(u).hostname or "") not in LOCAL_HOSTS]
    wants = mode == "on" or security == "TLS" or any(u.startswith("tls://") for u in urls)
    if mode == "auto" and remote:
        wants = True
    if mode == "off":
        wants = False
    if not wants:
        if remote and not allow_plain_tcp:
            raise UserError(
                f"plain TCP to {remote[0]} is refused: turn TLS on (NATS.TLS \"on\" or \"auto\"), or allow plain "
                "TCP explicitly on a trusted network (\"ALLOW_PLAIN_TCP\": true)"
            )
        return None, None
    cert = Path(keys_dir) / CERT_FILE if keys_dir is not None else None
    if cert is not None and cert.is_file():
        ctx = ssl.create_default_context(cafile=str(cert))
        return ctx, hostname  # tmrl's self-signed certificate names ``hostname``
    return ssl.create_default_context(), None  # a cluster with certificates the system trusts


def _stream_config(stream: str, max_bytes: int, max_msgs: int, replicas: int = 1) -> Any:
    from nats.js import api

    return api.StreamConfig(
        name=stream,
        subjects=[f"{SAMPLES_PREFIX}.>"],
        retention=api.RetentionPolicy.WORK_QUEUE,  # an acknowledged batch leaves the stream
        max_msgs=max_msgs,
        max_bytes=max_bytes,
        discard=api.DiscardPolicy.OLD,
        storage=api.StorageType.FILE,
        duplicate_window=120.0,
        num_replicas=replicas,
    )


async def _ensure_layout(js: Any, stream: str, bucket: str, max_bytes: int, max_msgs: int,
                         replicas: int = 1) -> None:
    """Create (or bring up to date) the samples stream and the weights buckets."""
    import nats.js.errors as jse
    from nats.js import api

    cfg = _stream_config(stream, max_bytes, max_msgs, replicas)
    try:
        await js.add_stream(cfg)
    except jse.BadRequestError:  # exists with another configuration (e.g. other bounds)
        await js.update_stream(cfg)
    try:
        await js.create_key_value(bucket=bucket, history=1, storage=api.StorageType.FILE, replicas=replicas)
    except jse.BadRequestError:
        await js.key_value(bucket)
    try:
        await js.create_object_store(bucket=bucket, storage=api.StorageType.FILE, replicas=replicas)
    except jse.BadRequestError:
        await js.object_store(bucket)


class _NatsLink:
    """What the worker's and the trainer's links share: the loop thread, the connection, its
    state, closing."""

    _role = ""

    def __init__(
        self,
        server_ip: str,
        server_port: int,
        password: str,
        local_port: int | None = None,
        header_size: int = 10,
        security: str | None = "TLS",
        keys_dir: Any = None,
        hostname: str = DEFAULT_HOSTNAME,
        max_frame_bytes: int | None = None,
        allow_pickle: bool = False,
        *,
        allow_plain_tcp: bool = False,
        urls: Any = None,
        credentials: str | os.PathLike[str] | None = None,
        tls: str = "auto",
        stream: str = DEFAULT_STREAM,
        bucket: str = DEFAULT_BUCKET,
        max_bytes: int = DEFAULT_MAX_BYTES,
        max_msgs: int = DEFAULT_MAX_MSGS,
        replicas: int = 1,
        recon_delay: float = 0.5,
        trainer_key: Any = None,
    ):
        _require_client()
        self._urls = _urls(server_ip, server_port, urls)
        self._tls, self._tls_hostname = _client_tls(
            self._urls, security, tls, keys_dir, hostname, allow_plain_tcp
        )
        self._user, self._password = role_credentials(self._role, password, credentials, keys_dir)
        if allow_pickle:
            logger.warning("the nats transport never uses pickle: ALLOW_PICKLE has no effect on it")
        _check_names(stream, bucket)
        self._stream, self._bucket = stream, bucket
        self._max_bytes, self._max_msgs, self._replicas = int(max_bytes), int(max_msgs), int(replicas)
        self._recon_delay = float(recon_delay)
        self._state_cv = threading.Condition()
        self._is_connected = False
        self._closed = False
        self.refused: str | None = None
        """The server's last refusal (e.g. a wrong password or a permission error), or None."""
        self.connect_failures = 0
        """Failed connection attempts so far (the link keeps trying)."""
        self._nc: Any = None
        self._error_log = _Rate(logging.WARNING)
        self._loop = _Loop(f"tmrl-nats-{self._role}")
        self._ready: Any = None  # an asyncio.Event, made on the loop
        self._tasks: list[Any] = []
        self._loop.submit(self._start()).result(30)

    # -- the connection (on the loop) -------------------------------------------------------------

    async def _start(self) -> None:
        import asyncio

        self._ready = asyncio.Event()
        self._tasks.append(asyncio.ensure_future(self._connect()))

    async def _connect(self) -> None:
        import asyncio

        import nats

        async def on_error(e: Exception) -> None:
            text = str(e) or type(e).__name__
            if not self._is_connected:
                self.connect_failures += 1
            if "authorization" in text.lower() or "permission" in text.lower():
                self.refused = text
                self._error_log("%s link: the NATS server refused it: %s", self._role, text)
            else:
                self._error_log("%s link: %s", self._role, text)

        async def on_disconnect() -> None:
            self._set_connected(False)
            self._on_disconnected()

        async def on_reconnect() -> None:
            import asyncio

            self.refused = None
            asyncio.ensure_future(self._on_connected(reconnect=True))

        async def on_closed() -> None:
            self._set_connected(False)

        while True:
            try:
                self._nc = await self._open(nats, on_error, on_disconnect, on_reconnect, on_closed)
                break
            except Exception as e:  # noqa: BLE001 (e.g. a TLS failure: tried again, reported)
                await on_error(e)
                await asyncio.sleep(max(self._recon_delay, 0.5))
        self.refused = None
        await self._on_connected(reconnect=False)

    async def _open(self, nats: Any, on_error: Any, on_disconnect: Any, on_reconnect: Any, on_closed: Any) -> Any:
        return await nats.connect(
            servers=self._urls,
            user=self._user,
            password=self._password,
            tls=self._tls,
            tls_hostname=self._tls_hostname,
            name=f"tmrl-{self._role}",
            allow_reconnect=True,
            max_reconnect_attempts=-1,
            reconnect_time_wait=self._recon_delay,
            connect_timeout=2,
            ping_interval=5,
            max_outstanding_pings=3,
            inbox_prefix=INBOX[self._role],
            error_cb=on_error,
            disconnected_cb=on_disconnect,
            reconnected_cb=on_reconnect,
            closed_cb=on_closed,
        )

    async def _on_connected(self, reconnect: bool) -> None:
        """Role setup after a (re)connection; then the link counts as connected."""
        self._set_connected(True)

    def _on_disconnected(self) -> None:
        """Role cleanup when the connection is lost, before nats-py reconnects (on the loop)."""

    def _set_connected(self, value: bool) -> None:
        with self._state_cv:
            self._is_connected = value and not self._closed
            self._state_cv.notify_all()
        if self._ready is not None:
            (self._ready.set if self._is_connected else self._ready.clear)()

    # -- the contract -----------------------------------------------------------------------------

    @property
    def connected(self) -> bool:
        """Whether the link is connected to the NATS server right now."""
        return self._is_connected

    def wait_connected(self, timeout: float | None = None) -> bool:
        """Block until connected (True) or ``timeout`` seconds passed / the link closed (False)."""
        deadline = None if timeout is None else time.monotonic() + timeout
        with self._state_cv:
            while not self._is_connected and not self._closed:
                left = None if deadline is None else deadline - time.monotonic()
                if left is not None and left <= 0:
                    break
                self._state_cv.wait(1.0 if left is None else min(left, 1.0))
        return self._is_connected

    def close(self, timeout: float = 15.0) -> None:
        """Flush what was handed over (for at most ``timeout - 1`` seconds), disconnect and stop the
        link's thread. Idempotent."""
        if self._closed:
            return
        deadline = time.monotonic() + timeout
        self._flush(max(timeout - 1.0, 0.0))
        self._closed = True
        self._set_connected(False)
        try:
            self._loop.submit(self._shutdown()).result(max(deadline - time.monotonic() - 0.2, 0.1))
        except Exception as e:  # noqa: BLE001 (closing must not fail: the thread is stopped below anyway)
            logger.debug("%s link: closing the connection failed (%s)", self._role, e)
        self._loop.stop(max(deadline - time.monotonic(), 0.1))
        self._set_connected(False)

    def _flush(self, budget: float) -> None:
        pass

    async def _shutdown(self) -> None:
        for t in self._tasks:
            t.cancel()
        nc = self._nc
        if nc is not None and not nc.is_closed:
            try:
                if nc.is_connected:
                    await nc.flush(timeout=1)
            except Exception as e:  # noqa: BLE001
                logger.debug("%s link: last flush failed (%s)", self._role, e)
            await nc.close()

    def __enter__(self) -> Any:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class NatsWorkerLink(_NatsLink):
    """A rollout worker's connection over NATS JetStream: sends sample batches, receives the
    latest weights.

    Sample batches are published on ``tmrl.samples.<worker id>`` in order, pipelined: up to
    :data:`SEND_WINDOW` batches (:data:`SEND_WINDOW_BYTES` bytes) are in flight before the server
    acknowledged them (stored in the stream). A batch is kept until acknowledged; after a
    reconnection (or a refusal, or :data:`ACK_TIMEOUT` seconds without an answer) every
    unacknowledged batch is published again, in order, with the same message id, which the stream
    deduplicates. While disconnected, at most
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
        self._weights: bytes | None = None
        self._weights_cv = threading.Condition()
        self._version: tuple[str, int] | None = None
        self._relookup = True
        self._drop_log = _Rate(logging.WARNING)
        self._send_wake: Any = None
        self._weights_wake: Any = None
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

    # -- samples ----------------------------------------------------------------------------------

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
                if self._inflight_seqs() and time.monotonic() - self._last_ack > ACK_TIMEOUT:
                    self._error_log("worker link: no acknowledgement for %.0f s: the %d batches in flight are "
                                    "sent again", ACK_TIMEOUT, len(self._inflight_seqs()))
                    self._resend_from_first()
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

    # -- weights ----------------------------------------------------------------------------------

    def latest_weights(self, block: bool = False, timeout: float | None = None) -> bytes | None:
        """The newest weights broadcast since the last call (older unread ones dropped), or None;
        with ``block``, wait up to ``timeout`` seconds for them."""
        deadline = None if timeout is None else time.monotonic() + timeout
        with self._weights_cv:
            while block and self._weights is None and not self._closed:
                left = None if deadline is None else deadline - time.monotonic()
                if left is not None and left <= 0:
                    break
                self._weights_cv.wait(1.0 if left is None else min(left, 1.0))
            weights, self._weights = self._weights, None
        return weights

    @property
    def weights_version(self) -> tuple[str, int] | None:
        """``(store epoch, revision)`` of the last weights received, or None."""
        return self._version

    async def _weights_reader(self) -> None:
        import asyncio

        wake = self._weights_wake

        async def announced(msg: Any) -> None:
            wake.set()

        subscribed = False
        kv = obs = None
        epoch = ""
        while True:
            try:
                await asyncio.wait_for(wake.wait(), WEIGHTS_POLL)
            except asyncio.TimeoutError:
                pass
            wake.clear()
            if not self._is_connected:
                continue
            if self._relookup:
                kv, self._relookup = None, False  # looked up again after a reconnection
            try:
                if not subscribed:
                    await self._nc.subscribe(f"{NOTIFY_PREFIX}.{self._bucket}", cb=announced)
                    subscribed = True  # nats-py subscribes again by itself after reconnections
                if kv is None:
                    js = self._nc.jetstream(timeout=5)
                    kv = await js.key_value(self._bucket)
                    obs = await js.object_store(self._bucket)
                    status = await kv.status()
                    epoch = str(getattr(status.stream_info, "created", "") or "")
                await self._read_weights(kv, obs, epoch)
            except Exception as e:  # noqa: BLE001 (no bucket yet, a restart: tried again later)
                logger.debug("worker link: no weights read (%s: %s)", type(e).__name__, e)
                kv = None

    async def _read_weights(self, kv: Any, obs: Any, epoch: str) -> None:
        import asyncio

        import nats.js.errors as jse

        try:
            entry = await kv.get(LATEST_KEY)
        except jse.KeyNotFoundError:
            return
        version = (epoch, int(entry.revision))
        if self._version is not None and self._version[0] == epoch and version[1] <= self._version[1]:
            return  # never an older version over a newer one
        meta = wire.decode(bytes(entry.value or b""))
        if not (isinstance(meta, dict) and isinstance(meta.get("name"), str) and isinstance(meta.get("nuid"), str)
                and type(meta.get("size")) is int):
            logger.error("worker link: ignored a weights announcement that is not valid")
            return
        try:
            # A get whose object is deleted meanwhile (two newer broadcasts) waits forever: bounded.
            result = await asyncio.wait_for(obs.get(meta["name"]), 30.0 + meta["size"] / 1e6)
        except (asyncio.TimeoutError, jse.NotFoundError):
            self._weights_wake.set()
            return
        if result.info.nuid != meta["nuid"]:
            return  # replaced meanwhile: its own announcement follows
        try:
            weights = wire.decode(bytes(result.data))
        except Exception as e:  # noqa: BLE001 (hostile or corrupt data must not stop the reader)
            logger.error("worker link: dropped weights that could not be decoded: %s", e)
            return
        if not isinstance(weights, (bytes, bytearray)):
            logger.error("worker link: dropped a broadcast that is not weights bytes (%s)", type(weights).__name__)
            return
        self._version = version
        with self._weights_cv:
            self._weights = bytes(weights)
            self._weights_cv.notify_all()


class NatsTrainerLink(_NatsLink):
    """The trainer's connection over NATS JetStream: receives sample batches, broadcasts weights.

    The link creates (or updates) the samples stream and the weights buckets, and consumes the
    stream through the durable pull consumer ``tmrl-trainer``. It holds at most 64 fetched
    batches; :meth:`receive_samples` returns them and acknowledges them then, so a trainer killed
    before that gets them again when it restarts (a new link resumes from the last acknowledged
    batch). :meth:`broadcast_weights` returns at once; the newest weights are uploaded in the
    background (older ones not uploaded yet are skipped).

    Same arguments as :class:`NatsWorkerLink` (``credentials`` or ``keys_dir/nats/trainer.json``
    being the trainer's), plus ``ack_wait``: seconds after which the server delivers again a batch
    the trainer has not acknowledged (the link renews it while the batch waits in its hands).
    """

    _role = "trainer"

    def __init__(self, *args: Any, ack_wait: float = 30.0, **kwargs: Any):
        self._inbox: collections.deque[Any] = collections.deque()
        self._inbox_lock = threading.Lock()
        self._ack_wait = float(ack_wait)
        self._stalled = False
        self._fresh = True
        self._psub: Any = None
        self._js: Any = None
        self._last_seq: int | None = None
        self.dropped = 0
        """Batches the stream discarded (its bounds) before this trainer got them (not those in
        flight when a connection dropped: the stream still holds them and delivers them again)."""
        self.acked = 0
        """Batches acknowledged (and confirmed by the server)."""
        self.broadcasts = 0
        """Weights uploaded and announced."""
        self._pending_weights: bytes | None = None
        self._weights_lock = threading.Lock()
        self._room: Any = None
        self._weights_wake: Any = None
        self._uploading = False
        self._objects: collections.deque[str] = collections.deque()
        self._drop_log = _Rate(logging.WARNING)
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
        import nats.js.errors as jse
        from nats.js import api

        js = self._js = self._nc.jetstream(timeout=5)
        await _ensure_layout(js, self._stream, self._bucket, self._max_bytes, self._max_msgs, self._replicas)
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
        if first:
            try:
                await self._clean_objects(js)
            except Exception as e:  # noqa: BLE001 (leftovers only cost space)
                logger.debug("trainer link: old weights objects not cleaned (%s)", e)
        if self._psub is None:
            self._psub = await js.pull_subscribe_bind(
                durable=CONSUMER, stream=self._stream, inbox_prefix=(INBOX["trainer"] + ".").encode()
            )

    # -- samples ----------------------------------------------------------------------------------

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

    def _flush(self, budget: float) -> None:
        deadline = time.monotonic() + budget
        while self._is_connected and time.monotonic() < deadline:
            with self._weights_lock:
                if self._pending_weights is None and not self._uploading:
                    break
            time.sleep(0.05)

    # -- weights ----------------------------------------------------------------------------------

    def broadcast_weights(self, data: bytes) -> None:
        """Send ``data`` to every connected worker and to every worker that connects later (only
        the newest broadcast is kept). Returns at once; the upload runs in the background.

        Raises:
            TypeError: ``data`` is not bytes-like.
            RuntimeError: the link is closed.
        """
        if not isinstance(data, (bytes, bytearray, memoryview)):
            raise TypeError(f"broadcast_weights takes bytes, not {type(data).__name__}")
        if self._closed:
            raise RuntimeError("this link is closed")
        encoded = wire.encode(bytes(data))
        with self._weights_lock:
            self._pending_weights = encoded
        self._loop.call(self._weights_wake.set)

    async def _broadcaster(self) -> None:
        import asyncio

        while True:
            await self._weights_wake.wait()
            self._weights_wake.clear()
            while self._is_connected:
                with self._weights_lock:
                    data, self._pending_weights = self._pending_weights, None
                    self._uploading = data is not None
                if data is None:
                    break
                try:
                    js = self._nc.jetstream(timeout=10)
                    obs = await js.object_store(self._bucket)
                    name = f"{WEIGHTS_OBJECT}-{secrets.token_hex(8)}"
                    info = await obs.put(name, data, meta=self._object_meta(name))
                    kv = await js.key_value(self._bucket)
                    await kv.put(LATEST_KEY, wire.encode({"name": name, "nuid": info.nuid, "size": int(info.size)}))
                    await self._nc.publish(f"{NOTIFY_PREFIX}.{self._bucket}", b"")
                    self.broadcasts += 1
                    self._objects.append(name)
                    while len(self._objects) > 2:  # the previous one stays for workers reading it now
                        await self._delete_object(obs, self._objects.popleft())
                except Exception as e:  # noqa: BLE001 (kept and uploaded after the reconnection)
                    self._error_log("trainer link: uploading the weights failed (%s: %s)", type(e).__name__, e)
                    with self._weights_lock:
                        if self._pending_weights is None:
                            self._pending_weights = data
                    await asyncio.sleep(0.5)
                finally:
                    with self._weights_lock:
                        self._uploading = False

    def _object_meta(self, name: str) -> Any:
        """Chunks as large as the server allows (at most 4 MiB): fewer round trips than the
        default 128 KiB for a large actor."""
        from nats.js import api

        chunk = max(128 * 1024, min(4 * 2**20, int(self._nc.max_payload) - 64 * 1024))
        return api.ObjectMeta(name=name, options=api.ObjectMetaOptions(max_chunk_size=chunk))

    async def _delete_object(self, obs: Any, name: str) -> None:
        try:
            await obs.delete(name)
        except Exception as e:  # noqa: BLE001 (deleted already; or left for the next trainer's cleanup)
            logger.debug("trainer link: weights object %s not deleted (%s)", name, e)

    async def _clean_objects(self, js: Any) -> None:
        """Delete the weights objects a previous trainer left, except the latest."""
        import nats.js.errors as jse

        obs = await js.object_store(self._bucket)
        kv = await js.key_value(self._bucket)
        keep = None
        try:
            meta = wire.decode(bytes((await kv.get(LATEST_KEY)).value or b""))
            keep = meta.get("name") if isinstance(meta, dict) else None
        except (jse.NotFoundError, wire.DecodeError):
            pass
        try:
            listed = await obs.list()
        except jse.NotFoundError:
            return
        for info in listed:
            if info.name != keep and not info.deleted:
                await self._delete_object(obs, info.name)
        if keep:
            self._objects.append(keep)

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


class NatsRelay:
    """The NATS backend's server: a local ``nats-server -js`` started and supervised (restarted
    when it exits unexpectedly), or nothing when ``urls`` names an existing NATS cluster.

    The local server's users are the two roles (a worker may only publish samples and read the
    weights; the trainer may consume samples and write the weights), with the passwords of
    ``keys_dir/nats/*.json`` (written by ``--install``) or derived from ``password``. It creates the
    samples stream and the weights buckets. Without TLS it listens on 127.0.0.1 only (unless
    ``allow_plain_tcp``); with TLS on every interface, with tmrl's key and certificate.

    Args:
        port: client port (0: a free one; see :attr:`port`).
        password: the shared PASSWORD.
        local_port, header_size, max_workers, max_frame_bytes, allow_pickle, trainer_key_file,
            max_total_bytes, partial_timeout, max_consumables, max_consumable_bytes: accepted for
            the tlspyo relay's signature, unused (the stream's bounds are ``max_bytes`` and
            ``max_msgs``).
        security: ``"TLS"`` or None; ``tls`` ``"on"``/``"off"`` overrides it.
        keys_dir: folder of ``key.pem``, ``certificate.pem`` and ``nats/``.
        allow_plain_tcp: without TLS, listen on every interface.
        urls: an existing NATS cluster: start nothing.
        store_dir: the JetStream store's folder (None: a temporary folder, removed by :meth:`stop`).
        stream, bucket, max_bytes, max_msgs: the samples stream and weights buckets (see the module).
        replicas: accepted for the links' options; a local server is a single node (one copy).
        max_payload: the largest message the server accepts (a sample batch must fit).
        start_timeout: seconds to wait for the server to start.

    Raises:
        UserError: ``nats-server`` is not installed, the port is in use, TLS credentials are
            missing, or an argument is invalid.
    """

    def __init__(
        self,
        port: int,
        password: str,
        local_port: int | None = None,
        header_size: int = 10,
        security: str | None = "TLS",
        keys_dir: Any = None,
        max_workers: int | None = None,
        max_frame_bytes: int | None = None,
        allow_pickle: bool = False,
        *,
        allow_plain_tcp: bool = False,
        urls: Any = None,
        credentials: Any = None,
        tls: str = "auto",
        store_dir: str | os.PathLike[str] | None = None,
        stream: str = DEFAULT_STREAM,
        bucket: str = DEFAULT_BUCKET,
        max_bytes: int = DEFAULT_MAX_BYTES,
        max_msgs: int = DEFAULT_MAX_MSGS,
        max_payload: int = DEFAULT_MAX_PAYLOAD,
        replicas: int = 1,
        start_timeout: float = 30.0,
        hostname: str = DEFAULT_HOSTNAME,
        trainer_key_file: Any = None,
        max_total_bytes: Any = None,
        partial_timeout: Any = None,
        max_consumables: Any = None,
        max_consumable_bytes: Any = None,
    ):
        if type(port) is not int or not 0 <= port <= 65535:
            raise UserError(f"the server port must be an integer from 0 to 65535, not {port!r} (config key PORT)")
        _require_client()
        self._server: ServerProcess | None = None
        self._temp: tempfile.TemporaryDirectory[str] | None = None
        self._stopped = False
        self.port: int = port
        """The port the NATS server listens on (clients connect there)."""
        if urls:
            _urls("127.0.0.1", 1, urls)  # validated
            logger.info("NATS transport: using the cluster at %s (no local server started)", urls)
            return
        _check_names(stream, bucket)
        mode = _check_tls_mode(tls)
        use_tls = mode == "on" or (mode == "auto" and security == "TLS")
        users = {role: role_credentials(role, password, None, keys_dir) for role in ("worker", "trainer")}
        if store_dir is None:
            self._temp = tempfile.TemporaryDirectory(prefix="tmrl-nats-")
            folder = Path(self._temp.name)
        else:
            folder = Path(store_dir)
            folder.mkdir(parents=True, exist_ok=True)
        config: dict[str, Any] = {
            "host": "0.0.0.0" if use_tls or allow_plain_tcp else "127.0.0.1",
            "port": port or -1,
            "server_name": "tmrl",
            "max_payload": int(max_payload),
            "jetstream": {"store_dir": str(folder / "jetstream")},
            "authorization": {"users": users_block(users, stream, bucket)},
        }
        if use_tls:
            key = Path(keys_dir) / KEY_FILE if keys_dir is not None else None
            cert = Path(keys_dir) / CERT_FILE if keys_dir is not None else None
            if key is None or not key.is_file() or cert is None or not cert.is_file():
                raise UserError(
                    f"TLS needs {KEY_FILE} and {CERT_FILE} in the credentials folder ({keys_dir}); "
                    "python -m tmrl --install creates them"
                )
            config["tls"] = {"cert_file": str(cert), "key_file": str(key)}
        elif allow_plain_tcp:
            logger.warning("TLS is off: the NATS server accepts plain TCP on every interface (allowed explicitly)")
        self._server = ServerProcess(config, folder, start_timeout)
        self.port = self._server.port
        try:
            self._provision(users["trainer"], use_tls, keys_dir, hostname, stream, bucket, max_bytes, max_msgs)
        except Exception:
            self.stop()
            raise
        logger.info("NATS server listening on port %d (%s), store in %s", self.port,
                    "TLS" if use_tls else "plain TCP", folder)

    def _provision(self, trainer: tuple[str, str], use_tls: bool, keys_dir: Any, hostname: str,
                   stream: str, bucket: str, max_bytes: int, max_msgs: int) -> None:
        import asyncio

        async def run() -> None:
            import nats

            ctx = None
            if use_tls:
                ctx = ssl.create_default_context(cafile=str(Path(keys_dir) / CERT_FILE))
            nc = await nats.connect(
                servers=[f"nats://127.0.0.1:{self.port}"], user=trainer[0], password=trainer[1], tls=ctx,
                tls_hostname=hostname if use_tls else None, allow_reconnect=False, connect_timeout=5,
                inbox_prefix=INBOX["trainer"], name="tmrl-relay",
            )
            try:
                await _ensure_layout(nc.jetstream(timeout=10), stream, bucket, int(max_bytes), int(max_msgs))
            finally:
                await nc.close()

        result: dict[str, BaseException] = {}

        def target() -> None:
            try:
                asyncio.run(run())
            except BaseException as e:  # noqa: BLE001 (reported below)
                result["error"] = e

        t = threading.Thread(target=target, daemon=True, name="tmrl-nats-provision")
        t.start()
        t.join(60)
        if "error" in result:
            e = result["error"]
            raise UserError(f"could not create the NATS stream and buckets: {type(e).__name__}: {e}")

    @property
    def running(self) -> bool:
        """Whether the relay runs (a supervised local server, or the use of an external cluster)."""
        if self._stopped:
            return False
        return self._server is None or self._server.running

    @property
    def pid(self) -> int:
        """Process id of the local ``nats-server`` (-1 with an external cluster)."""
        return self._server.pid if self._server is not None else -1

    @property
    def restarts(self) -> int:
        """How many times the supervisor restarted the local server."""
        return self._server.restarts if self._server is not None else 0

    def stop(self, timeout: float = 15.0) -> None:
        """Stop the local server (it flushes its store) and free the port. Idempotent."""
        if self._stopped:
            return
        self._stopped = True
        if self._server is not None:
            self._server.stop(timeout)
        if self._temp is not None:
            self._temp.cleanup()
            self._temp = None

    def __enter__(self) -> NatsRelay:  # noqa: PYI034
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()
