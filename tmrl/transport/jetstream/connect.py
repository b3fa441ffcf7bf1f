"""The NATS backend's connection: the server URLs, TLS, and :class:`_NatsLink`, what the worker's
and the trainer's links share (the loop thread, the connection and its state, the reconnections,
closing). The links add their channels (:mod:`~tmrl.transport.jetstream.samples`,
:mod:`~tmrl.transport.jetstream.weights`) on top of it.
"""

from __future__ import annotations

import logging
import os
import ssl
import threading
import time
from pathlib import Path
from typing import Any
from urllib.parse import urlsplit

from tmrl.errors import UserError
from tmrl.transport._nats_server import INBOX, role_credentials
from tmrl.transport._process import LOCAL_HOSTS, check_server_address
from tmrl.transport.credentials import CERT_FILE, DEFAULT_HOSTNAME
from tmrl.transport.jetstream.bridge import _Loop, _Rate
from tmrl.transport.jetstream.layout import (
    DEFAULT_BUCKET,
    DEFAULT_MAX_BYTES,
    DEFAULT_MAX_MSGS,
    DEFAULT_STREAM,
    _check_names,
)

logger = logging.getLogger("tmrl.transport.nats")


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
        raise UserError('TRANSPORT "nats" needs the NATS client: pip install ".[nats]" in the checkout of this project')


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
        self._losses = 0  # connections lost so far: a wait notices one however soon nats-py reconnects
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
            if self._is_connected and not value:
                self._losses += 1
            self._is_connected = value and not self._closed
            self._state_cv.notify_all()
        if self._ready is not None:
            (self._ready.set if self._is_connected else self._ready.clear)()

    async def _while_connected(self, coro: Any, bound: float) -> Any:
        """``await coro`` for at most ``bound`` seconds and no longer than the connection lasts
        (a connection lost and regained meanwhile counts: what ``coro`` waited for went with it).

        Raises:
            asyncio.TimeoutError: ``bound`` passed.
            ConnectionError: the connection dropped first (``coro`` is cancelled in every case).
        """
        import asyncio

        loop = asyncio.get_running_loop()
        task = asyncio.ensure_future(coro)
        deadline = loop.time() + bound
        losses = self._losses
        try:
            while not task.done():
                if not self._is_connected or self._losses != losses:
                    raise ConnectionError("the connection dropped")
                left = deadline - loop.time()
                if left <= 0:
                    raise asyncio.TimeoutError
                await asyncio.wait({task}, timeout=min(0.2, left))
            return task.result()
        finally:
            if not task.done():
                task.cancel()

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
