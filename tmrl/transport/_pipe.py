"""Messages between a link (or relay) object and its network process, over the process's pipes.

A message is a 9-byte header (kind: uint8, length: uint64 little-endian) and ``length`` bytes.
Payloads are read into buffers of exactly the announced size (after checking it against a limit),
so big objects cost one allocation and no re-copying.
"""

from __future__ import annotations

import os
import struct
import threading

HEADER = struct.Struct("<BQ")

# parent -> network process
CONFIG, SEND, CREDIT, STOP = 1, 2, 3, 4
# network process -> parent
READY, OBJ, STATUS, LOG, CLOSED = 10, 11, 12, 13, 14


class PipeClosed(Exception):
    """The other end of the pipe is gone."""


def read_exact(fd: int, n: int) -> bytearray:
    """Read exactly ``n`` bytes from ``fd`` into a new bytearray.

    Raises:
        PipeClosed: end of file before ``n`` bytes.
    """
    buf = bytearray(n)
    view = memoryview(buf)
    got = 0
    while got < n:
        k = os.readv(fd, [view[got:]])
        if k == 0:
            raise PipeClosed()
        got += k
    view.release()
    return buf


def read_message(fd: int, max_len: int) -> tuple[int, bytearray]:
    """Read one message; its payload must be at most ``max_len`` bytes.

    Raises:
        PipeClosed: the writer closed the pipe, or announced a payload above ``max_len``.
    """
    kind, length = HEADER.unpack(read_exact(fd, HEADER.size))
    if length > max_len:
        raise PipeClosed(f"pipe message of {length} bytes exceeds {max_len}")
    return kind, read_exact(fd, length) if length else bytearray()


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
