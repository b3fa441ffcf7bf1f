"""The :class:`Server`: the relay between one trainer and the workers."""

from __future__ import annotations

import logging
import os
from pathlib import Path
from typing import ClassVar

from tmrl.config.settings import NetSettings
from tmrl.distributed._common import FROM_CONFIG, LOGGER_NAME, _given, _given_keep_none, _settings
from tmrl.util import show_progress_on_console

logger = logging.getLogger(LOGGER_NAME)


class Server:
    """The central relay: one :class:`Trainer` and up to ``max_workers`` :class:`RolloutWorker`
    connect to it. It forwards samples to the trainer and the trainer's weights to every worker
    (the latest weights also to workers that connect later).

    The relay runs in a child process from construction until :meth:`stop` or the end of this
    process: a ``Server`` that is not kept in a variable keeps running.

    Args:
        port: public port (``PORT`` in the config when ``None``).
        password: shared password (``PASSWORD``).
        local_port: accepted for compatibility with tmrl 0.7, unused.
        header_size: tlspyo header size in bytes (``HEADER_SIZE``); the same on every process.
        security: ``"TLS"`` or ``None`` for plain TCP (``SECURITY`` by default).
        keys_dir: folder holding ``key.pem`` and ``certificate.pem`` (``CREDENTIALS_DIRECTORY``).
        max_workers: most workers at once; ``None`` or negative for no limit (``NB_WORKERS``).
        settings: the :class:`~tmrl.config.settings.NetSettings` the ``None`` arguments are read
            from (default: derived from ``config.json`` when the server is built).

    Raises:
        UserError: the port cannot be bound, TLS credentials are missing, or plain TCP is refused.
    """

    # why: keeps every Server reachable until stop(), so that a Server() not kept in a variable runs on
    _alive: ClassVar[list[Server]] = []

    def __init__(
        self,
        port: int | None = None,
        password: str | None = None,
        local_port: int | None = None,
        header_size: int | None = None,
        security: str | None = FROM_CONFIG,
        keys_dir: str | os.PathLike[str] | None = None,
        max_workers: int | None = FROM_CONFIG,
        *,
        settings: NetSettings | None = None,
    ):
        from tmrl.transport import BACKENDS

        show_progress_on_console()
        cfg = _settings(settings)
        port = int(_given(port, cfg.port))
        password = _given(password, cfg.password)
        header_size = int(_given(header_size, cfg.header_size))
        security = _given_keep_none(security, cfg.security)
        keys_dir = _given(keys_dir, cfg.credentials_directory)
        max_workers = _given_keep_none(max_workers, cfg.max_workers)
        if max_workers is not None and int(max_workers) < 0:
            max_workers = None
        self.port = port
        from tmrl.transport.credentials import TRAINER_PUBLIC_KEY_FILE

        self._relay = BACKENDS[cfg.transport].relay(
            port=port,
            password=password,
            local_port=local_port,
            header_size=header_size,
            security=security,
            keys_dir=str(keys_dir) if keys_dir is not None else None,
            max_workers=max_workers,
            trainer_key_file=Path(keys_dir) / TRAINER_PUBLIC_KEY_FILE if keys_dir is not None else None,
            **cfg.link_options(),
            **cfg.relay_options(),
            **cfg.transport_options("relay"),
        )
        Server._alive.append(self)
        logger.info("server listening on port %d (%s)", port, "TLS" if security else "plain TCP")

    @property
    def running(self) -> bool:
        """Whether the relay process is running."""
        return bool(self._relay.running)

    def stop(self, timeout: float = 15.0) -> None:
        """Stop the relay (idempotent): it may flush for up to ``timeout`` seconds, then it is
        killed."""
        self._relay.stop(timeout)
        if self in Server._alive:
            Server._alive.remove(self)

    def __enter__(self) -> Server:
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()


# ================================================================================================
# Trainer side
