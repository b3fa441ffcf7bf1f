"""The NATS backend's server: :class:`NatsRelay`, a supervised local ``nats-server -js`` (or nothing,
given the URLs of an existing NATS cluster) with the roles' users, the samples stream and the
weights buckets. The process itself is run by :class:`tmrl.transport._nats_server.ServerProcess`.
"""

from __future__ import annotations

import logging
import os
import ssl
import tempfile
import threading
from pathlib import Path
from typing import Any

from tmrl.errors import UserError
from tmrl.transport._nats_server import (
    DEFAULT_MAX_PAYLOAD,
    INBOX,
    ServerProcess,
    role_credentials,
    users_block,
)
from tmrl.transport.credentials import CERT_FILE, DEFAULT_HOSTNAME, KEY_FILE
from tmrl.transport.jetstream.connect import _check_tls_mode, _require_client, _urls
from tmrl.transport.jetstream.layout import (
    DEFAULT_BUCKET,
    DEFAULT_MAX_BYTES,
    DEFAULT_MAX_MSGS,
    DEFAULT_STREAM,
    _check_names,
    _ensure_layout,
)

logger = logging.getLogger("tmrl.transport.nats")


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
            # A client whose machine vanished is dropped within about 45 s (the default, 2 minutes
            # and two pings, takes 6): every role notices a vanished peer within a minute.
            "ping_interval": "15s",
            "ping_max": 2,
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
