# Twisted's zope interfaces and tlspyo (untyped) defeat mypy here; the logic is tested instead.
# mypy: disable-error-code="misc, has-type, arg-type, call-arg, import-untyped, list-item"
"""The network process behind a :class:`~tmrl.transport.RelayServer` or a link.

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

import collections
import hmac
import logging
import math
import os
import random
import signal
import struct
import sys
import threading
import time
from collections.abc import Callable
from typing import Any

from tmrl import wire
from tmrl.transport import _pipe
from tmrl.util import RateLimitedLog

log_relay = logging.getLogger("tmrl.transport.relay")
log_link = logging.getLogger("tmrl.transport.link")

_KILLED, _CLOSED, _ALIVE, _HANDSHAKE = "KILLED", "CLOSED", "ALIVE", "HANDSHAKE"
_STDIN: Any = None  # the raw pipe from the parent, opened by main()
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
    vanished (no FIN, no RST) within about a minute."""
    import socket

    tcp = getattr(transport, "transport", None) or transport  # under TLS, the TCP transport
    try:
        tcp.bufferSize = 1 << 20
    except AttributeError:
        pass
    try:
        sock = transport.getHandle()
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_KEEPALIVE, 1)
        if hasattr(socket, "TCP_KEEPIDLE"):
            sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_KEEPIDLE, 30)
            sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_KEEPINTVL, 10)
            sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_KEEPCNT, 3)
    except (AttributeError, OSError):
        pass  # not a TCP socket (tests with fake transports) or an OS without these options


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


# ================================================================================================
# relay


def run_relay(cfg: dict[str, Any], writer: _pipe.PipeWriter) -> None:
    import OpenSSL
    from tlspyo.server import Server as TlspyoServer
    from tlspyo.server import ServerProtocol as TlspyoServerProtocol
    from twisted.internet import reactor, ssl
    from twisted.internet.error import CannotListenError, ReactorNotRunning
    from twisted.internet.interfaces import IPushProducer
    from twisted.internet.protocol import Factory
    from zope.interface import implementer

    max_consumables = cfg["max_consumables"]
    max_total_bytes = cfg.get("max_total_bytes") or (3 * cfg["max_consumable_bytes"]) // 2
    # The backlog takes at most half of the memory budget, so that the relay holds workers back
    # (back-pressure) well before the budget bites; the other half is for objects in progress.
    max_consumable_bytes = min(cfg["max_consumable_bytes"], max_total_bytes // 2)
    partial_timeout = float(cfg.get("partial_timeout") or 60.0)

    class RelayState(TlspyoServer):
        """tlspyo's relay bookkeeping (clients, groups) with bounded queues and frame stores."""

        def __init__(self) -> None:
            groups = {
                "workers": {"max_count": cfg["max_workers"], "max_consumables": max_consumables},
                "trainers": {"max_count": 1, "max_consumables": max_consumables},
            }
            super().__init__(
                port=cfg["port"],
                password=cfg["password"],
                serializer=None,
                deserializer=None,
                accepted_groups=groups,
                header_size=cfg["header_size"],
                local_com_port=-1,
                security="TLS" if cfg["security"] == "TLS" else "TCP",
                keys_dir=cfg["keys_dir"],
            )
            for g in groups:
                self.add_group(g)  # unbounded deque; bounded by hand below so drops are counted
            self.password_bytes = cfg["password"].encode("utf-8")
            # group -> complete frame group of the last broadcast, and the one in progress
            self.complete: dict[str, list[bytes]] = {}
            self.partial: dict[str, list[Any]] = {}
            self.complete_bytes: dict[str, int] = {}
            self.dropped = 0
            self.queued_bytes = 0  # bytes of frames in the consumable queues
            self._last_log: dict[str, float] = {}
            self.connections: set[Any] = set()
            self._refusal_log: dict[tuple[str, str], float] = {}
            self.closing = False
            # Back-pressure: worker connections whose reading is paused while the samples
            # waiting for the trainer are above the high-water mark (3/4 of the bounds); read
            # again once they are back under the low-water mark (1/2).
            self.held: set[Any] = set()
            self._release_scheduled = False
            self.high_count = max(1, (3 * max_consumables) // 4)
            self.low_count = max_consumables // 2
            self.high_bytes = (3 * max_consumable_bytes) // 4
            self.low_bytes = max_consumable_bytes // 2

        def log_refusal(self, peer: str, line: str, reason: str) -> None:
            # A refused link retries every few seconds: one warning per host and reason a minute.
            key = (peer.rsplit(":", 1)[0], reason)
            now = time.monotonic()
            if now - self._refusal_log.get(key, -math.inf) > 60.0:
                self._refusal_log[key] = now
                if len(self._refusal_log) > 1000:
                    self._refusal_log.clear()
                log_relay.warning("%s", line)
            else:
                log_relay.debug("%s", line)

        def refusal(self, groups: tuple[str, ...]) -> str | None:
            for g in groups:
                if g not in self._accepted_groups:
                    return f"unknown group {g!r} (expected 'workers' or 'trainers')"
            for g in groups:
                n = len(self.group_info[g]["ids"])
                if g == "trainers" and n >= 1:
                    return "refused a second trainer: a trainer is already connected (one trainer per server)"
                max_count = self._accepted_groups[g]["max_count"]
                if g == "workers" and max_count is not None and n >= max_count:
                    return (
                        f"refused a worker: max_workers={max_count} workers are already connected "
                        "(config key NB_WORKERS)"
                    )
            return None

        def trainer_refusal(self, nonce: bytes, proof: Any) -> str | None:
            """Why a trainer is refused (``None``: accepted). With a pinned trainer public key
            (``trainer_public_key.pem``, read at each trainer handshake, so a key made after the
            relay started applies), a trainer must sign this connection's challenge with it."""
            path = cfg.get("trainer_key_file")
            pinned = None
            try:
                if path:
                    with open(path, "rb") as f:
                        pinned = f.read(1 << 16)
            except FileNotFoundError:
                pass
            except OSError as e:
                return f"refused a trainer: cannot read the pinned trainer key {path} ({e})"
            if pinned is None:
                return None
            from tmrl.transport.credentials import HANDSHAKE_CONTEXT, verify_signature

            sig = proof.get("sig") if type(proof) is dict else None
            if type(sig) is not bytes or not verify_signature(pinned, sig, HANDSHAKE_CONTEXT + nonce):
                return (
                    "refused a trainer: it does not hold the trainer key pinned in trainer_public_key.pem "
                    "(copy the trainer's trainer_public_key.pem to the server, or remove the pinned one)"
                )
            return None

        def out_frame(self, key: tuple, idx: int, count: int, total: int, chunk: bytes, bcast: bool) -> bytes:
            env = wire.encode((0, "OBJ", (key, idx, count, total, chunk, bcast)))
            return _frame(self.header_size, env)

        def broadcast_frame(
            self, group: str, key: tuple, idx: int, count: int, total: int, chunk: bytes
        ) -> None:
            out = self.out_frame(key, idx, count, total, chunk, True)
            part = self.partial.get(group)
            if idx == 0:
                part = self.partial[group] = [key, count, total, [out], len(chunk)]
            elif part is not None and part[0] == key and len(part[3]) == idx and part[1] == count:
                part[3].append(out)
                part[4] += len(chunk)
            else:
                log_relay.debug("dropped an out-of-order broadcast frame for %s", group)
                return
            if part[4] > total:
                del self.partial[group]
                return
            members = [self.to_clients[cid] for cid in self.group_info[group]["ids"]]
            if idx == 0:
                # A member still draining earlier data does not get this broadcast streamed: it
                # gets the newest one when it has caught up (resumeProducing). Without this, a
                # slow worker would make the relay buffer every broadcast for it.
                for member in members:
                    if member.paused:
                        member.stale.add(group)
                        log_relay.debug(
                            "%s is still receiving earlier data: it will get the newest broadcast when it catches up",
                            member._peer,
                        )
            for member in members:
                if group not in member.stale:
                    member.transport.write(out)
            if len(part[3]) == count:
                del self.partial[group]
                if part[4] == total:
                    self.complete[group] = part[3]
                    self.complete_bytes[group] = part[4]

        def held_bytes(self) -> int:
            """Bytes of sample and weight data this relay holds: the backlog, batches sent to the
            trainer and not yet acknowledged, objects being received, the stored broadcasts."""
            total = self.queued_bytes + sum(self.complete_bytes.values())
            total += sum(part[4] for part in self.partial.values())
            for conn in self.connections:
                total += conn.unacked_bytes + (conn._partial[5] if conn._partial is not None else 0)
            return total

        def over_budget(self, extra: int) -> bool:
            """Whether taking ``extra`` more bytes would exceed ``max_total_bytes``."""
            return self.held_bytes() + extra > max_total_bytes

        def sweep_partials(self) -> None:
            """Close connections whose half-received object has had no new part for
            ``partial_timeout`` seconds (unless the relay itself paused their reading)."""
            if self.closing:
                return
            now = time.monotonic()
            for conn in list(self.connections):
                since = conn.last_part
                if since is not None and not conn.held and now - since > partial_timeout:
                    conn._kill(f"no part of a message for {partial_timeout:.0f} s")
            reactor.callLater(min(5.0, partial_timeout / 4), self.sweep_partials)

        def add_consumable(self, group: str, key: tuple, frames: list[bytes]) -> None:
            queue = self.group_info[group]["to_consume"]
            size = sum(len(f) for f in frames)
            while queue and (
                len(queue) >= max_consumables or self.queued_bytes + size > max_consumable_bytes
            ):
                self.queued_bytes -= sum(len(f) for f in queue.popleft()[1])
                self.dropped += 1
                self.log_every(
                    "drop",
                    5.0,
                    logging.WARNING,
                    "the trainer is falling behind: dropped the oldest pending sample batch "
                    "(%d dropped so far, max_consumables=%d, max_consumable_bytes=%d)",
                    self.dropped,
                    max_consumables,
                    max_consumable_bytes,
                )
            queue.append((key, frames))
            self.queued_bytes += size
            self.dispatch(group)

        def dispatch(self, group: str) -> None:
            info = self.group_info[group]
            queue, pending = info["to_consume"], info["pending_consumers"]
            for cid in list(pending):
                while pending[cid] > 0 and queue:
                    pending[cid] -= 1
                    self.to_clients[cid].deliver(group, *queue.popleft())
            self.maybe_release()

        def log_every(self, key: str, interval: float, level: int, msg: str, *args: Any) -> None:
            """Log at ``level`` at most once per ``interval`` seconds for ``key``; at DEBUG between."""
            now = time.monotonic()
            if now - self._last_log.get(key, -math.inf) > interval:
                self._last_log[key] = now
            else:
                level = logging.DEBUG
            log_relay.log(level, msg, *args)

        def backlog(self) -> int:
            return len(self.group_info["trainers"]["to_consume"])

        def hold(self, conn: Any) -> bool:
            """Whether ``conn`` (a worker) must stop reading for now; pauses it if so."""
            if conn.held:
                return True
            if "workers" not in conn._groups or (
                self.backlog() < self.high_count and self.queued_bytes < self.high_bytes
            ):
                return False
            conn.held = True
            conn.transport.pauseProducing()
            self.held.add(conn)
            self.log_every(
                "hold",
                60.0,
                logging.INFO,
                "the trainer is behind (%d sample batches waiting): workers wait until it catches up",
                self.backlog(),
            )
            return True

        def maybe_release(self) -> None:
            if (
                self.held
                and not self._release_scheduled
                and self.backlog() <= self.low_count
                and self.queued_bytes <= self.low_bytes
            ):
                # Later, not here: reading frames again may add samples and dispatch them.
                self._release_scheduled = True
                reactor.callLater(0, self.release)

        def release(self) -> None:
            self._release_scheduled = False
            held, self.held = self.held, set()
            for conn in held:
                conn.held = False
                if conn._state not in (_KILLED, _CLOSED, "DEAD"):
                    conn.transport.resumeProducing()
                    conn.process_frames()

        def shutdown(self, budget: float = 3.0) -> None:
            if self.closing:
                return
            self.closing = True
            for conn in list(self.connections):
                conn.transport.unregisterProducer()
                conn.transport.loseConnection()  # flushes what is queued
            self.maybe_stop()
            reactor.callLater(min(3.0, budget), _stop_reactor)

        def maybe_stop(self) -> None:
            if self.closing and not self.connections:
                _stop_reactor()

    def _stop_reactor() -> None:
        try:
            reactor.stop()
        except ReactorNotRunning:
            pass  # already stopping

    @implementer(IPushProducer)
    class RelayProtocol(TlspyoServerProtocol):
        """One connection at the relay (a worker, the trainer, or anybody who found the port)."""

        def __init__(self, server: RelayState, peer: str):
            super().__init__(server)
            self._peer = peer
            self._reader = _FrameReader(server.header_size, server.password_bytes, cfg["max_frame_bytes"])
            self._groups: tuple[str, ...] = ()
            self._partial: list[Any] | None = (
                None  # consumable being received: [msg_id, dest, count, total, chunks, size]
            )
            self.paused = False
            self._nonce = b""
            self._handshake_timer: Any = None
            self.stale: set[str] = set()
            self.unacked: dict[tuple, tuple[str, list[bytes]]] = {}
            self.unacked_bytes = 0
            self.held = False  # reading paused by the relay's back-pressure
            self.last_part: float | None = None  # when the last part of an unfinished object came

        def connectionMade(self) -> None:
            self._server.connections.add(self)
            _tune(self.transport)
            self.transport.registerProducer(self, True)
            # A fresh challenge: the link answers with a token derived from it and the password
            # (never the password), and a trainer proves it holds the trainer key by signing it.
            self._nonce = os.urandom(32)
            self._reader.pw = session_token(self._server.password_bytes, self._nonce)
            self.transport.write(_frame(self._header_size, wire.encode((0, "HELLO", self._nonce))))
            # Whoever found the port gets a bounded time to authenticate, not a free socket forever.
            self._handshake_timer = reactor.callLater(cfg["handshake_timeout"], self._handshake_expired)

        def _handshake_expired(self) -> None:
            self._handshake_timer = None
            if self._state == _HANDSHAKE:
                self._kill(f"no handshake within {cfg['handshake_timeout']:.0f} s")

        def _cancel_handshake_timer(self) -> None:
            if self._handshake_timer is not None and self._handshake_timer.active():
                self._handshake_timer.cancel()
            self._handshake_timer = None

        def connectionLost(self, reason: Any = None) -> None:
            if self._server.has_client(self._identifier):
                self._server.delete_client(self._identifier)
                log_relay.info("%s (%s) disconnected", self._peer, "/".join(self._groups))
            if self.unacked:
                self._requeue_unacked()
            srv = self._server
            for group, part in list(srv.partial.items()):  # its unfinished broadcast goes too
                if part[0][0] == self._identifier:
                    del srv.partial[group]
            self._identifier = None
            self._state = "DEAD"
            self._partial = None
            self.last_part = None
            self._cancel_handshake_timer()
            self._server.connections.discard(self)
            self._server.held.discard(self)
            self._server.maybe_stop()

        def _kill(self, reason: str) -> None:
            self._server.log_refusal(self._peer, f"closed the connection from {self._peer}: {reason}", reason)
            if reason == "wrong password":
                # Telling the peer costs nothing (it knows what it sent) and saves users a search.
                self.transport.write(_frame(self._header_size, wire.encode((0, "REFUSED", reason))))
                self._state = _KILLED
                self.transport.loseConnection()
                return
            self._state = _KILLED
            self.transport.abortConnection()

        def dataReceived(self, data: bytes) -> None:
            if self._state in (_KILLED, _CLOSED):
                return
            self._reader.feed(data)
            self.process_frames()

        def process_frames(self) -> None:
            try:
                while self._state not in (_KILLED, _CLOSED) and not self._server.hold(self):
                    body = self._reader.next_frame()
                    if body is None:
                        break
                    try:
                        env = wire.decode(body, copy=True)
                    except wire.DecodeError:
                        self._kill(
                            "a frame that is not tmrl wire data (pickle and other formats are refused)"
                        )
                        return
                    self._handle(env)
            except ValueError as e:
                self._kill(str(e))
            except Exception as e:  # a bug must not take the relay down with it
                log_relay.exception("closing the connection from %s after an internal error", self._peer)
                self._kill(f"internal error {type(e).__name__}")

        def _handle(self, env: Any) -> None:
            if type(env) is not tuple or len(env) != 4 or type(env[1]) is not str:
                self._kill("malformed envelope")
                return
            _, cmd, dest, obj = env
            if cmd == "ACK":
                if type(obj) is tuple:
                    done = self.unacked.pop(obj, None)
                    if done is not None:
                        self.unacked_bytes -= sum(len(f) for f in done[1])
                return
            if cmd == "HELLO":
                self._hello(obj, dest)
            elif self._state != _ALIVE:
                self._kill(f"command {cmd[:20]!r} before the handshake")
            elif cmd == "OBJ":
                self._obj(dest, obj)
            elif cmd == "NTF":
                self._ntf(dest)
            else:
                self._kill(f"unknown command {cmd[:20]!r}")

        def _hello(self, groups: Any, proof: Any) -> None:
            if self._state != _HANDSHAKE:
                self._kill("second handshake")
                return
            if type(groups) is str:
                groups = (groups,)
            if type(groups) not in (tuple, list) or not groups or not all(type(g) is str for g in groups):
                self._kill("malformed handshake")
                return
            groups = tuple(groups)
            reason = self._server.refusal(groups)
            if reason is None and "trainers" in groups:
                reason = self._server.trainer_refusal(self._nonce, proof)
            if reason is not None:
                self._server.log_refusal(self._peer, f"{reason} from {self._peer}", reason)
                self.transport.write(_frame(self._header_size, wire.encode((0, "REFUSED", reason))))
                self._state = _CLOSED
                self.transport.loseConnection()
                return
            self._cancel_handshake_timer()
            self._groups = groups
            self._identifier = self._server.add_client(groups=groups, client=self)
            self._state = _ALIVE
            self.transport.write(_frame(self._header_size, wire.encode((0, "WELCOME", None))))
            log_relay.info("%s connected (%s)", self._peer, "/".join(groups))
            for g in groups:
                self._send_stored_broadcast(g)

        def _send_stored_broadcast(self, group: str) -> None:
            # The latest complete broadcast, then the frames so far of the one in progress (the
            # rest of it is then streamed to this client like to the others).
            for out in self._server.complete.get(group, ()):
                self.transport.write(out)
            part = self._server.partial.get(group)
            if part is not None:
                for out in part[3]:
                    self.transport.write(out)

        # IPushProducer: Twisted tells us when this client's send buffer is full / drained.
        def pauseProducing(self) -> None:
            self.paused = True

        def resumeProducing(self) -> None:
            self.paused = False
            while self.stale and not self.paused:
                self._send_stored_broadcast(self.stale.pop())

        def stopProducing(self) -> None:
            self.stale.clear()

        def _obj(self, dest: Any, obj: Any) -> None:
            srv = self._server
            if (
                type(dest) is not dict
                or not dest
                or not all(
                    type(g) is str and g in srv.group_info and type(n) is int and n != 0
                    for g, n in dest.items()
                )
            ):
                self._kill("malformed destination")
                return
            if not _valid_chunk(obj, cfg["max_object_bytes"]):
                self._kill("malformed object frame")
                return
            # Workers only send samples to the trainer; the trainer only broadcasts to workers.
            role = "workers" if "workers" in self._groups else "trainers"
            allowed = all(
                (g == "trainers" and n > 0) if role == "workers" else (g == "workers" and n < 0)
                for g, n in dest.items()
            )
            if not allowed:
                self._kill(f"{role} may not send to {sorted(dest)} that way")
                return
            msg_id, idx, count, total, chunk = obj
            if srv.over_budget(len(chunk)):
                self._kill(
                    f"the relay's memory budget of {max_total_bytes} bytes is used up (config key "
                    "SERVER_MEMORY_BYTES)"
                )
                return
            # A multi-part object in progress: its sender must keep sending (partial_timeout).
            self.last_part = time.monotonic() if idx + 1 < count else None
            key = (self._identifier, msg_id)
            for g, n in dest.items():
                if n < 0:
                    srv.broadcast_frame(g, key, idx, count, total, chunk)
            consumers = {g: n for g, n in dest.items() if n > 0}
            if not consumers:
                return
            part = self._partial
            if idx == 0:
                part = self._partial = [msg_id, consumers, count, total, [], 0]
            elif part is None or part[0] != msg_id or len(part[4]) != idx or part[2] != count:
                self._partial = None
                return
            part[4].append(chunk)
            part[5] += len(chunk)
            if part[5] > total:
                self._kill("object frames larger than announced")
                return
            if len(part[4]) == count:
                self._partial = None
                if part[5] != total:
                    self._kill("object frames smaller than announced")
                    return
                frames = [srv.out_frame(key, i, count, total, c, False) for i, c in enumerate(part[4])]
                for g in consumers:  # one copy per group, whatever n > 0 asks
                    srv.add_consumable(g, key, frames)
                # The sender may forget the object now (it keeps it until then, for resending).
                self.transport.write(_frame(self._header_size, wire.encode((0, "ACK", msg_id))))

        def _ntf(self, dest: Any) -> None:
            if type(dest) is not dict or not all(type(g) is str and type(n) is int for g, n in dest.items()):
                self._kill("malformed notification")
                return
            for g, n in dest.items():
                info = self._server.group_info.get(g)
                if info is None or self._identifier not in info["pending_consumers"]:
                    continue
                if n > 0:
                    log_relay.debug("%s asks for %d more sample batches", self._peer, n)
                    pending = info["pending_consumers"]
                    pending[self._identifier] = min(pending[self._identifier] + n, 1 << 30)
                    self._server.dispatch(g)
                elif n < 0:
                    queue = info["to_consume"]
                    while queue:
                        self.deliver(g, *queue.popleft())
                    self._server.maybe_release()

        def deliver(self, group: str, key: tuple, frames: list[bytes]) -> None:
            # Kept until the link acknowledges it: if this connection drops first, the object goes
            # back to the front of the queue for the next trainer (at-least-once delivery).
            size = sum(len(f) for f in frames)
            self._server.queued_bytes -= size
            self.unacked[key] = (group, frames)
            self.unacked_bytes += size
            for out in frames:
                self.transport.write(out)
            log_relay.debug("sent a sample batch to %s", self._peer)

        def _requeue_unacked(self) -> None:
            srv = self._server
            for key, (group, frames) in reversed(list(self.unacked.items())):
                srv.group_info[group]["to_consume"].appendleft((key, frames))
                srv.queued_bytes += sum(len(f) for f in frames)
            groups = {g for g, _ in self.unacked.values()}
            log_relay.info(
                "%s left with %d sample batches unacknowledged: queued again", self._peer, len(self.unacked)
            )
            self.unacked.clear()
            self.unacked_bytes = 0
            for g in groups:
                srv.dispatch(g)

    class RelayFactory(Factory):
        def __init__(self, server: RelayState):
            self.server = server

        def buildProtocol(self, addr: Any) -> RelayProtocol:
            peer = f"{getattr(addr, 'host', '?')}:{getattr(addr, 'port', '?')}"
            return RelayProtocol(self.server, peer)

    state = RelayState()
    factory = RelayFactory(state)
    port = cfg["port"]
    interface = cfg["interface"]
    try:
        if cfg["security"] == "TLS":
            try:
                ctx = ssl.DefaultOpenSSLContextFactory(cfg["key_file"], cfg["cert_file"])
            except (OpenSSL.SSL.Error, OSError) as e:
                writer.send(
                    _pipe.READY,
                    wire.encode(
                        {
                            "error": f"cannot load the TLS credentials in {cfg['keys_dir']} ({e}): "
                            "run `python -m tmrl --install` to create them"
                        }
                    ),
                )
                return
            listening = reactor.listenSSL(port, factory, ctx, interface=interface)
        else:
            listening = reactor.listenTCP(port, factory, interface=interface)
    except CannotListenError as e:
        err = e.socketError
        import errno

        if getattr(err, "errno", None) == errno.EADDRINUSE:
            msg = f"port {port} is already in use: {err}; stop the other server or choose another port"
        else:
            msg = f"cannot listen on port {port}: {err}"
        writer.send(_pipe.READY, wire.encode({"error": msg}))
        return
    bound = listening.getHost().port
    log_relay.info(
        "relay listening on %s port %d (%s)",
        interface or "all interfaces",
        bound,
        cfg["security"] or "plain TCP",
    )
    writer.send(_pipe.READY, wire.encode({"ok": True, "port": bound}))
    reactor.callLater(min(5.0, partial_timeout / 4), state.sweep_partials)

    def control_loop() -> None:
        budget = _PARENT_GONE_BUDGET
        while True:
            try:
                kind, payload = _pipe.read_message(_STDIN, 1 << 20)
            except _pipe.PipeClosed:
                break
            if kind == _pipe.STOP:
                budget = _stop_budget(payload)
                break
        reactor.callFromThread(state.shutdown, budget)

    _serve(state.shutdown, control_loop)


# ================================================================================================
# links (workers and trainers)


def run_link(cfg: dict[str, Any], writer: _pipe.PipeWriter) -> None:
    from tlspyo.client import ClientProtocol as TlspyoClientProtocol
    from tlspyo.client import TLSClientFactory as TlspyoClientFactory
    from twisted.internet import reactor, ssl
    from twisted.internet.error import ReactorNotRunning
    from twisted.internet.interfaces import IPushProducer
    from zope.interface import implementer

    groups: tuple[str, ...] = tuple(cfg["groups"])
    header_size: int = cfg["header_size"]
    chunk_bytes: int = cfg["chunk_bytes"]
    max_object_bytes: int = cfg["max_object_bytes"]
    window: int = cfg["credit_window"]
    where = f"{cfg['server_ip']}:{cfg['server_port']}"
    trainer_key: Any = None
    if cfg.get("trainer_key"):
        from tmrl.transport.credentials import TrainerKey

        trainer_key = TrainerKey(cfg["trainer_key"])

    class LinkState:
        """What survives reconnections: the store of unsent objects, credit, and flags."""

        def __init__(self) -> None:
            # attributes tlspyo's TLSClientFactory reads
            self.password = cfg["password"]
            self.groups = groups
            self.header_size = header_size
            self.recon_max_delay = cfg["recon_max_delay"]
            self.recon_initial_delay = cfg["recon_initial_delay"]
            self.recon_factor = 1.5
            self.recon_jitter = 0.1
            self.password_bytes = cfg["password"].encode("utf-8")
            self.proto: LinkProtocol | None = None
            self.store: collections.deque[tuple[dict[str, int], memoryview, bytearray, tuple[int, int]]] = (
                collections.deque()
            )
            self.last_broadcast_sent: tuple[dict[str, int], memoryview, bytearray, tuple[int, int]] | None = (
                None
            )
            self.store_bytes = 0
            self.unacked: collections.OrderedDict[
                Any, tuple[dict[str, int], memoryview, bytearray, tuple[int, int]]
            ] = collections.OrderedDict()
            self.unacked_bytes = 0
            self.dropped = 0
            self.session = random.getrandbits(62)
            self.counter = 0
            self.backlog = 0  # objects handed to the parent and not yet consumed
            self.outstanding = 0  # credit granted to the relay on this connection
            self.last_broadcast: Any = None
            self.writable = threading.Event()
            self.writable.set()
            self.closing = False
            self.last_failure: str | None = None
            self.last_refusal: str | None = None
            self.lost_reason: str | None = None
            self.factory: LinkFactory | None = None
            self.close_budget: float = cfg["close_timeout"]
            # While disconnected, each send past the store's bound drops one object: one line a
            # second, not one per object.
            self.drop_log = RateLimitedLog(log_link, logging.WARNING, 1.0)

        def flush_logs(self) -> None:
            self.drop_log.flush()
            reactor.callLater(1.0, self.flush_logs)

        def status(self, **kw: Any) -> None:
            writer.send(_pipe.STATUS, wire.encode(kw))

        def handle_send(self, payload: bytearray, done: Callable[[], None]) -> None:
            try:
                mlen = int.from_bytes(payload[:4], "little")
                meta = wire.decode(bytes(payload[4 : 4 + mlen]))
                data = memoryview(payload)[4 + mlen :]
                self.send(meta, data, payload)
            finally:
                done()

        def send(self, dest: dict[str, int], data: memoryview, keep: bytearray) -> None:
            self.counter += 1
            msg_id = (self.session, self.counter)
            if any(n < 0 for n in dest.values()):
                # Kept so that a restarted relay gets the latest broadcast again on reconnection
                # (same msg_id: workers that already have it skip it).
                self.last_broadcast_sent = (dest, data, keep, msg_id)
            if self.proto is not None and self.proto.alive:
                self.proto.send_object(dest, data, msg_id)
                self.remember(dest, data, keep, msg_id)
                return
            if any(n < 0 for n in dest.values()):  # only the newest broadcast matters
                for item in [it for it in self.store if it[0] == dest]:
                    self.store.remove(item)
                    self.store_bytes -= len(item[1])
            self.store.append((dest, data, keep, msg_id))
            self.store_bytes += len(data)
            while len(self.store) > 1 and (
                len(self.store) > cfg["max_store"] or self.store_bytes > cfg["max_store_bytes"]
            ):
                _, old, _, _ = self.store.popleft()
                self.store_bytes -= len(old)
                self.dropped += 1
                self.drop_log(
                    "not connected to the relay at %s: dropped the oldest unsent object (%d dropped so far)",
                    where,
                    self.dropped,
                )

        def remember(
            self, dest: dict[str, int], data: memoryview, keep: bytearray, msg_id: tuple[int, int]
        ) -> None:
            # Samples stay here until the relay acknowledges them, to be sent again if the
            # connection drops first (at-least-once; the receiver may see a duplicate).
            if not any(n > 0 for n in dest.values()):
                return
            self.unacked[msg_id] = (dest, data, keep, msg_id)
            self.unacked_bytes += len(data)
            while len(self.unacked) > cfg["max_store"] or self.unacked_bytes > cfg["max_store_bytes"]:
                _, (_, old, _, _) = self.unacked.popitem(last=False)
                self.unacked_bytes -= len(old)

        def acked(self, msg_id: Any) -> None:
            item = self.unacked.pop(msg_id, None)
            if item is not None:
                self.unacked_bytes -= len(item[1])

        def connected(self, proto: LinkProtocol) -> None:
            self.proto = proto
            self.last_failure = None
            log_link.info("connected to the relay at %s (%s)", where, "/".join(groups))
            last = self.last_broadcast_sent
            if last is not None and not any(item[3] == last[3] for item in self.store):
                proto.send_object(last[0], last[1], last[3])
            while self.store and self.proto is proto and proto.alive:
                dest, data, keep, msg_id = self.store.popleft()
                self.store_bytes -= len(data)
                proto.send_object(dest, data, msg_id)
                self.remember(dest, data, keep, msg_id)
            self.outstanding = 0
            self.grant()
            # Reported last: when the owner sees "connected", credit and resends are on the wire.
            self.status(connected=True, refused=None)
            if self.closing:
                self.finish(proto)

        def disconnected(self) -> None:
            was = self.proto is not None
            self.proto = None
            self.outstanding = 0
            for item in reversed(list(self.unacked.values())):  # unacknowledged first, in order
                self.store.appendleft(item)
                self.store_bytes += len(item[1])
            self.unacked.clear()
            self.unacked_bytes = 0
            self.writable.set()  # objects now go to the bounded store instead of blocking
            if was and not self.closing:
                log_link.warning("lost the connection to the relay at %s; reconnecting", where)
                self.status(connected=False, refused=None)
            if self.closing and not self.store:
                _stop_reactor()

        def grant(self) -> None:
            if not window or self.proto is None or not self.proto.alive:
                return
            want = window - self.backlog - self.outstanding
            if want > 0:
                self.outstanding += want
                self.proto.send_env("NTF", {g: want for g in groups}, None)

        def on_credit(self, k: int) -> None:
            self.backlog = max(0, self.backlog - k)
            self.grant()

        def deliver(self, key: Any, payload: bytearray, bcast: bool) -> None:
            if bcast:
                msg_id = key[1] if type(key) is tuple and len(key) == 2 else key
                if msg_id == self.last_broadcast:
                    return  # the relay re-sent what we already have (reconnection)
                self.last_broadcast = msg_id
                writer.send(_pipe.OBJ, payload)
            else:
                self.outstanding = max(0, self.outstanding - 1)
                self.backlog += 1
                writer.send(_pipe.OBJ, payload)
                if self.proto is not None and self.proto.alive:
                    self.proto.send_env("ACK", None, key)  # now in the trainer process

        def shutdown(self, budget: float = math.inf) -> None:
            if self.closing:
                return
            self.closing = True
            self.close_budget = max(0.0, min(cfg["close_timeout"], budget))
            if self.proto is not None:
                self.finish(self.proto)
            elif self.store and self.close_budget > 0:
                # Not connected: give the relay a chance to take what this process still holds.
                log_link.info(
                    "waiting up to %.0f s to deliver %d unsent objects to %s",
                    self.close_budget,
                    len(self.store),
                    where,
                )
                reactor.callLater(self.close_budget, self.give_up)
            else:
                if self.factory is not None:
                    self.factory.stopTrying()
                if self.store:
                    self.give_up()
                _stop_reactor()

        def finish(self, proto: LinkProtocol) -> None:
            if self.factory is not None:
                self.factory.stopTrying()
            # A registered producer would make a TLS transport wait for it before closing.
            proto.transport.unregisterProducer()
            proto.transport.loseConnection()  # flushes what is queued first
            reactor.callLater(self.close_budget, _stop_reactor)

        def give_up(self) -> None:
            if self.store:
                log_link.warning(
                    "closing with %d objects never sent (no connection to %s)", len(self.store), where
                )
            _stop_reactor()

    def _stop_reactor() -> None:
        try:
            reactor.stop()
        except ReactorNotRunning:
            pass  # already stopping

    @implementer(IPushProducer)
    class LinkProtocol(TlspyoClientProtocol):
        """The link's connection to the relay."""

        def __init__(self, state: LinkState):
            super().__init__(client=state, password=cfg["password"], header_size=header_size, groups=groups)
            self._reader = _FrameReader(header_size, b"", cfg["max_frame_bytes"])
            self.token = b""  # the session token, once the relay's challenge arrived
            self._partials: collections.OrderedDict[Any, list[Any]] = collections.OrderedDict()
            self.alive = False

        # IPushProducer: Twisted pauses us when its write buffer is full; the control thread then
        # stops reading from the parent, whose writes block: back-pressure up to the worker loop.
        def pauseProducing(self) -> None:
            self._client.writable.clear()

        def resumeProducing(self) -> None:
            self._client.writable.set()

        def stopProducing(self) -> None:
            self._client.writable.set()

        def connectionMade(self) -> None:
            _tune(self.transport)
            self.transport.registerProducer(self, True)

        def connectionLost(self, reason: Any = None) -> None:
            if not self.alive and reason is not None:
                # The TLS layer tells us (not the factory) why a handshake failed.
                self._client.lost_reason = reason.getErrorMessage()
            self._state = "DEAD"
            self.alive = False
            if self._client.proto is self or self._client.proto is None:
                self._client.disconnected()

        def send_env(self, cmd: str, dest: Any, obj: Any) -> None:
            env = wire.encode((0, cmd, dest, obj))
            head = str(len(env)).encode("ascii").ljust(header_size, b" ") + self.token
            self.transport.writeSequence([head, env])

        def send_object(self, dest: dict[str, int], data: memoryview, msg_id: tuple[int, int]) -> None:
            total = len(data)
            count = max(1, -(-total // chunk_bytes))
            for idx in range(count):
                self.send_env(
                    "OBJ",
                    dest,
                    (msg_id, idx, count, total, data[idx * chunk_bytes : (idx + 1) * chunk_bytes]),
                )

        def _abort(self, reason: str) -> None:
            log_link.error("closed the connection to the relay at %s: %s", where, reason)
            self._state = _KILLED
            self.alive = False
            self.transport.abortConnection()

        def dataReceived(self, data: bytes) -> None:
            if self._state == _KILLED:
                return
            self._reader.feed(data)
            try:
                while self._state != _KILLED:
                    body = self._reader.next_frame()
                    if body is None:
                        return
                    env = wire.decode(body, copy=True)
                    if type(env) is not tuple or len(env) != 3 or type(env[1]) is not str:
                        raise ValueError("malformed envelope")
                    self._handle(env[1], env[2])
            except (ValueError, wire.DecodeError) as e:
                self._abort(str(e))
            except _pipe.PipeClosed:
                self._client.shutdown()

        def _handle(self, cmd: str, obj: Any) -> None:
            if cmd == "HELLO":
                if type(obj) is not bytes or not 16 <= len(obj) <= 64:
                    raise ValueError("the relay sent no valid challenge (an older tmrl server?)")
                self.token = session_token(self._client.password_bytes, obj)
                proof = None
                if trainer_key is not None and type(obj) is bytes:
                    from tmrl.transport.credentials import HANDSHAKE_CONTEXT

                    proof = {"sig": trainer_key.sign(HANDSHAKE_CONTEXT + obj)}
                self.send_env("HELLO", proof, groups)
            elif cmd == "WELCOME":  # accepted: only now may stored objects be sent
                self._state = _ALIVE
                self.alive = True
                self._client.connected(self)
            elif cmd == "REFUSED":
                reason = (obj if type(obj) is str else "no reason given")[:300]
                if reason != self._client.last_refusal:
                    self._client.last_refusal = reason
                    hint = " (check the password on both machines)" if reason == "wrong password" else ""
                    log_link.error(
                        "the relay at %s refused this %s: %s%s", where, _role_of(groups), reason, hint
                    )
                self._client.status(connected=False, refused=reason)
            elif cmd == "OBJ":
                self._frame(obj)
            elif cmd == "ACK":
                if type(obj) is tuple:
                    self._client.acked(obj)
            else:
                raise ValueError(f"unknown command {cmd[:20]!r}")

        def _frame(self, obj: Any) -> None:
            if type(obj) is not tuple or len(obj) != 6 or type(obj[5]) is not bool:
                raise ValueError("malformed object frame")
            key, idx, count, total, chunk, bcast = obj
            if type(key) is not tuple or not _valid_parts(idx, count, total, chunk, max_object_bytes):
                raise ValueError("malformed object frame")
            if idx == 0:
                self._partials.pop(key, None)
                if len(self._partials) >= 4:
                    self._partials.popitem(last=False)
                part = self._partials[key] = [bytearray(total), 0, 0]
            else:
                found = self._partials.get(key)
                if found is None or found[2] != idx:
                    self._partials.pop(key, None)
                    return  # joined mid-object, or lost frames: wait for the next one
                part = found
            buf, filled, _ = part
            if filled + len(chunk) > total:
                self._partials.pop(key, None)
                return
            buf[filled : filled + len(chunk)] = chunk
            part[1] = filled + len(chunk)
            part[2] = idx + 1
            if idx + 1 == count:
                del self._partials[key]
                if part[1] == total:
                    self._client.deliver(key, buf, bcast)

    class LinkFactory(TlspyoClientFactory):
        def __init__(self, state: LinkState):
            super().__init__(client=state)
            self._state = state

        def startedConnecting(self, connector: Any) -> None:
            pass

        def buildProtocol(self, addr: Any) -> LinkProtocol:
            self.resetDelay()
            return LinkProtocol(self._state)

        def clientConnectionLost(self, connector: Any, reason: Any) -> None:
            self._retry(connector, reason)

        def clientConnectionFailed(self, connector: Any, reason: Any) -> None:
            self._retry(connector, reason)

        def _retry(self, connector: Any, reason: Any) -> None:
            if self._state.closing and not self._state.store:
                _stop_reactor()
                return
            msg = self._state.lost_reason or reason.getErrorMessage()
            self._state.lost_reason = None
            if msg != self._state.last_failure:
                self._state.last_failure = msg
                # A certificate problem will not go away by retrying: say it louder.
                tls = any(w in msg.lower() for w in ("ssl", "certificate", "tls", "handshake"))
                log_link.log(
                    logging.WARNING if tls else logging.INFO,
                    "cannot reach the relay at %s (%s); retrying%s",
                    where,
                    msg,
                    " (check that certificate.pem is the server's)" if tls else "",
                )
            self.retry(connector)

    state = LinkState()
    factory = state.factory = LinkFactory(state)
    if cfg["security"] == "TLS":
        try:
            with open(cfg["cert_file"], "rb") as f:
                authority = ssl.Certificate.loadPEM(f.read())
        except Exception as e:  # noqa: BLE001 (any failure here is a bad or missing file: one line)
            writer.send(
                _pipe.READY,
                wire.encode(
                    {
                        "error": f"cannot load the TLS certificate {cfg['cert_file']} ({e}): copy certificate.pem "
                        "from the server's credentials folder (made by `python -m tmrl --install`)"
                    }
                ),
            )
            return
        options = ssl.optionsForClientTLS(hostname=cfg["hostname"], trustRoot=authority)
        reactor.connectSSL(cfg["server_ip"], cfg["server_port"], factory, options)
    else:
        reactor.connectTCP(cfg["server_ip"], cfg["server_port"], factory)
    writer.send(_pipe.READY, wire.encode({"ok": True}))
    reactor.callLater(1.0, state.flush_logs)

    def control_loop() -> None:
        sem = threading.Semaphore(2)  # at most two objects handed to the reactor at a time
        limit = max_object_bytes + (1 << 20)
        budget = _PARENT_GONE_BUDGET
        try:
            while True:
                # Held back by the relay (the connection's buffer is full), this process stops
                # reading the pipe so that the parent's sends block; it still watches the pipe, so
                # that a parent that closes it (stopping, or dead) is noticed at once.
                while not state.writable.wait(0.25):
                    if _pipe.peer_closed(_STDIN):
                        raise _pipe.PipeClosed()
                kind, payload = _pipe.read_message(_STDIN, limit)
                if kind == _pipe.SEND:
                    while not sem.acquire(timeout=0.25):
                        if _pipe.peer_closed(_STDIN):
                            raise _pipe.PipeClosed()
                    reactor.callFromThread(state.handle_send, payload, sem.release)
                elif kind == _pipe.CREDIT:
                    reactor.callFromThread(state.on_credit, int.from_bytes(payload, "little"))
                elif kind == _pipe.STOP:
                    budget = _stop_budget(payload)
                    break
        except _pipe.PipeClosed:
            pass
        reactor.callFromThread(state.shutdown, budget)

    _serve(state.shutdown, control_loop)


# ================================================================================================


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
    return os.getppid() != _PARENT_PID


def _on_signal(signum: int, frame: Any) -> None:
    # SIGTERM: stop (flushing briefly). The parent-death signal also arrives when the thread that
    # started us exits while our parent lives on: only a changed parent means it died.
    if signum == signal.SIGTERM or _parent_gone():
        _request_shutdown(_PARENT_GONE_BUDGET)


def _watch_parent() -> None:
    """Stop when the parent dies, checked twice a second (the fallback where no parent-death
    signal exists, and a second line of defence where it does)."""
    while True:
        time.sleep(0.5)
        if _parent_gone():
            try:
                _request_shutdown(_PARENT_GONE_BUDGET)
            except SystemExit:
                os._exit(0)
            return


def _set_parent_death_signal() -> None:
    """Ask Linux to send SIGUSR2 when the parent dies (prctl PR_SET_PDEATHSIG)."""
    if not sys.platform.startswith("linux"):
        return
    try:
        import ctypes

        libc = ctypes.CDLL(None, use_errno=True)
        libc.prctl(1, int(signal.SIGUSR2), 0, 0, 0)  # 1: PR_SET_PDEATHSIG
    except (OSError, AttributeError):
        pass  # the polling watch still applies


def _serve(shutdown: Callable[[float], None], control_loop: Callable[[], None]) -> None:
    """Run the reactor with the control thread; signals and the parent watch call ``shutdown``."""
    global _shutdown_hook
    _shutdown_hook = shutdown
    threading.Thread(target=control_loop, daemon=True, name="tmrl-control").start()
    from twisted.internet import reactor

    reactor.run(installSignalHandlers=False)


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
    """Entry point of the network process (see the module docstring)."""
    # Ctrl-C reaches the whole process group: the parent decides when we stop (or dies, closing
    # our stdin), so that pending objects are flushed and no port stays held.
    global _STDIN, _PARENT_PID
    _PARENT_PID = os.getppid()
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, _on_signal)
    if hasattr(signal, "SIGUSR2"):
        signal.signal(signal.SIGUSR2, _on_signal)
    _set_parent_death_signal()
    if _parent_gone():  # died before the death signal was armed
        return
    threading.Thread(target=_watch_parent, daemon=True, name="tmrl-parent-watch").start()
    _STDIN = open(0, "rb", buffering=0, closefd=False)  # noqa: SIM115 (for the process's lifetime)
    out_fd = os.dup(1)
    os.dup2(2, 1)  # a stray print must not corrupt the pipe protocol
    writer = _pipe.PipeWriter(out_fd)
    try:
        _kind, payload = _pipe.read_message(_STDIN, 1 << 20)
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
            run_relay(cfg, writer)
        else:
            run_link(cfg, writer)
    finally:
        try:
            writer.send(_pipe.CLOSED)
        except _pipe.PipeClosed:
            pass


if __name__ == "__main__":
    main()
