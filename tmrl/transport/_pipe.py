"""Messages between a link (or relay) object and its network process, over the process's pipes.

A message is a 9-byte header (kind: uint8, length: uint64 little-endian) and ``length`` bytes.
Payloads are read into buffers of exactly the announced size (after checking it against a limit),
so big objects cost one allocation and no re-copying.
"""

from __future__ import annotations

import os
import struct
import threading
from typing import Any

HEADER = struct.Struct("<BQ")

# parent -> network process
CONFIG, SEND, CREDIT, STOP = 1, 2, 3, 4
# network process -> parent
READY, OBJ, STATUS, LOG, CLOSED = 10, 11, 12, 13, 14


def enlarge(fd: int) -> None:
    """Give a pipe a 1 MiB buffer (Linux) so that big objects cross in fewer context switches."""
    try:
        import fcntl

        fcntl.fcntl(fd, getattr(fcntl, "F_SETPIPE_SZ", 1031), 1 << 20)
    except (ImportError, OSError):
        pass  # another OS, or a system limit below 1 MiB: the default size still works


class PipeClosed(Exception):
    """The other end of the pipe is gone."""


def read_exact(f: Any, n: int) -> bytearray:
    """Read exactly ``n`` bytes from the raw (unbuffered) file ``f`` into a new bytearray.

    Raises:
        PipeClosed: end of file before ``n`` bytes.
    """
    buf = bytearray(n)
    view = memoryview(buf)
    got = 0
    try:
        while got < n:
            k = f.readinto(view[got:])  # portable (Windows too) and without an extra copy
            if not k:
                raise PipeClosed()
            got += k
    except (OSError, ValueError) as e:  # ValueError: the file was closed under us
        raise PipeClosed(str(e)) from None
    finally:
        view.release()
    return buf


def read_message(f: Any, max_len: int) -> tuple[int, bytearray]:
    """Read one message from the raw file ``f``; its payload must be at most ``max_len`` bytes.

    Raises:
        PipeClosed: the writer closed the pipe, or announced a payload above ``max_len``.
    """
    kind, length = HEADER.unpack(read_exact(f, HEADER.size))
    if length > max_len:
        raise PipeClosed(f"pipe message of {length} bytes exceeds {max_len}")
    return kind, read_exact(f, length) if length else bytearray()


class PipeWriter:
    """Thread-safe writer of whole messages to a pipe file descriptor."""

    def __init__(self, fd: int):
        self.fd = fd
        self.lock = threading.Lock()

    def send(self, kind: int, *parts: bytes | bytearray | memoryview) -> None:
        """Write one message made of ``parts``; blocks while the pipe is full.

        Raises:
            PipeClosed: the reader is gone.
        """
        total = sum(len(p) for p in parts)
        with self.lock:
            try:
                self._write_all(HEADER.pack(kind, total))
                for p in parts:
                    self._write_all(p)
            except (BrokenPipeError, OSError) as e:
                raise PipeClosed(str(e)) from None

    def _write_all(self, data: bytes | bytearray | memoryview) -> None:
        view = memoryview(data).cast("B")
        while len(view):
            k = os.write(self.fd, view)
            view = view[k:]
