"""What both sides of the network process share: framing, checks, and the process plumbing.

The relay's classes live in :mod:`tmrl.transport._netrelay`, the link's in
:mod:`tmrl.transport._netlink`; :mod:`tmrl.transport._netproc` is the entry point (its
:func:`~tmrl.transport._netproc.main` opens the pipe from the parent and hands it to the relay or
the link). Importing this module imports neither Twisted nor tlspyo, nor any of those three.

The network process behind a :class:`~tmrl.transport.RelayServer` or a link.

Started as ``python -m tmrl.transport._netproc`` by :mod:`tmrl.transport._process`; it reads its
configuration from stdin (never from the command line, which other users can see), talks to its
parent through its stdin/stdout pipes (see :mod:`tmrl.transport._pipe`) and runs a Twisted
reactor. It exits when its parent asks, or when the parent's end of the pipe closes (the parent
died), so it never outlives the process that started it and never holds a port on its own.

The protocol classes extend tlspyo's (``tlspyo.server.ServerProtocol``,
``tlspyo.client.ClientProtocol``, ``tlspyo.client.TLSClientFactory``) and keep its framing: a
decimal length left-justified in ``header_size`` characters, the password (client to relay only),
then the frame. What changes:

- envelopes and frames are :mod:`tmrl.wire` data: nothing from the network is unpickled;
- receive buffers are a ``bytearray`` with a read offset (linear cost, no re-slicing);
- the password is compared with :func:`hmac.compare_digest` and never logged;
- a frame above ``max_frame_bytes`` or a malformed header closes that connection with one log line;
- objects travel as groups of frames of at most ``chunk_bytes``, reassembled by the receiving link;
  the relay forwards frames without decoding payloads and keeps the complete frame group of the
  last broadcast for links that connect later;
- queues are bounded (see docs/transport.md for the policy).

Envelopes (all ``tmrl.wire``):

- link to relay: ``(stamp, cmd, dest, obj)`` with ``cmd`` one of ``HELLO`` (``obj``: the groups),
  ``OBJ`` (``dest``: ``{group: n}``, ``n < 0`` broadcast, ``n > 0`` consumable copies; ``obj``:
  ``(msg_id, idx, count, total, chunk)``), ``NTF`` (``dest``: ``{group: credit}``), ``ACK`` (ignored);
- relay to link: ``(stamp, cmd, obj)`` with ``cmd`` one of ``HELLO``, ``WELCOME`` (the handshake
  was accepted), ``REFUSED`` (``obj``: reason),
  ``OBJ`` (``obj``: ``(key, idx, count, total, chunk, is_broadcast)``).
"""

from __future__ import annotations

import hmac
import logging
import math
import os
import signal
import struct
import threading
import time
from collections.abc import Callable
from typing import Any

from tmrl import platform

log_relay = logging.getLogger("tmrl.transport.relay")
log_link = logging.getLogger("tmrl.transport.link")

_KILLED, _CLOSED, _ALIVE, _HANDSHAKE = "KILLED", "CLOSED", "ALIVE", "HANDSHAKE"
_COMPACT_BYTES = 1 << 20


def _role_of(groups: Any) -> str:
    """The role a link plays, for messages: its relay groups in the singular (``worker``)."""
    names = {"workers": "worker", "trainers": "trainer"}
    return "/".join(names.get(g, g) for g in groups)


def _parse_length(raw: bytes) -> int | None:
    """The frame length in a tlspyo header (decimal, left-justified, space padded), or None."""
    digits = raw.rstrip(b" ")
    if not digits or not digits.isdigit() or len(digits) > 18:
        return None
    return int(digits)


def _tune(transport: Any) -> None:
    """Read in large pieces (fewer Python calls per megabyte) and detect a peer whose machine
    vanished (no FIN, no RST) within a minute on every system (:func:`tmrl.platform.keep_alive`)."""
    tcp = getattr(transport, "transport", None) or transport  # under TLS, the TCP transport
    try:
        tcp.bufferSize = 1 << 20
    except AttributeError:
        pass
    try:
        platform.keep_alive(transport.getHandle())
    except (AttributeError, OSError):
        pass  # not a TCP socket (tests with fake transports)


def session_token(password: bytes, nonce: bytes) -> bytes:
    """What a link puts where tlspyo framing puts the password: an HMAC of the relay's
    per-connection challenge under the password. The password itself never crosses the network
    (plain TCP included); a token is worth one connection only."""
    return hmac.new(password, b"tmrl session\0" + nonce, "sha256").hexdigest()[:32].encode("ascii")


def _frame(header_size: int, env: bytes, password: bytes = b"") -> bytes:
    head = str(len(env)).encode("ascii")
    return head.ljust(header_size, b" ") + password + env


class _FrameReader:
    """A linear-cost receive buffer that yields complete frames."""

    def __init__(self, header_size: int, password: bytes, max_frame_bytes: int):
        self.buf = bytearray()
        self.off = 0
        self.h = header_size
        self.pw = password
        self.max = max_frame_bytes

    def feed(self, data: bytes) -> None:
        self.buf += data

    def next_frame(self) -> bytearray | None:
        """The next complete frame's body, or None when more bytes are needed.

        Raises:
            ValueError: malformed header, wrong password or frame too large (message says which;
                never the password).
        """
        buf, off, h, p = self.buf, self.off, self.h, len(self.pw)
        if len(buf) - off < h + p:
            self._compact()
            return None
        length = _parse_length(bytes(buf[off : off + h]))
        if length is None:
            raise ValueError("invalid frame header (not tmrl framing, or a different header_size)")
        if p and not hmac.compare_digest(bytes(buf[off + h : off + h + p]), self.pw):
            raise ValueError("wrong password")
        if length > self.max:
            raise ValueError(f"frame of {length} bytes exceeds max_frame_bytes={self.max}")
        start = off + h + p
        end = start + length
        if len(buf) < end:
            self._compact()
            return None
        body = buf[start:end]  # one copy, independent of the receive buffer
        self.off = end
        return body

    def _compact(self) -> None:
        # bytearray deletes from the front in O(1) amortised; doing it only past a threshold keeps
        # the total cost linear in the bytes received.
        if self.off and (self.off == len(self.buf) or self.off >= _COMPACT_BYTES):
            del self.buf[: self.off]
            self.off = 0


def _valid_chunk(obj: Any, max_object_bytes: int) -> bool:
    """Whether ``obj`` is a well-formed ``(msg_id, idx, count, total, chunk)`` frame of a client."""
    if type(obj) is not tuple or len(obj) != 5:
        return False
    msg_id, idx, count, total, chunk = obj
    return (
        _valid_parts(idx, count, total, chunk, max_object_bytes)
        and type(msg_id) is tuple
        and len(msg_id) == 2
        and all(type(x) is int for x in msg_id)
    )


def _valid_parts(idx: Any, count: Any, total: Any, chunk: Any, max_object_bytes: int) -> bool:
    # count <= total: every frame but an empty object's carries data, which bounds the frame count.
    return (
        type(idx) is int
        and type(count) is int
        and type(total) is int
        and type(chunk) is bytes
        and 0 <= idx < count
        and 0 <= total <= max_object_bytes
        and len(chunk) <= total
        and count <= max(1, total)
    )


def stop_reactor() -> None:
    """Stop the reactor (no error when it is already stopping)."""
    from twisted.internet import reactor
    from twisted.internet.error import ReactorNotRunning

    try:
        reactor.stop()
    except ReactorNotRunning:
        pass  # already stopping


# ================================================================================================
# process plumbing

#: Seconds a network process may spend flushing when its parent is gone (or closed the pipe
#: without a STOP it could read): the parent's role must be gone within 5 s of a signal.
_PARENT_GONE_BUDGET = 1.0
_STOP = struct.Struct("<d")
_PARENT_PID = 0
_shutdown_hook: Callable[[float], None] | None = None


def _stop_budget(payload: bytes | bytearray) -> float:
    """The flush budget a STOP message carries (seconds; older parents send none)."""
    if len(payload) == _STOP.size:
        (budget,) = _STOP.unpack(payload)
        if budget >= 0:  # NaN compares False: the default below
            return float(budget)
    return math.inf


def _request_shutdown(budget: float) -> None:
    """Stop this process soon (from a signal handler or the watch thread)."""
    hook = _shutdown_hook
    if hook is None:
        raise SystemExit(0)  # still starting: nothing to flush
    from twisted.internet import reactor

    reactor.callFromThread(hook, budget)


def _parent_gone() -> bool:
    return platform.parent_changed(_PARENT_PID)


def _on_signal(signum: int, frame: Any) -> None:
    # SIGTERM: stop (flushing briefly). The parent-death signal also arrives when the thread that
    # started us exits while our parent lives on: only a changed parent means it died.
    if signum == signal.SIGTERM or _parent_gone():
        _request_shutdown(_PARENT_GONE_BUDGET)


def _watch_parent() -> None:
    """Stop when the parent dies, checked twice a second: on POSIX a second line of defence
    beside the parent-death signal; everywhere the pipe from the parent, which its death closes,
    is the first (``_control_loop``)."""
    while True:
        time.sleep(0.5)
        if _parent_gone():
            try:
                _request_shutdown(_PARENT_GONE_BUDGET)
            except SystemExit:
                os._exit(0)
            return


def _serve(shutdown: Callable[[float], None], control_loop: Callable[[], None]) -> None:
    """Run the reactor with the control thread; signals and the parent watch call ``shutdown``."""
    global _shutdown_hook
    _shutdown_hook = shutdown
    threading.Thread(target=control_loop, daemon=True, name="tmrl-control").start()
    from twisted.internet import reactor

    reactor.run(installSignalHandlers=False)


def arm_parent_watch() -> bool:
    """Make this process stop when its parent asks (SIGTERM) or dies: the signal handlers, the
    parent-death signal and the watch thread. False when the parent is gone already.

    Ctrl-C reaches the whole process group: it is ignored here, the parent decides when this
    process stops (or dies, closing its stdin), so that pending objects are flushed and no port
    stays held."""
    global _PARENT_PID
    _PARENT_PID = platform.parent_pid()
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, _on_signal)
    usr2 = getattr(signal, "SIGUSR2", None)  # POSIX: the parent-death signal (Linux arms it)
    if usr2 is not None:
        signal.signal(usr2, _on_signal)
        platform.set_parent_death_signal(usr2)
    if _parent_gone():  # died before the death signal was armed
        return False
    threading.Thread(target=_watch_parent, daemon=True, name="tmrl-parent-watch").start()
    return True
