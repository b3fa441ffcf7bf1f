"""Clocks for the real-time environment: the real one and a fake one for tests.

The environment never calls ``time`` directly. It asks its clock for ``now()``, waits with
``sleep_until(t)`` and passes messages between its threads through ``clock.channel()``. Two
implementations:

* :class:`PerfCounterClock` (the default): ``time.perf_counter``, with a sleep that wakes up a
  little early and yields until the deadline, so that time steps end within microseconds of
  their nominal time instead of the operating system's sleep overshoot.
* :class:`FakeClock`: virtual time, for deterministic tests. Each thread has its own virtual
  time; sleeping advances it without waiting, and a message carries its sender's time to its
  receiver (the receiver's time becomes the later of the two). The result is the timing an
  infinitely fast machine would show, whatever the real scheduling of the threads, so tests can
  assert exact timestamps.
"""

from __future__ import annotations

import queue
import threading
import time
from typing import Any, Generic, Protocol, TypeVar

__all__ = ["Channel", "Clock", "FakeClock", "PerfCounterClock", "receive"]

WAKE_EVERY = 0.2
"""Longest single wait of :func:`receive`, in seconds: how late Ctrl-C may be on Windows."""

T = TypeVar("T")


class Channel(Protocol[T]):
    """A FIFO from one thread to another."""

    def put(self, item: T) -> None:
        """Send ``item``; never blocks."""

    def get(self, timeout: float | None = None) -> T:
        """Receive the oldest item, blocking until one arrives.

        Raises:
            queue.Empty: ``timeout`` seconds (real time) passed first.
        """


def receive(channel: Channel[T]) -> T:
    """The oldest item of ``channel``, however long it takes to come.

    It waits in slices of :data:`WAKE_EVERY` seconds: on Windows, CPython 3.10 to 3.12 deliver
    Ctrl-C to a thread blocked on a lock only once the wait ends, so one wait without a timeout
    (a time step can wait 60 s for OpenPlanet's first frame) would hold Ctrl-C back as long.
    Between two slices the ``KeyboardInterrupt`` is raised at once.
    """
    while True:
        try:
            return channel.get(timeout=WAKE_EVERY)
        except queue.Empty:
            continue


class Clock(Protocol):
    """What the environment needs from a clock."""

    def now(self) -> float:
        """Current time in seconds (monotonic)."""

    def sleep(self, seconds: float) -> None:
        """Wait ``seconds`` (nothing when not positive)."""

    def sleep_until(self, deadline: float) -> None:
        """Wait until ``now() >= deadline`` (returns at once when already past)."""

    def channel(self) -> Channel[Any]:
        """A new channel between two threads using this clock."""


class _QueueChannel(Generic[T]):
    # Blocks in the operating system: polling near the expected arrival was measured to make
    # timing worse on a loaded machine (the polling thread uses up its share of the CPU).
    def __init__(self) -> None:
        self._q: queue.SimpleQueue[T] = queue.SimpleQueue()

    def put(self, item: T) -> None:
        self._q.put(item)

    def get(self, timeout: float | None = None) -> T:
        return self._q.get(timeout=timeout)


class PerfCounterClock:
    """Real time from ``time.perf_counter``.

    Args:
        spin: seconds before a deadline at which :meth:`sleep_until` stops sleeping in the
            operating system and yields in a loop instead (``time.sleep(0)`` releases the GIL, so
            other Python threads keep running). Larger is more precise under load and costs more
            CPU; 0 gives plain ``time.sleep``.
    """

    def __init__(self, spin: float = 0.0015) -> None:
        self.spin = float(spin)

    def now(self) -> float:
        return time.perf_counter()

    def sleep(self, seconds: float) -> None:
        if seconds > 0:
            self.sleep_until(time.perf_counter() + seconds)

    def sleep_until(self, deadline: float) -> None:
        spin = self.spin
        while True:
            remaining = deadline - time.perf_counter()
            if remaining <= 0:
                return
            if remaining > spin:
                time.sleep(remaining - spin)
            else:
                time.sleep(0)

    def channel(self) -> Channel[Any]:
        return _QueueChannel()


class _FakeChannel(Generic[T]):
    def __init__(self, clock: FakeClock) -> None:
        self._clock = clock
        self._q: queue.SimpleQueue[tuple[float, T]] = queue.SimpleQueue()

    def put(self, item: T) -> None:
        self._q.put((self._clock.now(), item))

    def get(self, timeout: float | None = None) -> T:
        sent_at, item = self._q.get(timeout=timeout)
        self._clock.sleep_until(sent_at)
        return item


class FakeClock:
    """Virtual time for tests: sleeping is instantaneous and advances the calling thread's time.

    A thread's time starts at ``start`` (or at the time given to :meth:`set_thread_time`), moves
    forward with :meth:`sleep`/:meth:`sleep_until`, and jumps forward when the thread receives a
    message sent at a later time through a :meth:`channel`. Real blocking (waiting for a message)
    still happens, so threads interact as in production; only durations are virtual.

    Args:
        start: the virtual time of a thread that has not slept yet.
    """

    def __init__(self, start: float = 0.0) -> None:
        self.start = float(start)
        self._local = threading.local()

    def now(self) -> float:
        return getattr(self._local, "t", self.start)

    def set_thread_time(self, t: float) -> None:
        """Move the calling thread's time to ``t`` (forward only)."""
        self.sleep_until(t)

    def sleep(self, seconds: float) -> None:
        if seconds > 0:
            self._local.t = self.now() + seconds

    def sleep_until(self, deadline: float) -> None:
        if deadline > self.now():
            self._local.t = float(deadline)

    def channel(self) -> Channel[Any]:
        return _FakeChannel(self)
