# Twisted's zope interfaces and tlspyo (untyped) defeat mypy here; the logic is tested instead.
# mypy: disable-error-code="misc, has-type, arg-type, call-arg, import-untyped, list-item"
"""The link side of the network process (a worker's or the trainer's connection to the relay).

Imported only in the network process (by :func:`tmrl.transport._netproc.main`): importing it
imports Twisted and tlspyo and installs Twisted's default reactor.

- :class:`LinkState`: what survives reconnections: the bounded store of unsent objects, samples
  sent and not yet acknowledged (sent again after a reconnection: at-least-once), the last
  broadcast sent, the trainer's credit window, and the messages to the parent. Built from the
  configuration the parent sends (``cfg``) and the pipe to the parent (``writer``).
- :class:`LinkProtocol`: one connection to the relay: the challenge handshake, sending objects
  as frame groups, reassembling received ones, acknowledging samples once they reached the
  parent.
- :class:`LinkFactory`: tlspyo's reconnecting factory, with one log line per new failure.
- :func:`run_link`: connect, report readiness, and relay the parent's pipe to the network until
  told to stop.
"""

from __future__ import annotations

import collections
import logging
import math
import random
import threading
from collections.abc import Callable
from typing import Any

from tlspyo.client import ClientProtocol as TlspyoClientProtocol
from tlspyo.client import TLSClientFactory as TlspyoClientFactory
from twisted.internet import reactor, ssl
from twisted.internet.interfaces import IPushProducer
from zope.interface import implementer

from tmrl import wire
from tmrl.transport import _netcommon as common
from tmrl.transport import _pipe
from tmrl.transport._netcommon import (
    _ALIVE,
    _KILLED,
    _FrameReader,
    _role_of,
    _tune,
    _valid_parts,
    session_token,
    stop_reactor,
)
from tmrl.util import RateLimitedLog

log_link = logging.getLogger("tmrl.transport.link")


class LinkState:
    """What survives reconnections: the store of unsent objects, credit, and flags."""

    def __init__(self, cfg: dict[str, Any], writer: _pipe.PipeWriter) -> None:
        self.cfg = cfg
        self.writer = writer
        self.chunk_bytes: int = cfg["chunk_bytes"]
        self.max_object_bytes: int = cfg["max_object_bytes"]
        self.window: int = cfg["credit_window"]
        self.where = f"{cfg['server_ip']}:{cfg['server_port']}"
        self.trainer_key: Any = None
        if cfg.get("trainer_key"):
            from tmrl.transport.credentials import TrainerKey

            self.trainer_key = TrainerKey(cfg["trainer_key"])
        # attributes tlspyo's TLSClientFactory reads
        self.password = cfg["password"]
        self.groups: tuple[str, ...] = tuple(cfg["groups"])
        self.header_size: int = cfg["header_size"]
        self.recon_max_delay = cfg["recon_max_delay"]
        self.recon_initial_delay = cfg["recon_initial_delay"]
        self.recon_factor = 1.5
        self.recon_jitter = 0.1
        self.password_bytes = cfg["password"].encode("utf-8")
        self.proto: LinkProtocol | None = None
        self.store: collections.deque[tuple[dict[str, int], memoryview, bytearray, tuple[int, int]]] = (
            collections.deque()
        )
        self.last_broadcast_sent: tuple[dict[str, int], memoryview, bytearray, tuple[int, int]] | None = None
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
        self.refused_now = False
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
        self.writer.send(_pipe.STATUS, wire.encode(kw))

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
            len(self.store) > self.cfg["max_store"] or self.store_bytes > self.cfg["max_store_bytes"]
        ):
            _, old, _, _ = self.store.popleft()
            self.store_bytes -= len(old)
            self.dropped += 1
            self.drop_log(
                "not connected to the server at %s: dropped the oldest unsent object (%d dropped so far)",
                self.where,
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
        while len(self.unacked) > self.cfg["max_store"] or self.unacked_bytes > self.cfg["max_store_bytes"]:
            _, (_, old, _, _) = self.unacked.popitem(last=False)
            self.unacked_bytes -= len(old)

    def acked(self, msg_id: Any) -> None:
        item = self.unacked.pop(msg_id, None)
        if item is not None:
            self.unacked_bytes -= len(item[1])

    def connected(self, proto: LinkProtocol) -> None:
        self.proto = proto
        self.last_failure = None
        log_link.info("connected to the server at %s (%s)", self.where, "/".join(self.groups))
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
            log_link.warning("lost the connection to the server at %s; reconnecting", self.where)
            self.status(connected=False, refused=None)
        if self.closing and not self.store:
            stop_reactor()

    def grant(self) -> None:
        if not self.window or self.proto is None or not self.proto.alive:
            return
        want = self.window - self.backlog - self.outstanding
        if want > 0:
            self.outstanding += want
            self.proto.send_env("NTF", {g: want for g in self.groups}, None)

    def on_credit(self, k: int) -> None:
        self.backlog = max(0, self.backlog - k)
        self.grant()

    def deliver(self, key: Any, payload: bytearray, bcast: bool) -> None:
        if bcast:
            msg_id = key[1] if type(key) is tuple and len(key) == 2 else key
            if msg_id == self.last_broadcast:
                return  # the relay re-sent what we already have (reconnection)
            self.last_broadcast = msg_id
            self.writer.send(_pipe.OBJ, payload)
        else:
            self.outstanding = max(0, self.outstanding - 1)
            self.backlog += 1
            self.writer.send(_pipe.OBJ, payload)
            if self.proto is not None and self.proto.alive:
                self.proto.send_env("ACK", None, key)  # now in the trainer process

    def shutdown(self, budget: float = math.inf) -> None:
        if self.closing:
            return
        self.closing = True
        self.close_budget = max(0.0, min(self.cfg["close_timeout"], budget))
        if self.proto is not None:
            self.finish(self.proto)
        elif self.store and self.close_budget > 0:
            # Not connected: give the relay a chance to take what this process still holds.
            log_link.info(
                "waiting up to %.0f s to deliver %d unsent objects to %s",
                self.close_budget,
                len(self.store),
                self.where,
            )
            reactor.callLater(self.close_budget, self.give_up)
        else:
            if self.factory is not None:
                self.factory.stopTrying()
            if self.store:
                self.give_up()
            stop_reactor()

    def finish(self, proto: LinkProtocol) -> None:
        if self.factory is not None:
            self.factory.stopTrying()
        # A registered producer would make a TLS transport wait for it before closing.
        proto.transport.unregisterProducer()
        proto.transport.loseConnection()  # flushes what is queued first
        reactor.callLater(self.close_budget, stop_reactor)

    def give_up(self) -> None:
        if self.store:
            log_link.warning(
                "closing with %d objects never sent (no connection to %s)", len(self.store), self.where
            )
        stop_reactor()


@implementer(IPushProducer)
@implementer(IPushProducer)
class LinkProtocol(TlspyoClientProtocol):
    """The link's connection to the relay."""

    def __init__(self, state: LinkState):
        super().__init__(
            client=state, password=state.cfg["password"], header_size=state.header_size, groups=state.groups
        )
        self._reader = _FrameReader(state.header_size, b"", state.cfg["max_frame_bytes"])
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
        head = str(len(env)).encode("ascii").ljust(self._client.header_size, b" ") + self.token
        self.transport.writeSequence([head, env])

    def send_object(self, dest: dict[str, int], data: memoryview, msg_id: tuple[int, int]) -> None:
        chunk_bytes = self._client.chunk_bytes
        total = len(data)
        count = max(1, -(-total // chunk_bytes))
        for idx in range(count):
            self.send_env(
                "OBJ",
                dest,
                (msg_id, idx, count, total, data[idx * chunk_bytes : (idx + 1) * chunk_bytes]),
            )

    def _abort(self, reason: str) -> None:
        log_link.error("closed the connection to the server at %s: %s", self._client.where, reason)
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
            if self._client.trainer_key is not None and type(obj) is bytes:
                from tmrl.transport.credentials import HANDSHAKE_CONTEXT

                proof = {"sig": self._client.trainer_key.sign(HANDSHAKE_CONTEXT + obj)}
            self.send_env("HELLO", proof, self._client.groups)
        elif cmd == "WELCOME":  # accepted: only now may stored objects be sent
            self._state = _ALIVE
            self.alive = True
            self._client.connected(self)
        elif cmd == "REFUSED":
            reason = (obj if type(obj) is str else "no reason given")[:300]
            # The connection closes next: that is the refusal, not a network failure to report.
            self._client.refused_now = True
            if reason != self._client.last_refusal:
                self._client.last_refusal = reason
                # A wrong password stops the role, which says so in one line: no second line here.
                log_link.log(
                    logging.DEBUG if reason == "wrong password" else logging.ERROR,
                    "the server at %s refused this %s: %s",
                    self._client.where,
                    _role_of(self._client.groups),
                    reason,
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
        if type(key) is not tuple or not _valid_parts(
            idx, count, total, chunk, self._client.max_object_bytes
        ):
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
            stop_reactor()
            return
        msg = self._state.lost_reason or reason.getErrorMessage()
        self._state.lost_reason = None
        refused, self._state.refused_now = self._state.refused_now, False
        if not refused and msg != self._state.last_failure:
            self._state.last_failure = msg
            # A certificate problem will not go away by retrying: say it louder.
            tls = any(w in msg.lower() for w in ("ssl", "certificate", "tls", "handshake"))
            log_link.log(
                logging.WARNING if tls else logging.INFO,
                "cannot reach the server at %s (%s); retrying%s",
                self._state.where,
                msg,
                " (check that certificate.pem is the server's)" if tls else "",
            )
        self.retry(connector)


def _connect(cfg: dict[str, Any], factory: LinkFactory, writer: _pipe.PipeWriter) -> bool:
    """Start connecting to the relay (TLS or plain TCP); False after reporting why not."""
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
            return False
        options = ssl.optionsForClientTLS(hostname=cfg["hostname"], trustRoot=authority)
        reactor.connectSSL(cfg["server_ip"], cfg["server_port"], factory, options)
    else:
        reactor.connectTCP(cfg["server_ip"], cfg["server_port"], factory)
    return True


def _wait_pipe(ready: Callable[[float], bool], stdin: Any) -> None:
    """Wait until ``ready(0.25)`` is true, watching the pipe from the parent (``stdin``)
    meanwhile: a parent that closes it (stopping, or dead) is noticed at once.

    Raises:
        _pipe.PipeClosed: the parent's end of the pipe closed.
    """
    while not ready(0.25):
        if _pipe.peer_closed(stdin):
            raise _pipe.PipeClosed()


def _control_loop(state: LinkState, stdin: Any) -> None:
    """The control thread: hand the parent's objects and credit (read from the pipe ``stdin``) to
    the reactor; stop on STOP (or when the parent's end of the pipe closes)."""
    sem = threading.Semaphore(2)  # at most two objects handed to the reactor at a time
    limit = state.max_object_bytes + (1 << 20)
    budget = common._PARENT_GONE_BUDGET
    try:
        while True:
            # Held back by the relay (the connection's buffer is full), this process stops
            # reading the pipe so that the parent's sends block; it still watches the pipe.
            _wait_pipe(state.writable.wait, stdin)
            kind, payload = _pipe.read_message(stdin, limit)
            if kind == _pipe.SEND:
                _wait_pipe(lambda t: sem.acquire(timeout=t), stdin)
                reactor.callFromThread(state.handle_send, payload, sem.release)
            elif kind == _pipe.CREDIT:
                reactor.callFromThread(state.on_credit, int.from_bytes(payload, "little"))
            elif kind == _pipe.STOP:
                budget = common._stop_budget(payload)
                break
    except _pipe.PipeClosed:
        pass
    reactor.callFromThread(state.shutdown, budget)


def run_link(cfg: dict[str, Any], writer: _pipe.PipeWriter, stdin: Any) -> None:
    """Serve as the link described by ``cfg`` until the parent says stop (or dies); ``writer``
    and ``stdin`` are the pipes to and from the parent."""
    state = LinkState(cfg, writer)
    factory = state.factory = LinkFactory(state)
    if not _connect(cfg, factory, writer):
        return
    writer.send(_pipe.READY, wire.encode({"ok": True}))
    reactor.callLater(1.0, state.flush_logs)
    common._serve(state.shutdown, lambda: _control_loop(state, stdin))
