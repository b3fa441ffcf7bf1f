"""The relay (the tmrl server): a tlspyo-style relay in its own process."""

from __future__ import annotations

import logging
import os
from typing import Any

from tmrl.errors import UserError
from tmrl.transport import _pipe
from tmrl.transport._process import NetProcess, check_common
from tmrl.transport.credentials import CERT_FILE, KEY_FILE

logger = logging.getLogger(__name__)

DEFAULT_MAX_FRAME_BYTES = 64 * 2**20
DEFAULT_MAX_OBJECT_BYTES = 2**30
DEFAULT_MAX_TOTAL_BYTES = 3 * 2**29  # 1.5 GiB
DEFAULT_MAX_WORKERS = 64


class RelayServer:
    """The relay between workers and the trainer, running in a child process.

    It accepts the groups ``workers`` (at most ``max_workers``) and ``trainers`` (exactly one),
    forwards sample batches from workers to the trainer and weight broadcasts from the trainer to
    the workers, and keeps the last broadcast for workers that connect later. It never decodes a
    payload.

    The relay runs until :meth:`stop`, the end of a ``with`` block, or the exit of the process
    that created it. Losing every reference to this object does **not** stop it.

    Args:
        port: TCP port to listen on (0 picks a free one; see :attr:`port`).
        password: shared with every worker and the trainer; compared in constant time, never logged.
        local_port: ignored (tmrl 0.7 compatibility): the relay talks to this object through pipes.
        header_size: characters of the frame length header; the same on every machine.
        security: ``"TLS"`` (default) or ``None`` for plain TCP.
        keys_dir: folder with ``key.pem`` and ``certificate.pem`` (needed with TLS).
        max_workers: most workers connected at once (``None``: no limit); one more is refused.
        max_frame_bytes: a connection that announces a larger frame is closed (the relay stays up).
        allow_pickle: accepted for symmetry with the links; the relay never decodes payloads, so it
            has no effect here.
        allow_plain_tcp: with ``security=None``, listen on every interface (otherwise only on
            127.0.0.1).
        max_consumables: pending sample batches kept for the trainer. At 3/4 of it (or of
            ``max_consumable_bytes``) the relay stops reading from workers, whose sends then
            block, until the backlog is down to half; the oldest batch is dropped and counted
            only if the bound is still reached.
        max_consumable_bytes: the same bound in bytes (all pending batches together); at most
            half of ``max_total_bytes``.
        max_object_bytes: largest object (sum of its frames) accepted.
        start_timeout: seconds to wait for the relay process to start.
        handshake_timeout: a connection that has not completed the handshake (right password,
            valid groups) after this many seconds is closed.
        max_total_bytes: the relay's memory budget for sample and weight data: the backlog,
            batches sent to the trainer and not acknowledged, objects being received and the
            stored broadcasts. A connection whose next part would exceed it is closed (one log
            line a minute). Default 1.5 GiB.
        partial_timeout: a connection that leaves an object half-sent for this many seconds
            (without being held back by the relay) is closed and the parts it sent are freed.
        trainer_key_file: path of a pinned ``trainer_public_key.pem``. When that file exists (it is
            read at each trainer handshake), a trainer is accepted only if it signs the relay's
            challenge with the matching private key: anyone else with the password cannot take the
            trainer's place (and broadcast weights) while it restarts.

    Raises:
        UserError: the port cannot be bound (``"port 55555 is already in use: ..."``), TLS
            credentials are missing, or an argument is invalid.
    """

    def __init__(
        self,
        port: int,
        password: str,
        local_port: int | None = None,
        header_size: int = 10,
        security: str | None = "TLS",
        keys_dir: Any = None,
        max_workers: int | None = DEFAULT_MAX_WORKERS,
        max_frame_bytes: int = DEFAULT_MAX_FRAME_BYTES,
        allow_pickle: bool = False,
        *,
        allow_plain_tcp: bool = False,
        max_consumables: int = 1000,
        max_consumable_bytes: int = 2**30,
        max_object_bytes: int = DEFAULT_MAX_OBJECT_BYTES,
        start_timeout: float = 60.0,
        handshake_timeout: float = 30.0,
        trainer_key_file: str | os.PathLike[str] | None = None,
        max_total_bytes: int = DEFAULT_MAX_TOTAL_BYTES,
        partial_timeout: float = 60.0,
    ):
        security, folder = check_common(
            password=password,
            header_size=header_size,
            security=security,
            keys_dir=keys_dir,
            max_frame_bytes=max_frame_bytes,
            needs_key=True,
        )
        if type(port) is not int or not 0 <= port <= 65535:
            raise UserError(
                f"the server port must be an integer from 0 to 65535, not {port!r} (config key PORT)"
            )
        if max_workers is not None and (type(max_workers) is not int or max_workers < 0):
            raise UserError(f"max_workers must be a non-negative integer or None, not {max_workers!r}")
        if type(max_total_bytes) is not int or max_total_bytes < 1 << 20:
            raise UserError(
                f"the server's memory budget must be an integer of at least {1 << 20} bytes, not "
                f"{max_total_bytes!r} (config key SERVER_MEMORY_BYTES)"
            )
        if not isinstance(partial_timeout, (int, float)) or not partial_timeout > 0:
            raise UserError(
                f"partial_timeout must be a positive number of seconds, not {partial_timeout!r} "
                "(config key SERVER_PARTIAL_TIMEOUT)"
            )
        if type(max_consumables) is not int or max_consumables < 1:
            raise UserError(f"max_consumables must be a positive integer, not {max_consumables!r}")
        interface = ""
        if security is None:
            if allow_plain_tcp:
                logger.warning(
                    "TLS is off: the relay accepts plain TCP on every interface (allowed explicitly)"
                )
            else:
                interface = "127.0.0.1"
                logger.warning("TLS is off: the relay accepts plain TCP connections from this machine only")
        cfg = {
            "role": "relay",
            "port": port,
            "password": password,
            "header_size": header_size,
            "security": security,
            "keys_dir": str(folder) if folder else None,
            "key_file": str(folder / KEY_FILE) if folder else None,
            "cert_file": str(folder / CERT_FILE) if folder else None,
            "max_workers": max_workers,
            "max_frame_bytes": max_frame_bytes,
            "max_object_bytes": max_object_bytes,
            "max_consumables": max_consumables,
            "max_consumable_bytes": max_consumable_bytes,
            "interface": interface,
            "handshake_timeout": float(handshake_timeout),
            "trainer_key_file": os.fspath(trainer_key_file) if trainer_key_file is not None else None,
            "max_total_bytes": max_total_bytes,
            "partial_timeout": float(partial_timeout),
        }
        self._serving = False  # set once the port is bound: only then is an exit unexpected
        self._proc = NetProcess(cfg, self._on_message, 1 << 20, name="relay")
        info = self._proc.wait_ready(start_timeout)
        self._serving = True
        self.port: int = info["port"]
        """The port the relay listens on."""

    def _on_message(self, kind: int, payload: bytearray) -> None:
        if kind == _pipe.CLOSED and self._serving and not self._proc._stopped:
            logger.error("the relay process exited unexpectedly")

    @property
    def running(self) -> bool:
        """Whether the relay process is alive."""
        return self._proc.alive

    @property
    def pid(self) -> int:
        """Process id of the relay process."""
        return self._proc.pid

    def stop(self, timeout: float = 15.0) -> None:
        """Close every connection (after flushing), stop the relay process and free the port.

        Idempotent; returns once the process has exited.
        """
        self._proc.stop(timeout)

    def __enter__(self) -> RelayServer:  # noqa: PYI034
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()
