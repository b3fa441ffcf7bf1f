"""A TCP fault proxy on 127.0.0.1, for chaos tests: it listens on a port, forwards every
connection to a target port, and can degrade or break what it forwards, now or on a schedule.

    proxy = FaultProxy(target_port=server_port).start()   # clients connect to proxy.port
    proxy.set_latency(200, jitter_ms=100)                  # each chunk 100-300 ms late, in order
    proxy.set_bandwidth(50_000)                            # bytes/s, each direction
    proxy.drop()                                           # cut every connection now
    proxy.partition(5.0)                                   # cut, hold new connections 5 s, heal
    proxy.heal()                                           # everything back to normal now
    proxy.schedule([(1.0, "partition", {"seconds": 2}), (4.0, "set_latency", {"ms": 50})])
    proxy.close()

A partition has three modes:

- ``"cut"`` (default): existing connections are cut (reset) and new ones are accepted but held,
  nothing forwarded, until the partition heals; then the held ones are cut too, and the clients
  reconnect (what a peer sees when a link goes down long enough for TCP to give up);
- ``"stall"``: nothing is cut, nothing flows: connections stay open and their bytes wait (a
  short outage TCP survives); new ones are held; all resume at the heal;
- ``"refuse"``: existing connections are cut and new ones are cut as soon as they are accepted
  (a machine that answers with resets).

A partition can wait for traffic (``on_chunk_bytes=N``): it is armed, and starts when a client
sends a chunk of at least N bytes (or, ``direction="down"``, the target does), which is lost with
the connections (a link that dies while a batch is on the wire: what the sender must send again).

Latency is added to every chunk in each direction (``ms`` plus a uniform jitter of
``+-jitter_ms``, never reordering bytes); the bandwidth cap holds each direction of each
connection to that many bytes per second. A connection whose target does not accept (the server
is down) is cut at once, as the server's own refusal would be.

Only the standard library is used; the proxy runs its own asyncio loop in a daemon thread.
Importing this module starts nothing.
"""

from __future__ import annotations

import asyncio
import random
import threading
import time
from collections.abc import Iterable
from dataclasses import dataclass, field
from typing import Any

CHUNK = 64 * 1024
"""Most bytes read at once from one side."""
QUEUE_CHUNKS = 64
"""Chunks waiting per direction before the proxy stops reading that side (back-pressure)."""
MODES = ("cut", "stall", "refuse")


@dataclass
class ProxyStats:
    """What a proxy has done so far (read them any time; they only grow)."""

    accepted: int = 0
    """Connections accepted from clients."""
    forwarded: int = 0
    """Connections that reached the target."""
    target_refused: int = 0
    """Connections cut because the target did not accept."""
    cut: int = 0
    """Connections cut by :meth:`FaultProxy.drop`, a partition or a refusal."""
    held: int = 0
    """Connections accepted during a partition and held."""
    bytes_up: int = 0
    """Bytes forwarded from clients to the target."""
    bytes_down: int = 0
    """Bytes forwarded from the target to clients."""
    lost_chunks: int = 0
    """Chunks read from a client and never forwarded (an armed partition's trigger)."""
    events: list[tuple[float, str]] = field(default_factory=list)
    """``(time.monotonic(), what)`` of every control applied (the schedule's too)."""


class _Conn:
    """One client connection and its connection to the target."""

    def __init__(self, client: asyncio.StreamWriter) -> None:
        self.client = client
        self.target: asyncio.StreamWriter | None = None
        self.tasks: list[asyncio.Task] = []
        self.ended = 0  # directions that reached their end of stream

    def abort(self) -> None:
        for w in (self.client, self.target):
            if w is not None:
                w.transport.abort()
        for t in self.tasks:
            t.cancel()


class FaultProxy:
    """Forwards ``listen_port`` of ``host`` to ``target_port`` of ``target_host``, with faults.

    Args:
        target_port: where connections go.
        listen_port: where clients connect (0: a free port, read :attr:`port` after :meth:`start`).
        host: the address listened on.
        target_host: the target's address.
        seed: seeds the latency jitter.
        name: shown in :attr:`stats` events and ``repr``.

    Every control method may be called from any thread; it takes effect before it returns.
    """

    def __init__(self, target_port: int, listen_port: int = 0, host: str = "127.0.0.1",
                 target_host: str = "127.0.0.1", seed: int = 0, name: str = "proxy") -> None:
        self.target = (target_host, int(target_port))
        self.host = host
        self.port = int(listen_port)
        self.name = name
        self.stats = ProxyStats()
        self._rng = random.Random(seed)
        self._latency = 0.0
        self._jitter = 0.0
        self._bandwidth: float | None = None
        self._mode: str | None = None  # the partition's mode while partitioned
        self._heal_handle: asyncio.TimerHandle | None = None
        self._armed: tuple[int, float | None, str, bool, bytes | None] | None = None
        self._conns: set[_Conn] = set()
        self._held: set[_Conn] = set()
        self._loop: asyncio.AbstractEventLoop | None = None
        self._thread: threading.Thread | None = None
        self._server: asyncio.base_events.Server | None = None
        self._flowing: asyncio.Event | None = None
        self._healed: asyncio.Event | None = None

    def __repr__(self) -> str:
        return f"FaultProxy({self.name}: {self.port} -> {self.target[1]})"

    # --- life -------------------------------------------------------------------------------------

    def start(self) -> FaultProxy:
        """Listen (in a new daemon thread) and return self once connections are accepted (a
        proxy already started is returned as it is)."""
        if self._thread is not None:
            return self
        ready = threading.Event()
        failure: list[BaseException] = []

        def run() -> None:
            loop = asyncio.new_event_loop()
            self._loop = loop
            asyncio.set_event_loop(loop)
            try:
                loop.run_until_complete(self._listen())
            except BaseException as e:  # noqa: BLE001 (reported to start())
                failure.append(e)
                ready.set()
                return
            ready.set()
            loop.run_forever()
            loop.close()

        self._thread = threading.Thread(target=run, daemon=True, name=f"faultproxy-{self.name}")
        self._thread.start()
        ready.wait()
        if failure:
            raise failure[0]
        return self

    async def _listen(self) -> None:
        self._flowing = asyncio.Event()
        self._flowing.set()
        self._healed = asyncio.Event()
        self._healed.set()
        self._server = await asyncio.start_server(self._accept, self.host, self.port, reuse_address=True)
        self.port = self._server.sockets[0].getsockname()[1]

    def close(self) -> None:
        """Stop listening, cut every connection and end the thread (idempotent)."""
        loop, thread = self._loop, self._thread
        if loop is None or thread is None or not thread.is_alive():
            return

        async def shut() -> None:
            if self._server is not None:
                self._server.close()
            for c in list(self._conns) + list(self._held):
                c.abort()

        try:
            asyncio.run_coroutine_threadsafe(shut(), loop).result(10)
        finally:
            loop.call_soon_threadsafe(loop.stop)
            thread.join(10)

    def __enter__(self) -> FaultProxy:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.close()

    # --- controls ---------------------------------------------------------------------------------

    def _call(self, fn: Any, *args: Any) -> Any:
        """Run ``fn(*args)`` on the proxy's loop and return its result."""
        assert self._loop is not None, "start() the proxy first"
        if threading.current_thread() is self._thread:
            return fn(*args)

        async def call() -> Any:
            return fn(*args)

        return asyncio.run_coroutine_threadsafe(call(), self._loop).result(10)

    def _note(self, what: str) -> None:
        self.stats.events.append((time.monotonic(), what))

    def set_latency(self, ms: float, jitter_ms: float = 0.0) -> None:
        """Delay every chunk by ``ms`` milliseconds plus a uniform ``+-jitter_ms`` (0: none)."""
        if ms < 0 or jitter_ms < 0:
            raise ValueError("latency and jitter are milliseconds >= 0")

        def apply() -> None:
            self._latency, self._jitter = ms / 1000.0, min(jitter_ms, ms) / 1000.0
            self._note(f"latency {ms:g}+-{jitter_ms:g} ms")

        self._call(apply)

    def set_bandwidth(self, bytes_per_s: float | None) -> None:
        """Cap each direction of each connection at ``bytes_per_s`` (``None``: no cap)."""
        if bytes_per_s is not None and bytes_per_s <= 0:
            raise ValueError("a bandwidth is bytes per second > 0 (None: no cap)")

        def apply() -> None:
            self._bandwidth = None if bytes_per_s is None else float(bytes_per_s)
            self._note(f"bandwidth {bytes_per_s}")

        self._call(apply)

    def drop(self) -> int:
        """Cut every open connection now (clients see a reset); returns how many were cut."""

        def apply() -> int:
            n = len(self._conns)
            for c in list(self._conns):
                c.abort()
            self._conns.clear()
            self.stats.cut += n
            self._note(f"drop ({n} cut)")
            return n

        return self._call(apply)

    def partition(self, seconds: float | None = None, mode: str = "cut", on_chunk_bytes: int | None = None,
                  direction: str = "up", on_chunk_holding: bytes | None = None) -> None:
        """Partition the link (see the module's docstring for ``mode``), healed after ``seconds``
        (``None``: until :meth:`heal`); with ``on_chunk_bytes``, only once a chunk of at least
        that many bytes is read, from a client (``direction`` ``"up"``) or from the target
        (``"down"``), and that holds ``on_chunk_holding`` when given (a protocol's marker, such as
        a subject): that chunk is lost; :attr:`partitioned` tells when."""
        if direction not in ("up", "down"):
            raise ValueError(f"direction {direction!r} is not up or down")
        if mode not in MODES:
            raise ValueError(f"mode {mode!r} is not one of {', '.join(MODES)}")
        if on_chunk_bytes is not None:

            def arm() -> None:
                self._armed = (int(on_chunk_bytes), seconds, mode, direction == "up", on_chunk_holding)
                self._note(f"armed {mode} on a chunk of {on_chunk_bytes} bytes")

            self._call(arm)
            return

        def apply() -> None:
            assert self._loop is not None and self._flowing is not None and self._healed is not None
            self._mode = mode
            self._healed.clear()
            if self._heal_handle is not None:
                self._heal_handle.cancel()
                self._heal_handle = None
            if mode == "stall":
                self._flowing.clear()
            else:
                n = len(self._conns)
                for c in list(self._conns):
                    c.abort()
                self._conns.clear()
                self.stats.cut += n
            if seconds is not None:
                self._heal_handle = self._loop.call_later(seconds, self._heal)
            self._note(f"partition {mode}" + ("" if seconds is None else f" {seconds:g} s"))

        self._call(apply)

    def _heal(self) -> None:
        assert self._flowing is not None and self._healed is not None
        self._armed = None
        if self._heal_handle is not None:
            self._heal_handle.cancel()
            self._heal_handle = None
        was = self._mode
        self._mode = None
        self._flowing.set()
        self._healed.set()
        if was is not None:
            self._note("healed")

    def heal(self, clear: bool = True) -> None:
        """End a partition now; with ``clear``, also remove latency and the bandwidth cap."""

        def apply() -> None:
            self._heal()
            if clear:
                self._latency, self._jitter, self._bandwidth = 0.0, 0.0, None
                self._note("cleared")

        self._call(apply)

    @property
    def partitioned(self) -> bool:
        """Whether a partition is on."""
        return self._mode is not None

    @property
    def open_connections(self) -> int:
        """Connections being forwarded now (held ones not included)."""
        return len(self._conns)

    def schedule(self, steps: Iterable[tuple[float, str, dict[str, Any]]]) -> None:
        """Apply ``(delay_s, method, kwargs)`` steps, each ``delay_s`` seconds from now (methods:
        ``set_latency``, ``set_bandwidth``, ``drop``, ``partition``, ``heal``)."""
        allowed = {"set_latency", "set_bandwidth", "drop", "partition", "heal"}
        steps = list(steps)
        for _, method, _ in steps:
            if method not in allowed:
                raise ValueError(f"{method!r} is not a proxy control ({', '.join(sorted(allowed))})")

        def apply() -> None:
            assert self._loop is not None
            for delay, method, kwargs in steps:
                self._loop.call_later(max(0.0, delay), lambda m=method, k=kwargs: getattr(self, m)(**k))

        self._call(apply)

    # --- forwarding -------------------------------------------------------------------------------

    async def _accept(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        assert self._healed is not None
        self.stats.accepted += 1
        conn = _Conn(writer)
        if self._mode == "refuse":
            self.stats.cut += 1
            writer.transport.abort()
            return
        if self._mode is not None:  # held until the partition heals
            self.stats.held += 1
            self._held.add(conn)
            mode = self._mode
            try:
                await self._healed.wait()
            finally:
                self._held.discard(conn)
            if mode == "cut":
                self.stats.cut += 1
                writer.transport.abort()
                return
        try:
            t_reader, t_writer = await asyncio.open_connection(*self.target)
        except OSError:
            self.stats.target_refused += 1
            writer.transport.abort()
            return
        if self._mode in ("cut", "refuse"):  # partitioned while connecting
            t_writer.transport.abort()
            writer.transport.abort()
            self.stats.cut += 1
            return
        self.stats.forwarded += 1
        conn.target = t_writer
        self._conns.add(conn)
        conn.tasks = [
            asyncio.ensure_future(self._pipe(conn, reader, t_writer, up=True)),
            asyncio.ensure_future(self._pipe(conn, t_reader, writer, up=False)),
        ]

    async def _pipe(self, conn: _Conn, src: asyncio.StreamReader, dst: asyncio.StreamWriter, up: bool) -> None:
        """One direction: read, delay, throttle, write, in order; the end of one side closes both."""
        assert self._flowing is not None
        queue: asyncio.Queue[tuple[float, bytes]] = asyncio.Queue(QUEUE_CHUNKS)
        sender = asyncio.ensure_future(self._send(conn, queue, dst, up))
        last_due = 0.0
        try:
            while True:
                await self._flowing.wait()
                data = await src.read(CHUNK)
                if not data:
                    break
                armed = self._armed
                if (armed is not None and armed[3] == up and len(data) >= armed[0]
                        and (armed[4] is None or armed[4] in data)):
                    _, seconds, mode, _, _ = armed
                    self._armed = None
                    self.stats.lost_chunks += 1
                    sender.cancel()
                    self.partition(seconds, mode)  # this chunk is lost with the connection
                    return
                due = time.monotonic()
                if self._latency:
                    due += self._latency + self._rng.uniform(-self._jitter, self._jitter)
                last_due = due = max(due, last_due)  # jitter never reorders bytes
                await queue.put((due, data))
            await queue.put((0.0, b""))  # end of stream: passed on after what is queued
            await sender
            if dst.can_write_eof():
                dst.write_eof()
            conn.ended += 1
            if conn.ended < 2:
                return  # the other direction goes on (a half-closed connection)
        except (asyncio.CancelledError, ConnectionError, OSError):
            sender.cancel()
        self._conns.discard(conn)
        conn.abort()

    async def _send(self, conn: _Conn, queue: asyncio.Queue, dst: asyncio.StreamWriter, up: bool) -> None:
        assert self._flowing is not None
        while True:
            due, data = await queue.get()
            if not data:
                return
            wait = due - time.monotonic()
            if wait > 0:
                await asyncio.sleep(wait)
            await self._flowing.wait()
            if self._bandwidth:
                await asyncio.sleep(len(data) / self._bandwidth)
            if up:
                self.stats.bytes_up += len(data)
            else:
                self.stats.bytes_down += len(data)
            dst.write(data)
            await dst.drain()
