"""The worker's and the trainer's connections to the relay."""

from __future__ import annotations

import collections
import logging
import pickle
import threading
import time
from typing import Any

from tmrl import wire
from tmrl.errors import UserError
from tmrl.transport import _pipe
from tmrl.transport._process import LOCAL_HOSTS, NetProcess, check_common, check_server_address
from tmrl.transport.credentials import CERT_FILE, DEFAULT_HOSTNAME
from tmrl.transport.relay import DEFAULT_MAX_FRAME_BYTES, DEFAULT_MAX_OBJECT_BYTES

logger = logging.getLogger(__name__)

CHUNK_BYTES = 4 * 2**20
CREDIT_WINDOW = 64


class _Link:
    """What WorkerLink and TrainerLink share: the network process, encoding, connection state."""

    _groups: tuple[str, ...] = ()
    _credit_window = 0

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
        max_frame_bytes: int = DEFAULT_MAX_FRAME_BYTES,
        allow_pickle: bool = False,
        *,
        allow_plain_tcp: bool = False,
        max_object_bytes: int = DEFAULT_MAX_OBJECT_BYTES,
        max_store: int = 256,
        max_store_bytes: int = 512 * 2**20,
        recon_initial_delay: float = 0.5,
        recon_max_delay: float = 5.0,
        start_timeout: float = 60.0,
        trainer_key: Any = None,
    ):
        security, folder = check_common(
            password=password,
            header_size=header_size,
            security=security,
            keys_dir=keys_dir,
            max_frame_bytes=max_frame_bytes,
            needs_key=False,
        )
        check_server_address(server_ip, server_port)
        if security is None:
            if server_ip not in LOCAL_HOSTS and not allow_plain_tcp:
                raise UserError(
                    f"plain TCP (security=None) to {server_ip} is refused: turn TLS on (\"TLS\": true in "
                    "config.json), or allow plain TCP explicitly on a trusted network (\"ALLOW_PLAIN_TCP\": true; "
                    "allow_plain_tcp=True in a script)"
                )
            logger.warning(
                "TLS is off: traffic to %s:%d is neither encrypted nor authenticated", server_ip, server_port
            )
        self._allow_pickle = bool(allow_pickle)
        if self._allow_pickle:
            logger.warning(
                "allow_pickle is on: objects received from the relay may be unpickled, which lets anyone "
                "who knows the password run code on this machine; use it on trusted networks only"
            )
        self._max_object_bytes = max_object_bytes
        self._connected = threading.Event()
        self._state_cv = threading.Condition()
        self.refused: str | None = None
        """The relay's last refusal reason (e.g. a second trainer), or None."""
        self._send_lock = threading.Lock()
        self._closed = False
        chunk = min(CHUNK_BYTES, max_frame_bytes - (1 << 16))
        cfg = {
            "role": "link",
            "groups": self._groups,
            "server_ip": server_ip,
            "server_port": server_port,
            "password": password,
            "header_size": header_size,
            "security": security,
            "cert_file": str(folder / CERT_FILE) if folder else None,
            "hostname": hostname,
            "max_frame_bytes": max_frame_bytes,
            "max_object_bytes": max_object_bytes,
            "chunk_bytes": chunk,
            "credit_window": self._credit_window,
            "max_store": max_store,
            "max_store_bytes": max_store_bytes,
            "recon_initial_delay": recon_initial_delay,
            "recon_max_delay": recon_max_delay,
            "close_timeout": 10.0,
            "trainer_key": trainer_key.private_pem if trainer_key is not None else None,
        }
        self._proc = NetProcess(cfg, self._on_message, max_object_bytes + (1 << 20), name=self._groups[0])
        self._proc.wait_ready(start_timeout)

    # -- connection state -------------------------------------------------------------------------

    @property
    def connected(self) -> bool:
        """Whether the link is connected to the relay right now."""
        return self._connected.is_set()

    def wait_connected(self, timeout: float | None = None) -> bool:
        """Block until connected (True) or ``timeout`` seconds passed / the link closed (False)."""
        deadline = None if timeout is None else time.monotonic() + timeout
        with self._state_cv:
            while not self._connected.is_set() and self._proc.alive:
                left = None if deadline is None else deadline - time.monotonic()
                if left is not None and left <= 0:
                    break
                self._state_cv.wait(left if left is None else min(left, 1.0))
        return self._connected.is_set()

    # -- encoding ---------------------------------------------------------------------------------

    def _encode(self, obj: Any) -> bytes:
        try:
            return wire.encode(obj)
        except TypeError:
            if not self._allow_pickle:
                raise
            return pickle.dumps(obj, protocol=pickle.HIGHEST_PROTOCOL)

    def _decode(self, data: bytearray) -> Any:
        if data[:4] == wire.MAGIC:
            return wire.decode(data)
        if self._allow_pickle:
            return pickle.loads(data)  # explicit opt-in for trusted networks (logged at start)
        raise wire.DecodeError(
            "received an object that is not tmrl wire data (pickle is refused unless allow_pickle is set)"
        )

    def _send(self, dest: dict[str, int], data: bytes) -> None:
        if self._closed:
            raise RuntimeError("this link is closed")
        if len(data) > self._max_object_bytes:
            raise ValueError(f"object of {len(data)} bytes exceeds max_object_bytes={self._max_object_bytes}")
        meta = wire.encode(dest)
        with self._send_lock:
            if not self._proc.send(_pipe.SEND, len(meta).to_bytes(4, "little"), meta, data):
                raise ConnectionError(f"the {self._groups[0]} network process is gone")

    # -- messages from the network process (reader thread) ----------------------------------------

    def _on_message(self, kind: int, payload: bytearray) -> None:
        if kind == _pipe.STATUS:
            status = wire.decode(payload)
            with self._state_cv:
                if status.get("connected"):
                    self._connected.set()
                    self.refused = None
                else:
                    self._connected.clear()
                    if status.get("refused"):
                        self.refused = str(status["refused"])
                self._state_cv.notify_all()
        elif kind == _pipe.OBJ:
            self._on_object(payload)
        elif kind == _pipe.CLOSED:
            with self._state_cv:
                self._connected.clear()
                self._state_cv.notify_all()
            self._on_closed()

    def _on_object(self, payload: bytearray) -> None:
        raise NotImplementedError

    def _on_closed(self) -> None:
        pass

    def close(self, timeout: float = 15.0) -> None:
        """Flush what was sent, disconnect and stop the network process; it is killed after
        ``timeout`` seconds (and flushes for at most ``timeout - 1``). Idempotent."""
        self._closed = True
        self._proc.stop(timeout)

    @property
    def pid(self) -> int:
        """Process id of the link's network process."""
        return self._proc.pid

    def __enter__(self) -> Any:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class WorkerLink(_Link):
    """A rollout worker's connection: sends sample batches, receives the latest weights.

    Args:
        server_ip: address of the relay.
        server_port: port of the relay.
        password: the relay's password.
        local_port: ignored (tmrl 0.7 compatibility): no local port is used.
        header_size: the relay's ``header_size``.
        security: ``"TLS"`` (default) or ``None`` (only to localhost, or with ``allow_plain_tcp``).
        keys_dir: folder holding ``certificate.pem`` (needed with TLS).
        hostname: the name in the relay's certificate (``"default"`` for tmrl's credentials).
        max_frame_bytes: a relay frame above this closes the connection (then it reconnects).
        allow_pickle: let objects that ``tmrl.wire`` cannot carry travel as pickle, and unpickle
            received non-wire objects. Trusted networks only; logs a warning.
        allow_plain_tcp: allow ``security=None`` to a remote relay.
        max_object_bytes: largest object sent or received.
        max_store, max_store_bytes: while disconnected, at most this many objects / bytes are kept
            for sending on reconnection; beyond that the oldest is dropped and counted.
        recon_initial_delay, recon_max_delay: reconnection delays in seconds.
        start_timeout: seconds to wait for the network process to start.

    Raises:
        UserError: invalid arguments, missing certificate, or plain TCP to a remote host.
    """

    _groups = ("workers",)

    def __init__(self, *args: Any, **kwargs: Any):
        self._weights: bytes | None = None
        self._weights_cv = threading.Condition()
        super().__init__(*args, **kwargs)

    def send_samples(self, obj: Any) -> None:
        """Send one object (typically a buffer of samples) to the trainer.

        Blocks while the network cannot keep up. While disconnected, the object is kept (bounded:
        the oldest unsent ones are dropped beyond ``max_store``) and sent on reconnection.

        Raises:
            TypeError: ``obj`` is not data ``tmrl.wire`` carries (and ``allow_pickle`` is off).
            ConnectionError: the link's network process is gone.
        """
        self._send({"trainers": 1}, self._encode(obj))

    def latest_weights(self, block: bool = False, timeout: float | None = None) -> bytes | None:
        """The newest weights broadcast since the last call, or None.

        Args:
            block: wait for new weights when none are pending.
            timeout: with ``block``, the longest wait in seconds (None: no limit).

        Returns:
            The bytes the trainer broadcast (older, unread broadcasts are dropped), or None.
        """
        deadline = None if timeout is None else time.monotonic() + timeout
        with self._weights_cv:
            while block and self._weights is None and self._proc.alive:
                left = None if deadline is None else deadline - time.monotonic()
                if left is not None and left <= 0:
                    break
                self._weights_cv.wait(left if left is None else min(left, 1.0))
            weights, self._weights = self._weights, None
        return weights

    def _on_object(self, payload: bytearray) -> None:
        try:
            obj = self._decode(payload)
        except Exception as e:  # noqa: BLE001 (hostile or corrupt data must not stop the reader)
            logger.error("dropped weights that could not be decoded: %s", e)
            return
        if not isinstance(obj, (bytes, bytearray)):
            logger.error("dropped a broadcast that is not weights bytes (%s)", type(obj).__name__)
            return
        with self._weights_cv:
            self._weights = bytes(obj)
            self._weights_cv.notify_all()

    def _on_closed(self) -> None:
        with self._weights_cv:
            self._weights_cv.notify_all()


class TrainerLink(_Link):
    """The trainer's connection: receives sample batches, broadcasts weights.

    Same arguments as :class:`WorkerLink`, plus ``trainer_key`` (keyword): a
    :class:`~tmrl.transport.credentials.TrainerKey` with which the link answers the relay's
    challenge, for relays that pin the trainer's public key. The link asks the relay for at most
    64 objects at a time and asks for more as :meth:`receive_samples` drains them, so a trainer
    that falls behind leaves the backlog at the relay (bounded by its ``max_consumables``).
    """

    _groups = ("trainers",)
    _credit_window = CREDIT_WINDOW

    def __init__(self, *args: Any, **kwargs: Any):
        self._inbox: collections.deque[bytearray] = collections.deque()
        self._inbox_lock = threading.Lock()
        super().__init__(*args, **kwargs)

    def receive_samples(self) -> list[Any]:
        """Every object received since the last call, oldest first; never blocks.

        Objects that cannot be decoded are logged and skipped.
        """
        with self._inbox_lock:
            raw = list(self._inbox)
            self._inbox.clear()
        if raw:
            self._proc.send(_pipe.CREDIT, len(raw).to_bytes(8, "little"))
        out = []
        for payload in raw:
            try:
                out.append(self._decode(payload))
            except Exception as e:  # noqa: BLE001 (one bad object must not lose the others)
                logger.error("dropped a sample batch that could not be decoded: %s", e)
        return out

    def broadcast_weights(self, data: bytes) -> None:
        """Send ``data`` (the actor's weights file) to every connected worker and to every worker
        that connects later (the relay keeps the latest broadcast).

        Raises:
            TypeError: ``data`` is not bytes-like.
            ConnectionError: the link's network process is gone.
        """
        if not isinstance(data, (bytes, bytearray, memoryview)):
            raise TypeError(f"broadcast_weights takes bytes, not {type(data).__name__}")
        self._send({"workers": -1}, wire.encode(bytes(data) if isinstance(data, memoryview) else data))

    def _on_object(self, payload: bytearray) -> None:
        with self._inbox_lock:
            self._inbox.append(payload)
