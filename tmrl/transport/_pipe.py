"""Messages between a link (or relay) object and its network process, over the process's pipes.

A message is a 9-byte header (kind: uint8, length: uint64 little-endian) and ``length`` bytes.
Payloads are read into buffers of exactly the announced size (after checking it against a limit),
so big objects cost one allocation and no re-copying.
"""

from __future__ import annotations

import os
import struct
import threading
import time
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


def peer_closed(f: Any) -> bool:
    """Whether the writer of the pipe ``f`` (a raw file we read) has closed its end, without
    reading from it: a network process held back (not reading its pipe) still notices that its
    parent is gone. Always ``False`` where the OS cannot tell (then the parent-death watch
    applies)."""
    try:
        fd = f.fileno()
    except (OSError, ValueError):
        return True
    import select

    if not hasattr(select, "poll"):  # Windows: ask the pipe itself
        return _windows_pipe_broken(fd)
    try:
        poller = select.poll()
        poller.register(fd, select.POLLHUP | select.POLLERR)
        return any(ev & (select.POLLHUP | select.POLLERR) for _, ev in poller.poll(0))
    except (OSError, ValueError):
        return False


def _windows_pipe_broken(fd: int) -> bool:
    try:
        import ctypes
        import msvcrt  # type: ignore[import-not-found,unused-ignore]

        handle = msvcrt.get_osfhandle(fd)
        avail = ctypes.c_ulong(0)
        ok = ctypes.windll.kernel32.PeekNamedPipe(handle, None, 0, None, ctypes.byref(avail), None)  # type: ignore[attr-defined,unused-ignore]
        return not ok
    except (ImportError, AttributeError, OSError, ValueError):
        return False


class PipeWriter:
    """Thread-safe writer of whole messages to a pipe file descriptor.

    A write interrupted half-way (an exception raised by a signal handler while the pipe was full)
    leaves the stream without a message boundary: the writer then refuses every later message
    (:class:`PipeClosed`), and the owner stops the reader by closing the pipe or by a signal.
    """

    def __init__(self, fd: int, closer: Any = None):
        self.fd = fd
        self._closer = closer  # the file object owning ``fd``, when there is one: it closes it
        self.lock = threading.Lock()
        self.broken = False
        self.closed = False

    def send(self, kind: int, *parts: bytes | bytearray | memoryview) -> None:
        """Write one message made of ``parts``; blocks while the pipe is full.

        Raises:
            PipeClosed: the reader is gone, or the writer was closed or broken.
        """
        total = sum(len(p) for p in parts)
        with self.lock:
            if self.closed or self.broken:
                raise PipeClosed("the pipe writer is closed")
            try:
                self._write_all(HEADER.pack(kind, total))
                for p in parts:
                    self._write_all(p)
            except (BrokenPipeError, OSError) as e:
                self.broken = True
                raise PipeClosed(str(e)) from None
            except BaseException:
                self.broken = True  # KeyboardInterrupt mid-message: the stream has lost its framing
                raise

    def try_send(self, kind: int, payload: bytes, timeout: float) -> bool:
        """Write one small message (at most ``select.PIPE_BUF`` bytes: all or nothing) without
        blocking longer than ``timeout`` seconds, whatever the reader does. Returns whether it was
        written."""
        data = HEADER.pack(kind, len(payload)) + payload
        if not self.lock.acquire(timeout=max(0.0, timeout)):
            return False  # another thread is stuck writing: the caller falls back to a signal
        try:
            if self.closed or self.broken:
                return False
            return self._write_before(data, time.monotonic() + timeout)
        finally:
            self.lock.release()

    def _write_before(self, data: bytes, deadline: float) -> bool:
        if not hasattr(os, "set_blocking"):  # Windows before Python 3.12: a thread that may block
            return self._write_in_thread(data, deadline)
        try:
            os.set_blocking(self.fd, False)
        except OSError:
            return False  # cannot write without risking a block: let the caller signal instead
        try:
            while True:
                try:
                    os.write(self.fd, data)  # a write of at most PIPE_BUF bytes is atomic
                    return True
                except BlockingIOError:
                    if time.monotonic() >= deadline:
                        return False
                    time.sleep(0.01)
                except OSError:
                    return False
        finally:
            try:
                os.set_blocking(self.fd, True)
            except OSError:
                pass

    def _write_in_thread(self, data: bytes, deadline: float) -> bool:
        """Write ``data`` (at most ``PIPE_BUF`` bytes: all or nothing) from a helper thread, and
        say whether it was written by ``deadline``. A write still blocked then (the reader is not
        reading) leaves the writer broken: nothing else may be written after it."""
        done = threading.Event()
        failed: list[OSError] = []

        def write() -> None:
            try:
                os.write(self.fd, data)
            except OSError as e:
                failed.append(e)
            done.set()

        threading.Thread(target=write, name="tmrl-pipe-stop", daemon=True).start()
        if done.wait(max(0.0, deadline - time.monotonic())):
            return not failed
        self.broken = True
        return False

    def close(self, timeout: float) -> bool:
        """Close the descriptor (the reader sees end of file) unless another thread is writing
        after ``timeout`` seconds (closing under a blocked writer could let it write into a
        reused descriptor). Returns whether it was closed."""
        if not self.lock.acquire(timeout=max(0.0, timeout)):
            return False
        try:
            if not self.closed:
                self.closed = True
                try:
                    self._closer() if self._closer is not None else os.close(self.fd)
                except OSError:
                    pass
            return True
        finally:
            self.lock.release()

    def _write_all(self, data: bytes | bytearray | memoryview) -> None:
        view = memoryview(data).cast("B")
        while len(view):
            k = os.write(self.fd, view)
            view = view[k:]
