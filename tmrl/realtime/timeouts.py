"""A console a person can read under load: :class:`~tmrl.realtime.env.TimeStepTimeoutWarning`\\ s
summarised, one line per interval with their count and the worst overrun, instead of two lines per
time step that ran late (the message and the source line Python echoes under it).

Within :func:`summarised_timeouts` every timeout warning is counted (none is printed) and at most
one line per ``interval`` seconds goes to the ``tmrl.realtime`` logger::

    12:00:10 WARNING tmrl.realtime: 37 time steps ran late in the last 10 s (worst 41.2 ms after
    the end of its time step, 20.0 ms allowed): the clock restarted each time; make inference
    faster, give the trainer fewer threads or raise time_step_timeout_factor

Other warnings are shown as before. The environment itself still issues one warning per timeout,
as rtgym does: code that counts them (``warnings.catch_warnings``) sees every one.
"""

from __future__ import annotations

import logging
import threading
import time
import warnings
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import Any

from tmrl.realtime.env import TimeStepTimeoutWarning

__all__ = ["DEFAULT_INTERVAL", "TimeoutSummary", "summarised_timeouts"]

logger = logging.getLogger("tmrl.realtime")

#: Seconds between two summary lines, at most one line per interval.
DEFAULT_INTERVAL = 10.0


class TimeoutSummary:
    """Counts time steps that ran late and writes at most one line per ``interval`` seconds.

    The first timeout of a quiet period is reported at once; the ones that follow within
    ``interval`` are reported together when the interval is over (by a timer, so a burst that
    stops is reported too) or by :meth:`flush`.

    Args:
        interval: seconds between two lines.
        log: where a line goes (default: a WARNING of the ``tmrl.realtime`` logger).
        clock: the time in seconds (tests pass a fake one).
    """

    def __init__(self, interval: float = DEFAULT_INTERVAL, log: Callable[[str], None] | None = None,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self.interval = float(interval)
        self._log = log or logger.warning
        self._clock = clock
        self._lock = threading.Lock()
        self._count = 0
        self._worst = 0.0
        self._allowed: float | None = None
        self._last_line = -float("inf")
        self._since = clock()
        self._timer: threading.Timer | None = None
        self.total = 0
        """Timeouts counted since this summary was made."""
        self.lines = 0
        """Lines written."""

    def add(self, late: float | None, allowed: float | None) -> None:
        """Count one time step that ran ``late`` seconds after its end (``allowed``: the limit)."""
        with self._lock:
            now = self._clock()
            if self._count == 0 and now - self._last_line >= self.interval:
                self._since = now
            self._count += 1
            self.total += 1
            if late is not None and late > self._worst:
                self._worst = late
            if allowed is not None:
                self._allowed = allowed
            due = self._last_line + self.interval
            if now >= due:
                line = self._take(now)
            else:
                line = None
                if self._timer is None:
                    self._timer = threading.Timer(due - now, self._on_timer)
                    self._timer.daemon = True
                    self._timer.start()
        if line is not None:
            self._log(line)

    def _on_timer(self) -> None:
        with self._lock:
            self._timer = None
            now = self._clock()
            if self._count == 0 or now < self._last_line + self.interval:
                return  # a line went out meanwhile
            line = self._take(now)
        self._log(line)

    def _take(self, now: float) -> str:
        """The line for what was counted since the last one (the lock is held)."""
        count, worst, allowed = self._count, self._worst, self._allowed
        span = max(now - self._since, 0.0)
        self._count, self._worst, self._since, self._last_line = 0, 0.0, now, now
        self.lines += 1
        steps = "1 time step ran late" if count == 1 else f"{count} time steps ran late"
        when = "just now" if span < 1.0 else f"in the last {span:.0f} s"
        limit = f", {1000 * allowed:.1f} ms allowed" if allowed is not None else ""
        return (f"{steps} {when} (worst {1000 * worst:.1f} ms after the end of its time step{limit}): the clock "
                f"restarted {'each time' if count > 1 else 'from then'}; make inference faster, give the trainer "
                "fewer threads or raise time_step_timeout_factor")

    def flush(self) -> None:
        """Write the line of what was counted and not yet reported, if anything."""
        with self._lock:
            if self._timer is not None:
                self._timer.cancel()
                self._timer = None
            line = self._take(self._clock()) if self._count else None
        if line is not None:
            self._log(line)


@contextmanager
def summarised_timeouts(interval: float = DEFAULT_INTERVAL,
                        log: Callable[[str], None] | None = None) -> Iterator[TimeoutSummary]:
    """Within the block, :class:`~tmrl.realtime.env.TimeStepTimeoutWarning`\\ s are counted by a
    :class:`TimeoutSummary` (at most one line per ``interval`` seconds) instead of being printed;
    what is left is written when the block ends, however it ends. Other warnings are shown as
    before. Process-wide while it lasts (Python's warnings are), from any thread.

    Args:
        interval: seconds between two lines.
        log: where a line goes (default: a WARNING of the ``tmrl.realtime`` logger).
    """
    summary = TimeoutSummary(interval, log)
    previous = warnings.showwarning

    def show(message: Any, category: type[Warning], filename: str, lineno: int, file: Any = None,
             line: str | None = None) -> None:
        if isinstance(category, type) and issubclass(category, TimeStepTimeoutWarning):
            summary.add(getattr(message, "late", None), getattr(message, "allowed", None))
        else:
            previous(message, category, filename, lineno, file, line)

    warnings.filterwarnings("always", category=TimeStepTimeoutWarning)
    entry = warnings.filters[0]
    warnings.showwarning = show
    try:
        yield summary
    finally:
        if warnings.showwarning is show:
            warnings.showwarning = previous
        try:  # ours only: filters added meanwhile stay ("always" leaves nothing in the registries)
            warnings.filters.remove(entry)
        except ValueError:
            pass
        summary.flush()
