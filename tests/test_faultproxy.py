"""The chaos tests' TCP fault proxy (bench/faultproxy.py) in front of a plain echo server on
127.0.0.1: forwarding, latency with jitter (in order), a bandwidth cap, dropped connections,
partitions (cut, stall, refuse) healed on time or on demand, a target that is down, a schedule.
Fast, real sockets, no tmrl. Timings are asserted only as lower bounds (a busy machine is slower,
never faster)."""

from __future__ import annotations

import socket
import socketserver
import sys
import threading
import time
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench.faultproxy import FaultProxy

pytestmark = pytest.mark.timeout(60)


class _Echo(socketserver.BaseRequestHandler):
    def handle(self) -> None:
        while True:
            try:
                data = self.request.recv(65536)
            except OSError:
                return
            if not data:
                return
            self.request.sendall(data)


class _Server(socketserver.ThreadingTCPServer):
    daemon_threads = True
    allow_reuse_address = True


@pytest.fixture
def echo():
    server = _Server(("127.0.0.1", 0), _Echo)
    thread = threading.Thread(target=server.serve_forever, daemon=True)
    thread.start()
    yield server
    server.shutdown()
    server.server_close()


@pytest.fixture
def proxy(echo):
    p = FaultProxy(echo.server_address[1], seed=1).start()
    yield p
    p.close()


def connect(proxy: FaultProxy, timeout: float = 10.0) -> socket.socket:
    s = socket.create_connection(("127.0.0.1", proxy.port), timeout=timeout)
    s.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
    return s


def recv_exactly(s: socket.socket, n: int) -> bytes:
    out = b""
    while len(out) < n:
        chunk = s.recv(n - len(out))
        if not chunk:
            raise ConnectionError(f"closed after {len(out)} of {n} bytes")
        out += chunk
    return out


def echoes(s: socket.socket, data: bytes) -> bool:
    s.sendall(data)
    return recv_exactly(s, len(data)) == data


def wait_until(cond, timeout: float = 10.0) -> None:
    """Poll the proxy's own state (it changes on its thread)."""
    deadline = time.monotonic() + timeout
    while not cond():
        assert time.monotonic() < deadline, "timed out"
        time.sleep(0.01)


def is_cut(s: socket.socket, timeout: float = 10.0) -> bool:
    """Whether the connection is closed by the other end (reset or end of stream)."""
    s.settimeout(timeout)
    try:
        return s.recv(1) == b""
    except (ConnectionResetError, BrokenPipeError):
        return True
    except TimeoutError:
        return False


def test_forwards_both_ways_and_counts(proxy):
    with connect(proxy) as s:
        assert echoes(s, b"hello" * 1000)
    assert proxy.stats.accepted == 1 and proxy.stats.forwarded == 1
    assert proxy.stats.bytes_up == proxy.stats.bytes_down == 5000


def test_latency_with_jitter_delays_every_chunk_and_keeps_the_order(proxy):
    proxy.set_latency(100, jitter_ms=50)
    with connect(proxy) as s:
        t0 = time.monotonic()
        assert echoes(s, b"x")
        assert time.monotonic() - t0 >= 2 * 0.05  # 50 ms at least each way
        msgs = [f"{i:04d}".encode() for i in range(40)]
        for m in msgs:  # 40 chunks, each with its own jitter: 10 ms apart, so that each is read alone
            s.sendall(m)
            time.sleep(0.01)
        assert recv_exactly(s, 160) == b"".join(msgs)
    proxy.heal()
    with connect(proxy) as s:
        t0 = time.monotonic()
        assert echoes(s, b"y")


def test_the_bandwidth_cap_holds_each_direction(proxy):
    proxy.set_bandwidth(100_000)
    data = bytes(range(256)) * 200  # 51,200 bytes: >= 0.5 s up, and as much down
    with connect(proxy) as s:
        t0 = time.monotonic()
        threading.Thread(target=s.sendall, args=(data,), daemon=True).start()
        assert recv_exactly(s, len(data)) == data
        assert time.monotonic() - t0 >= 0.5


def test_drop_cuts_open_connections_and_new_ones_work(proxy):
    a, b = connect(proxy), connect(proxy)
    assert echoes(a, b"1") and echoes(b, b"2")
    assert proxy.drop() == 2
    assert is_cut(a) and is_cut(b)
    with connect(proxy) as c:
        assert echoes(c, b"3")
    a.close()
    b.close()


def test_a_cut_partition_cuts_holds_new_connections_and_heals_on_time(proxy):
    old = connect(proxy)
    assert echoes(old, b"before")
    proxy.partition(mode="cut")
    assert is_cut(old)
    held = connect(proxy)  # accepted, never forwarded
    held.sendall(b"lost?")
    wait_until(lambda: proxy.stats.held == 1)
    held.settimeout(0.5)
    with pytest.raises(TimeoutError):
        held.recv(1)
    assert proxy.partitioned
    proxy.heal()
    assert is_cut(held)  # the held ones are cut at the heal: the client connects again
    with connect(proxy) as s:
        assert echoes(s, b"after")
    # healed by itself after the given time
    proxy.partition(1.0)
    t0 = time.monotonic()
    with connect(proxy) as s:  # held, then cut at the heal
        assert is_cut(s)
        assert time.monotonic() - t0 >= 0.9
    assert not proxy.partitioned
    with connect(proxy) as s:
        assert echoes(s, b"again")
    old.close()
    held.close()


def test_a_stalled_link_keeps_its_connections_and_delivers_at_the_heal(proxy):
    s = connect(proxy)
    assert echoes(s, b"before")
    proxy.partition(mode="stall")
    s.sendall(b"waits")
    s.settimeout(0.5)
    with pytest.raises(TimeoutError):
        s.recv(1)
    proxy.heal()
    s.settimeout(10)
    assert recv_exactly(s, 5) == b"waits"
    s.close()


def test_a_refusing_partition_cuts_every_new_connection(proxy):
    proxy.partition(mode="refuse")
    with connect(proxy) as s:
        assert is_cut(s)
    proxy.heal()
    with connect(proxy) as s:
        assert echoes(s, b"ok")
    with pytest.raises(ValueError):
        proxy.partition(mode="sometimes")


def test_a_target_that_is_down_cuts_the_connection(echo):
    with socket.socket() as free:
        free.bind(("127.0.0.1", 0))
        dead_port = free.getsockname()[1]
    with FaultProxy(dead_port).start() as p:
        with connect(p) as s:
            assert is_cut(s)
        assert p.stats.target_refused == 1


def test_a_schedule_applies_its_steps_in_time(proxy):
    proxy.schedule([(0.0, "partition", {"mode": "refuse"}), (0.4, "heal", {})])
    with connect(proxy) as s:
        assert is_cut(s)
    deadline = time.monotonic() + 10
    while proxy.partitioned and time.monotonic() < deadline:
        time.sleep(0.02)  # polling the proxy's own state: the heal is due 0.4 s after the start
    assert not proxy.partitioned
    with connect(proxy) as s:
        assert echoes(s, b"healed")
    assert [what for _, what in proxy.stats.events] == ["partition refuse", "healed", "cleared"]
    with pytest.raises(ValueError):
        proxy.schedule([(1.0, "close", {})])


def test_an_armed_partition_starts_with_a_large_chunk_and_loses_it(proxy):
    s = connect(proxy)
    proxy.partition(mode="cut", on_chunk_bytes=1000)
    assert not proxy.partitioned  # armed: small chunks still pass
    assert echoes(s, b"small")
    s.sendall(b"x" * 5000)  # the trigger: lost with the connection
    assert is_cut(s)
    assert proxy.stats.lost_chunks == 1 and proxy.stats.bytes_up == 5 and proxy.partitioned
    held = connect(proxy)
    wait_until(lambda: proxy.stats.held == 1)  # the proxy's own count: accepted and held
    proxy.heal()
    assert is_cut(held)
    with connect(proxy) as after:
        assert echoes(after, b"after")
    s.close()
    held.close()


def test_an_armed_partition_can_wait_for_a_marker_in_the_chunk(proxy):
    s = connect(proxy)
    proxy.partition(mode="cut", on_chunk_bytes=100, on_chunk_holding=b"PUB samples")
    assert echoes(s, b"y" * 2000)  # large, without the marker: passes
    s.sendall(b"PUB samples " + b"z" * 200)
    assert is_cut(s) and proxy.partitioned and proxy.stats.lost_chunks == 1
    proxy.heal()
    s.close()
