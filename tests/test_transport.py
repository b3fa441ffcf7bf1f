"""Tests of tmrl.transport over a real relay on 127.0.0.1 (real processes, real sockets)."""

from __future__ import annotations

import logging
import os
import pickle
import socket
import stat
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import process_support
import pytest

from tmrl import wire
from tmrl.errors import UserError
from tmrl.transport import RelayServer, TrainerLink, WorkerLink, ensure_credentials
from tmrl.transport._netproc import session_token

pytestmark = pytest.mark.timeout(120)

PASSWORD = "correct horse battery staple"
HEADER = 10


def _children() -> list[int]:
    """Pids of this process's live network processes."""
    return process_support.children(command_holds="tmrl.transport._netproc")


def _wait_for(cond: Callable[[], Any], timeout: float = 20.0, what: str = "condition") -> Any:
    """Poll ``cond`` until it is truthy (for effects that happen in another process)."""
    deadline = time.monotonic() + timeout
    while True:
        value = cond()
        if value:
            return value
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out waiting for {what}")
        time.sleep(0.02)


@pytest.fixture(scope="module")
def credentials(tmp_path_factory) -> Path:
    folder = tmp_path_factory.mktemp("credentials")
    ensure_credentials(folder)
    return folder


@pytest.fixture
def net(port_factory, caplog):
    """Start relays and links that are all stopped (and checked gone) at the end of the test."""
    caplog.set_level(logging.DEBUG, logger="tmrl.transport")
    made: list[Any] = []
    # network processes another test left behind are not this test's: CI once saw two (a link of
    # an earlier test still dialling a closed port) fail the first test of this file
    before = set(_children())

    class Net:
        port = port_factory()

        def relay(self, **kw: Any) -> RelayServer:
            kw.setdefault("security", None)
            r = RelayServer(kw.pop("port", self.port), kw.pop("password", PASSWORD), **kw)
            made.append(r)
            return r

        def _link(self, cls: type, kw: dict[str, Any]) -> Any:
            kw.setdefault("security", None)
            link = cls("127.0.0.1", kw.pop("port", self.port), kw.pop("password", PASSWORD), **kw)
            made.append(link)
            return link

        def worker(self, **kw: Any) -> WorkerLink:
            return self._link(WorkerLink, kw)

        def trainer(self, **kw: Any) -> TrainerLink:
            return self._link(TrainerLink, kw)

    yield Net()
    for obj in reversed(made):
        obj.close() if hasattr(obj, "close") else obj.stop()
    assert [pid for pid in _children() if pid not in before] == [], "a network process outlived its test"


def _receive(trainer: TrainerLink, n: int, timeout: float = 30.0) -> list[Any]:
    got: list[Any] = []
    _wait_for(lambda: got.extend(trainer.receive_samples()) or len(got) >= n, timeout, f"{n} objects")
    return got


class _Raw:
    """A plain socket to the relay that has read its HELLO: ``token`` is what a link with the
    right password puts in each frame (the relay's challenge under the password)."""

    def __init__(self, port: int):
        self.sock = socket.create_connection(("127.0.0.1", port), timeout=20)
        length = int(_recv_exact(self, HEADER))
        env = wire.decode(_recv_exact(self, length))
        assert env[1] == "HELLO"
        self.nonce = env[2]
        self.token = session_token(PASSWORD.encode(), self.nonce)

    def sendall(self, data: bytes) -> None:
        self.sock.sendall(data)

    def recv(self, n: int) -> bytes:
        return self.sock.recv(n)

    def close(self) -> None:
        self.sock.close()


def _raw_connect(port: int) -> _Raw:
    """A plain socket to the relay, after reading its HELLO frame."""
    return _Raw(port)


def _recv_exact(s: Any, n: int) -> bytes:
    data = b""
    while len(data) < n:
        chunk = s.recv(n - len(data))
        if not chunk:
            raise ConnectionError("closed")
        data += chunk
    return data


def _closed_by_peer(s: Any) -> bool:
    """True when the relay closes the socket (reads until EOF or reset)."""
    try:
        while s.recv(65536):
            pass
        return True
    except (ConnectionResetError, BrokenPipeError):
        return True
    finally:
        s.close()


def _tlspyo_frame(body: bytes, raw: _Raw) -> bytes:
    return f"{len(body):<{HEADER}}".encode() + raw.token + body


def _log_text(caplog) -> str:
    return "\n".join(r.getMessage() for r in caplog.records)


# ------------------------------------------------------------------------------------------------


def test_samples_flow_from_two_workers_to_the_trainer(net):
    net.relay()
    trainer = net.trainer()
    w1, w2 = net.worker(), net.worker()
    assert trainer.wait_connected(30) and w1.wait_connected(30) and w2.wait_connected(30)
    for i in range(20):
        w1.send_samples({"worker": 1, "i": i, "obs": np.full((3,), i, dtype=np.float32)})
        w2.send_samples(("two", i, None))
    got = _receive(trainer, 40)
    assert len(got) == 40
    from_w1 = [g["i"] for g in got if isinstance(g, dict)]
    from_w2 = [g[1] for g in got if isinstance(g, tuple)]
    assert from_w1 == list(range(20)) and from_w2 == list(range(20))  # order kept per worker
    obs = next(g for g in got if isinstance(g, dict) and g["i"] == 7)["obs"]
    assert obs.dtype == np.float32 and obs.flags.writeable and np.all(obs == 7)


def test_weights_reach_connected_and_late_workers_latest_only(net):
    net.relay()
    trainer = net.trainer()
    early = net.worker()
    assert trainer.wait_connected(30) and early.wait_connected(30)
    trainer.broadcast_weights(b"v1")
    assert early.latest_weights(block=True, timeout=30) == b"v1"
    assert early.latest_weights() is None  # each broadcast is returned once
    trainer.broadcast_weights(b"v2")
    trainer.broadcast_weights(b"v3")
    late = net.worker()
    assert late.latest_weights(block=True, timeout=30) == b"v3"
    _wait_for(lambda: early._weights == b"v3", what="v3 at the early worker")
    assert early.latest_weights() == b"v3"  # v2 was dropped: only the newest is kept


def test_a_worker_that_connects_during_a_multi_frame_broadcast_gets_it(net):
    net.relay(max_frame_bytes=1 << 18)
    trainer = net.trainer(max_frame_bytes=1 << 18)
    assert trainer.wait_connected(30)
    big = np.random.default_rng(0).bytes(3_000_000)  # ~15 frames of 192 KiB
    trainer.broadcast_weights(big)
    late = net.worker(max_frame_bytes=1 << 18)
    assert late.latest_weights(block=True, timeout=60) == big


def test_second_trainer_is_refused_with_a_clear_log_line(net, caplog):
    net.relay()
    first = net.trainer()
    assert first.wait_connected(30)
    second = net.trainer()
    _wait_for(lambda: second.refused, what="the refusal")
    assert "second trainer" in second.refused and not second.connected
    _wait_for(lambda: "refused a second trainer" in _log_text(caplog), what="the relay's log line")
    assert first.connected


def test_wrong_password_is_refused_and_never_logged(net, caplog):
    net.relay()
    wrong = "hunter2-wrong-password"
    bad = net.worker(password=wrong)
    _wait_for(lambda: bad.refused, what="the refusal")
    assert bad.refused == "wrong password" and not bad.connected
    s = _raw_connect(net.port)
    s.sendall(f"{len(hello := wire.encode((1, 'HELLO', None, ('workers',)))):<{HEADER}}".encode() + b"x" * 32 + hello)
    assert _closed_by_peer(s)
    _wait_for(lambda: "wrong password" in _log_text(caplog), what="the relay's log line")
    text = _log_text(caplog)
    assert wrong not in text and "x" * len(PASSWORD) not in text and PASSWORD not in text


def test_garbage_and_oversized_frames_leave_the_relay_up(net, caplog):
    relay = net.relay(max_frame_bytes=1 << 20)
    s = _raw_connect(net.port)
    s.sendall(b"GET / HTTP/1.1\r\nHost: x\r\n\r\n" + os.urandom(200))
    assert _closed_by_peer(s)
    s = _raw_connect(net.port)
    s.sendall(f"{10**9:<{HEADER}}".encode() + s.token + b"\x00" * 100)
    assert _closed_by_peer(s)
    s = _raw_connect(net.port)  # right password, garbage envelope
    s.sendall(_tlspyo_frame(os.urandom(64), s))
    assert _closed_by_peer(s)
    _wait_for(lambda: "exceeds max_frame_bytes" in _log_text(caplog), what="the oversized-frame log line")
    assert "invalid frame header" in _log_text(caplog)
    assert relay.running
    trainer, worker = net.trainer(), net.worker()
    worker.send_samples("still works")
    assert _receive(trainer, 1) == ["still works"]


class _TouchOnUnpickle:
    def __init__(self, path: Path):
        self.path = path

    def __reduce__(self):
        return (open, (str(self.path), "w"))


def _link_records(caplog, text: str) -> list[logging.LogRecord]:
    """Records of the links' own logger (the owner's process) that contain ``text``."""
    return [r for r in caplog.records if r.name == "tmrl.transport.links" and text in r.getMessage()]


def _raw_peer(port: int, group: str) -> socket.socket:
    """A raw tlspyo client, past the handshake, in ``group``."""
    s = _raw_connect(port)
    s.sendall(_tlspyo_frame(wire.encode((1, "HELLO", None, (group,))), s))
    assert wire.decode(_recv_exact(s, int(_recv_exact(s, HEADER))))[1] == "WELCOME"
    return s


def _raw_object(s: socket.socket, msg_id: int, dest: dict[str, int], payload: bytes) -> None:
    """Send ``payload`` as one object of one chunk to ``dest``."""
    frame = ((7, msg_id), 0, 1, len(payload), payload)
    s.sendall(_tlspyo_frame(wire.encode((msg_id + 1, "OBJ", dest, frame)), s))


def test_pickled_envelope_is_refused_by_the_relay(net, tmp_path, caplog):
    net.relay()
    marker = tmp_path / "pwned_by_envelope"
    s = _raw_connect(net.port)
    s.sendall(_tlspyo_frame(pickle.dumps((1, "HELLO", None, _TouchOnUnpickle(marker))), s))
    assert _closed_by_peer(s)
    _wait_for(lambda: "not tmrl wire data" in _log_text(caplog), what="the relay's log line")
    assert not marker.exists()


def test_trainer_link_refuses_a_delivered_pickle_by_default(net, tmp_path, caplog):
    net.relay()
    trainer = net.trainer()  # allow_pickle left at its default
    assert trainer.wait_connected(30)
    marker = tmp_path / "pwned_by_samples"
    s = _raw_peer(net.port, "workers")
    _raw_object(s, 1, {"trainers": 1}, pickle.dumps(_TouchOnUnpickle(marker)))
    _raw_object(s, 2, {"trainers": 1}, wire.encode("after the pickle"))
    # The relay keeps a worker's order: once the second object is out, the pickle went through
    # the trainer link's decoder before it.
    assert _receive(trainer, 1) == ["after the pickle"]
    s.close()
    assert _link_records(caplog, "dropped a sample batch that could not be decoded")
    assert _link_records(caplog, "pickle is refused unless allow_pickle is set")
    assert not marker.exists()


def test_worker_link_refuses_delivered_pickled_weights_by_default(net, tmp_path, caplog):
    net.relay()
    worker = net.worker()
    assert worker.wait_connected(30)
    marker = tmp_path / "pwned_by_weights"
    s = _raw_peer(net.port, "trainers")  # a hostile trainer that knows the password
    _raw_object(s, 1, {"workers": -1}, pickle.dumps(_TouchOnUnpickle(marker)))
    _wait_for(lambda: _link_records(caplog, "dropped weights that could not be decoded"), what="the refusal")
    _raw_object(s, 2, {"workers": -1}, wire.encode(b"good weights"))
    assert worker.latest_weights(block=True, timeout=30) == b"good weights"  # the link still works
    s.close()
    assert _link_records(caplog, "pickle is refused unless allow_pickle is set")
    assert not marker.exists()


def test_allow_pickle_reaches_both_links(net, tmp_path, port_factory):
    # The opt-in really switches the decoder: the same payloads are unpickled.
    net.relay()
    trainer = net.trainer(allow_pickle=True)
    assert trainer.wait_connected(30)
    to_trainer, to_worker = tmp_path / "unpickled_by_trainer", tmp_path / "unpickled_by_worker"
    s = _raw_peer(net.port, "workers")
    _raw_object(s, 1, {"trainers": 1}, pickle.dumps(_TouchOnUnpickle(to_trainer)))
    got = _receive(trainer, 1)
    got[0].close()  # the unpickled object is the file that __reduce__ opened
    s.close()
    assert to_trainer.exists()
    # A second relay, whose trainer is the raw peer (a relay takes one trainer).
    port = port_factory()
    net.relay(port=port)
    worker = net.worker(port=port, allow_pickle=True)
    assert worker.wait_connected(30)
    s = _raw_peer(port, "trainers")
    _raw_object(s, 1, {"workers": -1}, pickle.dumps(_TouchOnUnpickle(to_worker)))
    _wait_for(to_worker.exists, what="the worker link to unpickle the broadcast")
    s.close()


def test_tls_with_fresh_credentials(net, tmp_path):
    folder = tmp_path / "creds"
    key, cert = ensure_credentials(folder)
    assert key.name == "key.pem" and cert.name == "certificate.pem"
    if os.name == "posix":  # (Windows has no such file modes)
        assert stat.S_IMODE(key.stat().st_mode) == 0o600
    before = (key.read_bytes(), cert.read_bytes())
    assert ensure_credentials(folder) == (key, cert) and (key.read_bytes(), cert.read_bytes()) == before
    worker_folder = tmp_path / "worker_creds"  # a worker machine holds the certificate only
    worker_folder.mkdir()
    (worker_folder / "certificate.pem").write_bytes(cert.read_bytes())
    net.relay(security="TLS", keys_dir=folder)
    trainer = net.trainer(security="TLS", keys_dir=worker_folder)
    worker = net.worker(security="TLS", keys_dir=worker_folder)
    worker.send_samples([np.arange(4)])
    got = _receive(trainer, 1)
    assert np.array_equal(got[0][0], np.arange(4))
    trainer.broadcast_weights(b"tls weights")
    assert worker.latest_weights(block=True, timeout=30) == b"tls weights"


def test_tls_with_a_foreign_certificate_does_not_connect(net, tmp_path, credentials, caplog):
    other = tmp_path / "other"
    ensure_credentials(other)
    net.relay(security="TLS", keys_dir=credentials)
    worker = net.worker(security="TLS", keys_dir=other)
    _wait_for(lambda: "check that certificate.pem is the server's" in _log_text(caplog), what="a TLS failure")
    assert not worker.connected
    assert any(
        r.levelno == logging.WARNING and "cannot reach the server" in r.getMessage() for r in caplog.records
    )


def test_configuration_mistakes_are_one_line_user_errors(tmp_path, port_factory):
    before = set(_children())  # another test's leftovers are not this test's (see the net fixture)
    with pytest.raises(UserError, match="python -m tmrl --install"):
        RelayServer(port_factory(), PASSWORD, keys_dir=tmp_path / "missing")
    with pytest.raises(UserError, match="python -m tmrl --install"):
        WorkerLink("127.0.0.1", port_factory(), PASSWORD)  # TLS, no keys_dir
    with pytest.raises(UserError, match="allow_plain_tcp"):
        WorkerLink("192.0.2.1", port_factory(), PASSWORD, security=None)
    with pytest.raises(UserError, match="security"):
        TrainerLink("127.0.0.1", port_factory(), PASSWORD, security="SSLv2")
    broken = tmp_path / "broken"
    broken.mkdir()
    (broken / "key.pem").write_text("not a key")
    (broken / "certificate.pem").write_text("not a certificate")
    with pytest.raises(UserError, match="cannot load the TLS credentials"):
        RelayServer(port_factory(), PASSWORD, keys_dir=broken)
    assert set(_children()) - before == set()


def test_a_busy_port_is_reported_once_without_traceback(port_factory, caplog):
    before = set(_children())
    with socket.socket() as blocker:
        blocker.bind(("127.0.0.1", 0))
        blocker.listen()
        port = blocker.getsockname()[1]
        with pytest.raises(UserError) as info:
            RelayServer(port, PASSWORD, security=None)
    msg = str(info.value)
    assert msg.startswith(f"port {port} is already in use: ") and "\n" not in msg
    assert "Traceback" not in _log_text(caplog)
    assert set(_children()) - before == set()


def test_links_need_no_local_ports_and_survive_a_relay_restart(net):
    relay = net.relay()
    trainer = net.trainer()
    workers = [net.worker(local_port=None) for _ in range(3)]
    assert all(w.wait_connected(30) for w in workers) and trainer.wait_connected(30)
    trainer.broadcast_weights(b"w1")
    relay.stop()
    _wait_for(lambda: not trainer.connected and not any(w.connected for w in workers), what="disconnection")
    workers[0].send_samples("sent while the relay was down")
    net.relay()  # same port
    assert all(w.wait_connected(30) for w in workers) and trainer.wait_connected(30)
    assert _receive(trainer, 1) == ["sent while the relay was down"]
    trainer.broadcast_weights(b"w2")
    for w in workers:
        seen: list[Any] = []
        _wait_for(lambda w=w, seen=seen: seen.append(w.latest_weights()) or b"w2" in seen, what="w2")


def test_relay_holds_workers_back_instead_of_dropping_when_the_trainer_lags(net, caplog):
    caplog.set_level(logging.INFO, logger="tmrl.transport")
    net.relay(max_consumables=4)  # the relay stops reading workers at 3 pending batches
    worker = net.worker()
    assert worker.wait_connected(30)
    for i in range(20):
        worker.send_samples(i)
    _wait_for(lambda: "workers wait until it catches up" in _log_text(caplog), what="the back-pressure log line")
    trainer = net.trainer()
    assert _receive(trainer, 20) == list(range(20))  # nothing dropped, in order
    assert "dropped" not in _log_text(caplog)


def test_trainer_link_memory_is_bounded_by_its_credit(net):
    net.relay(max_consumables=1000)
    trainer = net.trainer()
    worker = net.worker()
    assert trainer.wait_connected(30) and worker.wait_connected(30)
    for i in range(200):
        worker.send_samples(i)
    _wait_for(lambda: len(trainer._inbox) >= 64, what="the first 64 objects")
    time.sleep(0.3)  # give the relay a chance to (wrongly) push more; nothing must arrive
    assert len(trainer._inbox) == 64
    assert _receive(trainer, 200) == list(range(200))


@pytest.mark.parametrize("n_floats", [1_000_000, 20_000_000])
def test_big_weight_broadcast_completes(net, n_floats, capsys):
    net.relay()
    trainer = net.trainer()
    worker = net.worker()
    assert trainer.wait_connected(30) and worker.wait_connected(30)
    weights = wire.encode({"w": np.random.default_rng(0).standard_normal(n_floats).astype(np.float32)})
    t0 = time.perf_counter()
    trainer.broadcast_weights(weights)
    got = worker.latest_weights(block=True, timeout=100)
    elapsed = time.perf_counter() - t0
    assert got == weights
    with capsys.disabled():
        print(f"\n[transport] broadcast of {n_floats} float32 ({len(weights) / 1e6:.0f} MB): {elapsed:.2f} s")


_OWNER_SCRIPT = """
import signal, sys, time
from tmrl.transport import RelayServer, WorkerLink
relay = RelayServer(int(sys.argv[1]), "pw", security=None)
link = WorkerLink("127.0.0.1", int(sys.argv[1]), "pw", security=None)
print(relay.pid, link.pid, flush=True)
while True:
    time.sleep(0.05)
"""


def _pid_gone(pid: int) -> bool:
    return not process_support.alive(pid)


@pytest.mark.posix
def test_network_processes_end_with_their_owner_on_ctrl_c_and_free_the_port(tmp_path, port_factory):
    import signal

    # Ctrl-C reaches the whole process group in a terminal; here it is sent to the owner only,
    # and the network processes ignore SIGINT anyway: they end because their owner does.
    _network_processes_end_with_their_owner(tmp_path, port_factory, lambda owner: owner.send_signal(signal.SIGINT))


def test_network_processes_end_with_their_killed_owner_and_free_the_port(tmp_path, port_factory):
    # SIGKILL, or TerminateProcess on Windows: no clean-up in the owner
    _network_processes_end_with_their_owner(tmp_path, port_factory, lambda owner: owner.kill())


def _network_processes_end_with_their_owner(tmp_path, port_factory, stop: Callable[[Any], None]) -> None:
    import subprocess
    import sys

    script = tmp_path / "owner.py"
    script.write_text(_OWNER_SCRIPT)
    port = port_factory()
    owner = subprocess.Popen([sys.executable, str(script), str(port)], stdout=subprocess.PIPE, text=True)
    try:
        pids = [int(p) for p in owner.stdout.readline().split()]
        assert len(pids) == 2 and not any(_pid_gone(p) for p in pids)
        stop(owner)
        owner.wait(30)
    finally:
        if owner.poll() is None:
            owner.kill()
        owner.stdout.close()
    _wait_for(lambda: all(_pid_gone(p) for p in pids), what="the network processes to exit")
    with socket.socket() as s:  # the port is free again
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        s.bind(("127.0.0.1", port))


_rss_bytes = process_support.rss_bytes


def test_a_stalled_worker_does_not_make_the_relay_buffer_every_broadcast(net, caplog):
    relay = net.relay()
    trainer, stalled, fresh = net.trainer(), net.worker(), net.worker()
    assert trainer.wait_connected(30) and stalled.wait_connected(30) and fresh.wait_connected(30)
    size = 4 * 2**20
    trainer.broadcast_weights(b"\x00" * size)
    _wait_for(lambda: fresh._weights is not None, what="the first broadcast")
    base = _rss_bytes(relay.pid)
    process_support.freeze(stalled.pid)  # its network process stops reading its socket
    try:
        for i in range(1, 13):  # 48 MiB in total
            trainer.broadcast_weights(bytes([i]) * size)
            _wait_for(lambda i=i: (fresh._weights or b"\x00")[:1] == bytes([i]), what=f"broadcast {i}")
        grown = _rss_bytes(relay.pid) - base
    finally:
        process_support.thaw(stalled.pid)
    assert grown < 6 * size, f"the relay grew by {grown / 2**20:.0f} MiB for a stalled worker"
    _wait_for(
        lambda: (stalled._weights or b"\x00")[:1] == bytes([12]),
        what="the newest weights at the stalled worker",
    )
    assert "it will get the newest broadcast when it catches up" in _log_text(caplog)


def test_a_worker_cannot_broadcast_fake_weights(net, caplog):
    net.relay()
    victim = net.worker()
    assert victim.wait_connected(30)
    s = _raw_connect(net.port)
    s.sendall(_tlspyo_frame(wire.encode((1, "HELLO", None, ("workers",))), s))
    assert wire.decode(_recv_exact(s, int(_recv_exact(s, HEADER))))[1] == "WELCOME"
    fake = wire.encode(b"fake weights")
    s.sendall(_tlspyo_frame(wire.encode((2, "OBJ", {"workers": -1}, ((1, 1), 0, 1, len(fake), fake))), s))
    assert _closed_by_peer(s)
    _wait_for(lambda: "workers may not send" in _log_text(caplog), what="the refusal log line")
    assert victim.latest_weights() is None


def test_a_killed_trainer_is_replaced_and_gets_the_backlog(net):
    net.relay()
    first = net.trainer()
    worker = net.worker()
    assert first.wait_connected(30) and worker.wait_connected(30)
    process_support.kill(first.pid)  # the trainer's machine process dies without goodbye
    _wait_for(lambda: not first.connected, what="the dead trainer")
    worker.send_samples("kept at the relay")
    second = net.trainer()
    assert second.wait_connected(30)
    assert _receive(second, 1) == ["kept at the relay"]


def test_samples_in_flight_to_a_dying_trainer_go_to_the_next_one(net, caplog):
    net.relay()
    worker = net.worker()
    first = net.trainer()
    assert first.wait_connected(30) and worker.wait_connected(30)
    _wait_for(lambda: "asks for 64 more sample batches" in _log_text(caplog), what="the trainer's credit")
    process_support.freeze(first.pid)  # it stops reading: what the relay sends it stays unacknowledged
    for i in range(5):
        worker.send_samples(i)
    _wait_for(
        lambda: _log_text(caplog).count("sent a sample batch") >= 5,
        what="the batches sent to the first trainer",
    )
    process_support.kill(first.pid)
    second = net.trainer()
    got = _receive(second, 5)
    assert sorted(set(got)) == [0, 1, 2, 3, 4]  # nothing lost (duplicates would be allowed)
    assert "left with 5 sample batches unacknowledged: queued again" in _log_text(caplog)


def test_samples_unacknowledged_by_a_dying_relay_are_sent_again(net):
    old_relay = net.relay()
    worker = net.worker()
    assert worker.wait_connected(30)
    process_support.freeze(old_relay.pid)  # receives nothing more, acknowledges nothing
    for i in range(3):
        worker.send_samples(("held by the worker", i))
    process_support.kill(old_relay.pid)
    _wait_for(lambda: not worker.connected, what="the worker to notice")
    net.relay()
    trainer = net.trainer()
    got = _receive(trainer, 3)
    assert sorted(set(got)) == [("held by the worker", i) for i in range(3)]


def test_a_silent_connection_is_closed_after_the_handshake_timeout(net, caplog):
    relay = net.relay(handshake_timeout=0.5)
    s = _raw_connect(net.port)  # connects, never authenticates
    assert _closed_by_peer(s)
    _wait_for(lambda: "no handshake within" in _log_text(caplog), what="the timeout log line")
    assert relay.running
