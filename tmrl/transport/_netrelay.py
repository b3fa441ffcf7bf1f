# Twisted's zope interfaces and tlspyo (untyped) defeat mypy here; the logic is tested instead.
# mypy: disable-error-code="misc, has-type, arg-type, call-arg, import-untyped, list-item"
"""The relay side of the network process: tlspyo's relay with tmrl's framing, bounds and checks.

Imported only in the network process (by :func:`tmrl.transport._netproc.main`): importing it
imports Twisted and tlspyo and installs Twisted's default reactor.

- :class:`RelayState`: the relay's bookkeeping (tlspyo's clients and groups), the bounded queue
  of sample batches for the trainer, the stored last broadcast, back-pressure and the memory
  budget. Built from the configuration the parent sends (``cfg``).
- :class:`RelayProtocol`: one connection (a worker, the trainer, or anybody who found the port):
  the challenge handshake, frame checks, receiving objects and delivering them (kept until
  acknowledged, re-queued when the connection drops first).
- :class:`RelayFactory`: builds a :class:`RelayProtocol` per accepted connection.
- :func:`run_relay`: listen, report readiness to the parent, and serve until told to stop.
"""

from __future__ import annotations

import errno
import logging
import math
import os
import time
from typing import Any

import OpenSSL
from tlspyo.server import Server as TlspyoServer
from tlspyo.server import ServerProtocol as TlspyoServerProtocol
from twisted.internet import reactor, ssl
from twisted.internet.error import CannotListenError
from twisted.internet.interfaces import IPushProducer
from twisted.internet.protocol import Factory
from zope.interface import implementer

from tmrl import wire
from tmrl.transport import _netcommon as common
from tmrl.transport import _pipe
from tmrl.transport._netcommon import (
    _ALIVE,
    _CLOSED,
    _HANDSHAKE,
    _KILLED,
    _frame,
    _FrameReader,
    _tune,
    _valid_chunk,
    session_token,
    stop_reactor,
)

log_relay = logging.getLogger("tmrl.transport.relay")


class RelayState(TlspyoServer):
    """tlspyo's relay bookkeeping (clients, groups) with bounded queues and frame stores."""

    def __init__(self, cfg: dict[str, Any]) -> None:
        self.cfg = cfg
        max_consumables = self.max_consumables = cfg["max_consumables"]
        self.max_total_bytes = cfg.get("max_total_bytes") or (3 * cfg["max_consumable_bytes"]) // 2
        # The backlog takes at most half of the memory budget, so that the relay holds workers back
        # (back-pressure) well before the budget bites; the other half is for objects in progress.
        max_consumable_bytes = self.max_consumable_bytes = min(
            cfg["max_consumable_bytes"], self.max_total_bytes // 2
        )
        self.partial_timeout = float(cfg.get("partial_timeout") or 60.0)
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
        path = self.cfg.get("trainer_key_file")
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

    def broadcast_frame(self, group: str, key: tuple, idx: int, count: int, total: int, chunk: bytes) -> None:
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
        return self.held_bytes() + extra > self.max_total_bytes

    def sweep_partials(self) -> None:
        """Close connections whose half-received object has had no new part for
        ``partial_timeout`` seconds (unless the relay itself paused their reading)."""
        if self.closing:
            return
        now = time.monotonic()
        for conn in list(self.connections):
            since = conn.last_part
            if since is not None and not conn.held and now - since > self.partial_timeout:
                conn._kill(f"no part of a message for {self.partial_timeout:.0f} s")
        reactor.callLater(min(5.0, self.partial_timeout / 4), self.sweep_partials)

    def add_consumable(self, group: str, key: tuple, frames: list[bytes]) -> None:
        queue = self.group_info[group]["to_consume"]
        size = sum(len(f) for f in frames)
        while queue and (
            len(queue) >= self.max_consumables or self.queued_bytes + size > self.max_consumable_bytes
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
                self.max_consumables,
                self.max_consumable_bytes,
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
        reactor.callLater(min(3.0, budget), stop_reactor)

    def maybe_stop(self) -> None:
        if self.closing and not self.connections:
            stop_reactor()


@implementer(IPushProducer)
class RelayProtocol(TlspyoServerProtocol):
    """One connection at the relay (a worker, the trainer, or anybody who found the port)."""

    def __init__(self, server: RelayState, peer: str):
        super().__init__(server)
        self._peer = peer
        self._reader = _FrameReader(server.header_size, server.password_bytes, server.cfg["max_frame_bytes"])
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
        self._handshake_timer = reactor.callLater(
            self._server.cfg["handshake_timeout"], self._handshake_expired
        )

    def _handshake_expired(self) -> None:
        self._handshake_timer = None
        if self._state == _HANDSHAKE:
            self._kill(f"no handshake within {self._server.cfg['handshake_timeout']:.0f} s")

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
                    self._kill("a frame that is not tmrl wire data (pickle and other formats are refused)")
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
                type(g) is str and g in srv.group_info and type(n) is int and n != 0 for g, n in dest.items()
            )
        ):
            self._kill("malformed destination")
            return
        if not _valid_chunk(obj, self._server.cfg["max_object_bytes"]):
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
                f"the relay's memory budget of {srv.max_total_bytes} bytes is used up (config key "
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
        if consumers:
            self._collect(key, consumers, msg_id, idx, count, total, chunk)

    def _collect(
        self,
        key: tuple,
        consumers: dict[str, int],
        msg_id: Any,
        idx: int,
        count: int,
        total: int,
        chunk: bytes,
    ) -> None:
        """Add one frame of an object for the consumers (the trainer); once complete, queue it and
        acknowledge it to its sender."""
        srv = self._server
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


def _listen(cfg: dict[str, Any], factory: RelayFactory, writer: _pipe.PipeWriter) -> Any:
    """Listen on the configured port (TLS or plain TCP); ``None`` after reporting why not."""
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
                return None
            return reactor.listenSSL(port, factory, ctx, interface=interface)
        return reactor.listenTCP(port, factory, interface=interface)
    except CannotListenError as e:
        err = e.socketError
        if getattr(err, "errno", None) == errno.EADDRINUSE:
            msg = f"port {port} is already in use: {err}; stop the other server or choose another port"
        else:
            msg = f"cannot listen on port {port}: {err}"
        writer.send(_pipe.READY, wire.encode({"error": msg}))
        return None


def _control_loop(state: RelayState, stdin: Any) -> None:
    """The control thread: wait for the parent's STOP on the pipe ``stdin`` (or its end of the
    pipe closing)."""
    budget = common._PARENT_GONE_BUDGET
    while True:
        try:
            kind, payload = _pipe.read_message(stdin, 1 << 20)
        except _pipe.PipeClosed:
            break
        if kind == _pipe.STOP:
            budget = common._stop_budget(payload)
            break
    reactor.callFromThread(state.shutdown, budget)


def run_relay(cfg: dict[str, Any], writer: _pipe.PipeWriter, stdin: Any) -> None:
    """Serve as the relay described by ``cfg`` until the parent says stop (or dies); ``writer``
    and ``stdin`` are the pipes to and from the parent."""
    state = RelayState(cfg)
    factory = RelayFactory(state)
    listening = _listen(cfg, factory, writer)
    if listening is None:
        return
    bound = listening.getHost().port
    log_relay.info(
        "relay listening on %s port %d (%s)",
        cfg["interface"] or "all interfaces",
        bound,
        cfg["security"] or "plain TCP",
    )
    writer.send(_pipe.READY, wire.encode({"ok": True, "port": bound}))
    reactor.callLater(min(5.0, state.partial_timeout / 4), state.sweep_partials)
    common._serve(state.shutdown, lambda: _control_loop(state, stdin))
