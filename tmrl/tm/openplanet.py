"""TCP clients of the TMRL OpenPlanet plugins: TMRL_GrabData (telemetry) and TMRL_SaveGhost (replays).

The plugin runs inside TrackMania 2020, listens on ``127.0.0.1:9000`` by default and, once a
client is connected, writes one frame per game frame: 11 little-endian float32 values (44 bytes)

    speed, distance, x, y, z, input steer, input gas, input brake, race finished, gear, rpm

:class:`OpenPlanetClient` keeps a background thread connected to the plugin. The thread drains
the socket and keeps only the newest complete frame (a partial frame waits for its remaining
bytes), and reconnects by itself when the plugin or the game restarts. :meth:`retrieve_data`
returns a frame newer than the last one it returned, or raises :class:`TelemetryTimeout` whose
message says what to check.

The TMRL_SaveGhost plugin listens on ``127.0.0.1:10000``. Its protocol is a bare connection: each
connection it accepts asks it to save the ghost of the race just driven as a replay; nothing is
sent either way. :func:`request_replay` is that request.
"""

from __future__ import annotations

import logging
import socket
import struct
import threading
import time
from typing import NamedTuple

from tmrl.errors import UserError

__all__ = [
    "DEFAULT_HOST",
    "DEFAULT_PORT",
    "FRAME_BYTES",
    "FRAME_FLOATS",
    "FRAME_FORMAT",
    "OpenPlanetClient",
    "Telemetry",
    "TelemetryTimeout",
    "pack_frame",
    "request_replay",
    "SAVEGHOST_PORT",
]

logger = logging.getLogger(__name__)

DEFAULT_HOST = "127.0.0.1"
DEFAULT_PORT = 9000
FRAME_FLOATS = 11
FRAME_FORMAT = "<" + "f" * FRAME_FLOATS
FRAME_BYTES = struct.calcsize(FRAME_FORMAT)  # 44
SAVEGHOST_PORT = 10000
"""Port of the TMRL_SaveGhost plugin."""


class Telemetry(NamedTuple):
    """One telemetry frame of the plugin. A tuple: ``frame[2]`` is ``frame.x``."""

    speed: float
    distance: float
    x: float
    y: float
    z: float
    steer: float
    gas: float
    brake: float
    finished: float
    gear: float
    rpm: float


def pack_frame(values: tuple[float, ...] | list[float] | Telemetry) -> bytes:
    """Encode 11 values as the plugin does (44 bytes, little-endian float32). Used by fakes."""
    return struct.pack(FRAME_FORMAT, *values)


class TelemetryTimeout(UserError):
    """No new telemetry frame arrived in time; the message says what to check."""


def _hint(host: str, port: int) -> str:
    return (
        f"check that TrackMania 2020 is running with a map loaded (car on track, not a menu), that the "
        f"OpenPlanet plugin TMRL_GrabData is installed and enabled (F3 > Developer > Reload plugin), that "
        f"it listens on {host}:{port} (the plugin's port; 9000 unless you changed it), and that no other "
        f"program holds port {port}"
    )


class OpenPlanetClient:
    """Background TCP client of the TMRL_GrabData plugin.

    Args:
        host: address of the plugin (default ``127.0.0.1``).
        port: port of the plugin (default 9000).
        timeout: seconds :meth:`retrieve_data` waits for a new frame once a first frame arrived
            (default 10).
        first_timeout: seconds :meth:`retrieve_data` waits while no frame has ever arrived, which
            leaves time to start the game or load a map (default 60).
        retry_interval: seconds between two connection attempts while nothing answers.
        start: start the background thread now (default); otherwise call :meth:`start`.

    The client is thread-safe. Use it as a context manager or call :meth:`close`.
    """

    def __init__(
        self,
        host: str | None = None,
        port: int | None = None,
        timeout: float | None = None,
        first_timeout: float | None = None,
        retry_interval: float = 0.5,
        start: bool = True,
    ) -> None:
        self.host = DEFAULT_HOST if host is None else host
        self.port = DEFAULT_PORT if port is None else int(port)
        self.timeout = 10.0 if timeout is None else float(timeout)
        self.first_timeout = 60.0 if first_timeout is None else float(first_timeout)
        self.retry_interval = float(retry_interval)
        self._cond = threading.Condition()
        self._stop = threading.Event()
        self._frame: bytes | None = None
        self._seq = 0  # number of complete frames received so far
        self._taken = 0  # value of _seq when retrieve_data last returned
        self._connected = False
        self._connections = 0
        self._last_error: str | None = None
        self._sock: socket.socket | None = None
        self._thread: threading.Thread | None = None
        if start:
            self.start()

    # ------------------------------------------------------------------ lifecycle
    def start(self) -> None:
        """Start the background thread (idempotent)."""
        if self._thread is None:
            self._thread = threading.Thread(target=self._run, name="openplanet-client", daemon=True)
            self._thread.start()

    def close(self) -> None:
        """Stop the background thread and close the socket."""
        self._stop.set()
        sock = self._sock
        if sock is not None:
            try:
                sock.shutdown(socket.SHUT_RDWR)
            except OSError:
                pass
        if self._thread is not None:
            self._thread.join(timeout=5.0)
        with self._cond:
            self._cond.notify_all()

    def __enter__(self) -> OpenPlanetClient:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # ------------------------------------------------------------------ state
    @property
    def connected(self) -> bool:
        """True while a TCP connection to the plugin is open."""
        return self._connected

    @property
    def connections(self) -> int:
        """How many times a connection was established (reconnections included)."""
        return self._connections

    @property
    def frames_received(self) -> int:
        """Number of complete frames received since the client started (dropped ones included)."""
        return self._seq

    # ------------------------------------------------------------------ thread
    def _run(self) -> None:
        attempts = 0
        while not self._stop.is_set():
            try:
                sock = socket.create_connection((self.host, self.port), timeout=max(self.retry_interval, 1.0))
            except OSError as err:
                attempts += 1
                self._last_error = f"{type(err).__name__}: {err}"
                # Quiet for the first seconds (the game may be starting), then a reminder now and then.
                level = logging.INFO if attempts % 20 == 0 else logging.DEBUG
                logger.log(
                    level, "no OpenPlanet plugin at %s:%d yet (%s)", self.host, self.port, self._last_error
                )
                self._stop.wait(self.retry_interval)
                continue
            attempts = 0
            self._sock = sock
            self._connected = True
            self._connections += 1
            self._last_error = None
            logger.info("connected to the OpenPlanet plugin at %s:%d", self.host, self.port)
            try:
                self._receive(sock)
            except OSError as err:
                self._last_error = f"{type(err).__name__}: {err}"
            finally:
                self._connected = False
                self._sock = None
                sock.close()
            if not self._stop.is_set():
                logger.info("OpenPlanet plugin closed the connection; reconnecting")
                self._stop.wait(self.retry_interval)

    def _receive(self, sock: socket.socket) -> None:
        # A short receive timeout lets the thread notice close() without a busy loop.
        sock.settimeout(0.25)
        pending = b""  # bytes of an incomplete frame, kept until the rest arrives
        while not self._stop.is_set():
            try:
                chunk = sock.recv(65536)
            except socket.timeout:
                continue
            if not chunk:
                self._last_error = "connection closed by the plugin"
                return
            pending += chunk
            n = len(pending) // FRAME_BYTES
            if n == 0:
                continue
            # Everything already received is older than the last complete frame: drop it.
            newest = pending[(n - 1) * FRAME_BYTES : n * FRAME_BYTES]
            pending = pending[n * FRAME_BYTES :]
            with self._cond:
                self._frame = newest
                self._seq += n
                self._cond.notify_all()

    # ------------------------------------------------------------------ API
    def retrieve_data(self, timeout: float | None = None) -> Telemetry:
        """Return the newest complete frame, waiting for one newer than the last returned.

        Args:
            timeout: seconds to wait; default ``first_timeout`` until a first frame has arrived,
                ``timeout`` afterwards.

        Raises:
            TelemetryTimeout: no new frame in time (message: what to check).
        """
        if timeout is None:
            timeout = self.timeout if self._seq > 0 else self.first_timeout
        deadline = time.monotonic() + timeout
        with self._cond:
            while self._seq == self._taken:
                left = deadline - time.monotonic()
                if left <= 0 or self._stop.is_set():
                    raise TelemetryTimeout(self._timeout_message(timeout))
                self._cond.wait(left)
            self._taken = self._seq
            frame = self._frame
        assert frame is not None  # set together with _seq
        return Telemetry(*struct.unpack(FRAME_FORMAT, frame))

    def _timeout_message(self, timeout: float) -> str:
        where = f"{self.host}:{self.port}"
        if self._stop.is_set():
            return f"the OpenPlanet client for {where} is closed: create a new one"
        if not self._connected and self._seq == 0:
            cause = f"nothing answers at {where} ({self._last_error or 'no connection yet'})"
        elif not self._connected:
            cause = f"the OpenPlanet plugin at {where} went away ({self._last_error or 'disconnected'})"
        elif self._seq == 0:
            cause = f"connected to {where} but no telemetry frame came in {timeout:g} s"
        else:
            cause = (
                f"OpenPlanet stopped sending frames on {where} for {timeout:g} s (game paused or in a menu?)"
            )
        return f"{cause}: {_hint(self.host, self.port)}"

    def wait_frames(self, count: int, timeout: float) -> bool:
        """Wait until ``frames_received >= count``; return False on timeout."""
        with self._cond:
            return self._cond.wait_for(lambda: self._seq >= count or self._stop.is_set(), timeout) and (
                self._seq >= count
            )

    def measure_rate(self, duration: float = 1.0) -> float:
        """Frames per second the plugin sends, counted over ``duration`` seconds."""
        start_seq = self._seq
        t0 = time.perf_counter()
        self._stop.wait(duration)
        return (self._seq - start_seq) / max(time.perf_counter() - t0, 1e-9)


def request_replay(host: str = DEFAULT_HOST, port: int = SAVEGHOST_PORT, timeout: float = 2.0) -> str | None:
    """Ask the TMRL_SaveGhost plugin to save the last race as a replay: connect, then close (the
    plugin's whole protocol).

    Args:
        host: the plugin's address (the game's machine: 127.0.0.1).
        port: the plugin's port (:data:`SAVEGHOST_PORT`).
        timeout: seconds to wait for the connection.

    Returns:
        None when the plugin took the request, else why not (one line with the fix).
    """
    try:
        with socket.create_connection((host, port), timeout=timeout):
            pass
    except OSError as err:
        return (
            f"no replay saved: the TMRL_SaveGhost plugin does not answer at {host}:{port} "
            f"({err.strerror or err}); `python -m tmrl --install --env tm20lidar` installs it, then reload "
            "the plugins in the game (F3 > Developer > Reload plugin)"
        )
    return None
