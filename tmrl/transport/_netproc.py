"""Entry point of the network process behind a :class:`~tmrl.transport.RelayServer` or a link.

Started as ``python -m tmrl.transport._netproc`` by :mod:`tmrl.transport._process` (the command
line that tests and operators recognise the process by). :func:`main` arms the parent watch,
opens the pipe from the parent, reads the configuration from it (never from the command line,
which other users can see), sends the process's logging to the parent, and hands the pipe to the
relay or the link, which read their parent's messages from it. The code lives in three modules:

- :mod:`tmrl.transport._netcommon`: framing, checks, and the process plumbing (signals, the
  parent watch, the reactor and its control thread);
- :mod:`tmrl.transport._netrelay`: the relay's classes (imported when ``cfg["role"]`` is
  ``"relay"``);
- :mod:`tmrl.transport._netlink`: the link's classes (a worker's or the trainer's connection).

This module imports them; none of them imports it. Importing it imports neither Twisted nor
tlspyo.
"""

from __future__ import annotations

import logging
import os

from tmrl import wire
from tmrl.transport import _pipe
from tmrl.transport._netcommon import (  # noqa: F401 (re-exported: their home was this module)
    _frame,
    _FrameReader,
    _parse_length,
    _tune,
    arm_parent_watch,
    session_token,
)

__all__ = ["main", "session_token"]


class _PipeLogHandler(logging.Handler):
    """Sends log records to the parent, which logs them under the same logger name."""

    def __init__(self, writer: _pipe.PipeWriter):
        super().__init__()
        self.writer = writer

    def emit(self, record: logging.LogRecord) -> None:
        try:
            msg = record.getMessage()
            if record.exc_info:
                msg += "\n" + logging.Formatter().formatException(record.exc_info)
            self.writer.send(_pipe.LOG, wire.encode((record.levelno, record.name, msg)))
        except Exception:  # noqa: BLE001, S110 (the parent is gone: no one left to tell)
            pass


def main() -> None:
    """Serve as the relay or the link the parent describes on stdin, until it says stop (or dies)."""
    if not arm_parent_watch():  # the parent died already
        return
    stdin = open(0, "rb", buffering=0, closefd=False)  # noqa: SIM115 (for the process's lifetime)
    out_fd = os.dup(1)
    os.dup2(2, 1)  # a stray print must not corrupt the pipe protocol
    writer = _pipe.PipeWriter(out_fd)
    try:
        _kind, payload = _pipe.read_message(stdin, 1 << 20)
    except _pipe.PipeClosed:
        return
    cfg = wire.decode(payload)
    root = logging.getLogger()
    root.handlers[:] = [_PipeLogHandler(writer)]
    root.setLevel(cfg["log_level"])
    from twisted.logger import STDLibLogObserver, globalLogBeginner

    logging.getLogger("tmrl.transport.twisted").setLevel(logging.WARNING)
    logging.getLogger("tlspyo").setLevel(logging.WARNING)
    globalLogBeginner.beginLoggingTo(
        [STDLibLogObserver(name="tmrl.transport.twisted")], redirectStandardIO=False
    )
    try:
        if cfg["role"] == "relay":
            from tmrl.transport._netrelay import run_relay

            run_relay(cfg, writer, stdin)
        else:
            from tmrl.transport._netlink import run_link

            run_link(cfg, writer, stdin)
    finally:
        try:
            writer.send(_pipe.CLOSED)
        except _pipe.PipeClosed:
            pass


if __name__ == "__main__":
    main()
