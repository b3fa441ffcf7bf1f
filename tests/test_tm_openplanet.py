"""OpenPlanet telemetry client against a fake TMRL_GrabData plugin: a real TCP server on loopback
that writes real 44-byte frames, and can stall, stop and restart on the same port."""

from __future__ import annotations

import socket
import threading

import pytest

from tmrl.errors import UserError
from tmrl.tm.openplanet import FRAME_BYTES, OpenPlanetClient, Telemetry, TelemetryTimeout, pack_frame


class FakePlugin:
    """Listens like the plugin; frames are written only when the test asks (so it can stall)."""

    def __init__(self, port: int) -> None:
        self.port = port
        self.accepted = threading.Semaphore(0)  # released once per accepted connection
        self._conn: socket.socket | None = None
        self._srv: socket.socket | None = None
        self._thread: threading.Thread | None = None

    def start(self) -> FakePlugin:
        srv = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        srv.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        srv.bind(("127.0.0.1", self.port))
        srv.listen(1)
        self._srv = srv
        self._thread = threading.Thread(target=self._accept, args=(srv,), daemon=True)
        self._thread.start()
        return self

    def _accept(self, srv: socket.socket) -> None:
        try:
            conn, _ = srv.accept()
        except OSError:
            return
        conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        self._conn = conn
        self.accepted.release()

    def wait_client(self, timeout: float = 10.0) -> None:
        assert self.accepted.acquire(timeout=timeout), "client never connected"

    def send_raw(self, data: bytes) -> None:
        assert self._conn is not None
        self._conn.sendall(data)

    def send(self, *frames: tuple[float, ...]) -> None:
        self.send_raw(b"".join(pack_frame(f) for f in frames))

    def stop(self) -> None:
        if self._conn is not None:
            self._conn.close()
            self._conn = None
        if self._srv is not None:
            self._srv.close()
            self._srv = None
        if self._thread is not None:
            self._thread.join(timeout=5)


def frame(i: float) -> tuple[float, ...]:
    # distinct, exactly representable float32 values
    return (10.0 * i, i, 100.0 + i, 9.5, -3.25, 0.5, 1.0, 0.0, 0.0, 3.0, 5000.0 + i)


@pytest.fixture
def plugin(port_factory):
    fake = FakePlugin(port_factory()).start()
    yield fake
    fake.stop()


@pytest.fixture
def client(plugin):
    c = OpenPlanetClient(port=plugin.port, timeout=5.0, first_timeout=5.0, retry_interval=0.05)
    yield c
    c.close()


def test_frame_layout_is_44_bytes_of_little_endian_float32():
    raw = pack_frame(frame(1))
    assert len(raw) == FRAME_BYTES == 44
    assert raw[:4] == b"\x00\x00\x20\x41"  # 10.0f little-endian


def test_newest_complete_frame_wins(plugin, client):
    plugin.wait_client()
    plugin.send(frame(1), frame(2), frame(3))
    assert client.wait_frames(3, timeout=5)
    data = client.retrieve_data()
    assert isinstance(data, Telemetry)
    assert data == Telemetry(*frame(3))
    assert data[2] == data.x == 103.0 and data.rpm == 5003.0


def test_each_frame_is_returned_once(plugin, client):
    plugin.wait_client()
    plugin.send(frame(1))
    assert client.retrieve_data().distance == 1.0
    with pytest.raises(TelemetryTimeout):
        client.retrieve_data(timeout=0.2)  # the same frame is not returned twice
    plugin.send(frame(2))
    assert client.retrieve_data().distance == 2.0


def test_partial_frames_are_completed_not_returned(plugin, client):
    plugin.wait_client()
    raw1, raw2, raw3 = (pack_frame(frame(i)) for i in (1, 2, 3))
    for piece in (raw1[:5], raw1[5:30], raw1[30:]):
        plugin.send_raw(piece)
    assert client.retrieve_data() == Telemetry(*frame(1))
    plugin.send_raw(raw2[:30])
    with pytest.raises(TelemetryTimeout):
        client.retrieve_data(timeout=0.2)  # 30 bytes are not a frame
    plugin.send_raw(raw2[30:] + raw3[:7])
    assert client.retrieve_data() == Telemetry(*frame(2))
    plugin.send_raw(raw3[7:])
    assert client.retrieve_data() == Telemetry(*frame(3))


def test_stall_raises_a_user_error_with_a_hint(plugin, client):
    plugin.wait_client()
    plugin.send(frame(1))
    client.retrieve_data()
    with pytest.raises(TelemetryTimeout) as err:
        client.retrieve_data(timeout=0.2)
    assert isinstance(err.value, UserError)
    msg = str(err.value)
    assert "stopped sending" in msg and "TMRL_GrabData" in msg and "\n" not in msg


def test_connected_but_silent_says_so(plugin, client):
    plugin.wait_client()
    with pytest.raises(TelemetryTimeout, match="connected to 127.0.0.1:.* but no telemetry frame"):
        client.retrieve_data(timeout=0.2)


def test_nothing_answers_names_what_to_check(port_factory):
    port = port_factory()
    with OpenPlanetClient(port=port, retry_interval=0.05) as c:
        with pytest.raises(TelemetryTimeout) as err:
            c.retrieve_data(timeout=0.3)
    msg = str(err.value)
    assert f"nothing answers at 127.0.0.1:{port}" in msg
    for needle in ("TrackMania 2020 is running", "enabled", f"holds port {port}"):
        assert needle in msg
    assert "\n" not in msg


def test_reconnects_when_the_plugin_restarts(plugin, client):
    plugin.wait_client()
    plugin.send(frame(1))
    assert client.retrieve_data().distance == 1.0
    plugin.send_raw(pack_frame(frame(9))[:20])  # a partial frame lost with the old connection
    plugin.stop()
    plugin.start()  # same port, as when the game restarts
    plugin.wait_client()
    plugin.send(frame(2))
    assert client.retrieve_data() == Telemetry(*frame(2))
    assert client.connections == 2


def test_closed_client_raises_instead_of_hanging(plugin):
    c = OpenPlanetClient(port=plugin.port, retry_interval=0.05)
    c.close()
    with pytest.raises(TelemetryTimeout, match="closed"):
        c.retrieve_data(timeout=5.0)
