"""Duration measurements of a real-time environment (``benchmark`` in the config).

Every hook receives the timestamp from the environment's clock, so benchmarks under a
:class:`~tmrl.realtime.clock.FakeClock` are exact. Two kinds, as in rtgym:

* ``"polyak"`` (:class:`PolyakBenchmark`): for each duration, a running average and a running
  average absolute deviation, updated with factor ``benchmark_polyak``.
* ``"trace"`` (:class:`TraceBenchmark`): every timestamp, returned as numpy arrays with the
  durations computed from them.

The durations: ``time_step_duration`` (between two consecutive ``send_control`` calls),
``step_duration`` (inside ``step()``), ``join_duration`` (the part of ``step()`` spent waiting for
the running time step to end), ``inference_duration`` (between a ``step()`` return and the next
call), ``send_control_duration`` and ``get_obs_duration`` (the interface's methods).

The environment does not call a benchmark directly: it tells a :class:`StepObserver` what happens
at named points of ``reset()``, ``step()`` and the time-step thread. :class:`NullObserver` (no
``benchmark`` in the config) ignores everything; :class:`BenchmarkObserver` feeds a benchmark.
"""

from __future__ import annotations

import threading
from typing import Any, Protocol

import numpy as np

__all__ = [
    "DURATION_KEYS",
    "BenchmarkObserver",
    "NullObserver",
    "PolyakBenchmark",
    "StepObserver",
    "TraceBenchmark",
    "make_benchmark",
]

DURATION_KEYS = (
    "time_step_duration",
    "step_duration",
    "join_duration",
    "inference_duration",
    "send_control_duration",
    "get_obs_duration",
)


class PolyakBenchmark:
    """Running averages and average absolute deviations of the durations.

    Args:
        polyak: weight of a new measurement, in ``(0, 1]``; smaller is smoother.
    """

    def __init__(self, polyak: float = 0.1) -> None:
        self.polyak = float(polyak)
        self._lock = threading.Lock()
        self._avg: dict[str, float | None] = {k: None for k in DURATION_KEYS}
        self._dev: dict[str, float] = {k: 0.0 for k in DURATION_KEYS}
        self._t: dict[str, float | None] = {}

    def _add(self, key: str, value: float) -> None:
        old = self._avg[key]
        if old is None:
            self._avg[key] = value
            return
        delta = value - old
        self._avg[key] = old + self.polyak * delta
        self._dev[key] += self.polyak * (abs(delta) - self._dev[key])

    def _mark(self, name: str, t: float, since: str | None = None, key: str | None = None) -> None:
        with self._lock:
            if since is not None and key is not None:
                start = self._t.get(since)
                if start is not None:
                    self._add(key, t - start)
            self._t[name] = t

    # caller thread -------------------------------------------------------------------------
    def start_step(self, t: float) -> None:
        """``step()`` called at time ``t`` (ends the inference duration since the last step)."""
        self._mark("start_step", t, since="end_step", key="inference_duration")

    def end_step_join(self, t: float) -> None:
        """``step()`` finished waiting for the running time step at time ``t``."""
        self._mark("end_step_join", t, since="start_step", key="join_duration")

    def end_step(self, t: float) -> None:
        """``step()`` returns at time ``t`` (ends the step duration)."""
        self._mark("end_step", t, since="start_step", key="step_duration")

    def start_reset(self, t: float) -> None:
        """``reset()`` called at time ``t`` (not timed here)."""
        pass

    def end_reset_join(self, t: float) -> None:
        """``reset()`` finished waiting for the running time step at time ``t`` (not timed here)."""
        pass

    def end_reset(self, t: float) -> None:
        """``reset()`` returns at time ``t`` (not timed here)."""
        pass

    # time-step thread ----------------------------------------------------------------------
    def start_send_control(self, t: float) -> None:
        """The time-step thread starts sending a control at time ``t`` (one time step since the last)."""
        self._mark("start_send_control", t, since="start_send_control", key="time_step_duration")

    def end_send_control(self, t: float) -> None:
        """The control was sent at time ``t``."""
        self._mark("end_send_control", t, since="start_send_control", key="send_control_duration")

    def start_get_obs(self, t: float) -> None:
        """The time-step thread starts capturing an observation at time ``t``."""
        self._mark("start_get_obs", t)

    def end_get_obs(self, t: float) -> None:
        """The observation was captured at time ``t``."""
        self._mark("end_get_obs", t, since="start_get_obs", key="get_obs_duration")

    def result(self) -> dict[str, Any]:
        """``{duration_name: (average, average_deviation)}``; ``(None, 0.0)`` before any measurement."""
        with self._lock:
            return {k: (self._avg[k], self._dev[k]) for k in DURATION_KEYS}


class TraceBenchmark(PolyakBenchmark):
    """Every timestamp; reset() counts as a step, as in rtgym.

    Args:
        polyak: weight of a new measurement in the running averages (as :class:`PolyakBenchmark`).
    """

    _NAMES = (
        "start_step",
        "end_step_join",
        "end_step",
        "start_get_obs",
        "end_get_obs",
        "start_send_control",
        "end_send_control",
    )

    def __init__(self, polyak: float = 0.1) -> None:
        super().__init__(polyak)
        self._trace: dict[str, list[float]] = {k: [] for k in self._NAMES}

    def _mark(self, name: str, t: float, since: str | None = None, key: str | None = None) -> None:
        with self._lock:
            self._trace[name].append(t)

    def start_reset(self, t: float) -> None:
        """``reset()`` called at time ``t``: recorded as a step start, as rtgym does."""
        self.start_step(t)

    def end_reset_join(self, t: float) -> None:
        """``reset()`` finished waiting at time ``t``: recorded as a step's join."""
        self.end_step_join(t)

    def end_reset(self, t: float) -> None:
        """``reset()`` returns at time ``t``: recorded as a step end."""
        self.end_step(t)

    def result(self) -> dict[str, Any]:
        """``{"clock": {timestamp_name: array}, "deltas": {duration_name: array}}`` (``deltas``
        only once every timestamp has been recorded at least twice)."""
        with self._lock:
            tr = {k: np.asarray(v, dtype=np.float64) for k, v in self._trace.items()}
        out: dict[str, Any] = {"clock": tr}
        if min(len(v) for v in tr.values()) > 1:

            def diff(end: str, start: str) -> np.ndarray:
                n = min(len(tr[end]), len(tr[start]))
                return tr[end][:n] - tr[start][:n]

            starts, ends = tr["start_step"], tr["end_step"]
            n_inf = min(len(starts) - 1, len(ends))
            out["deltas"] = {
                "time_step_duration": np.diff(tr["start_send_control"]),
                "step_duration": diff("end_step", "start_step"),
                "join_duration": diff("end_step_join", "start_step"),
                "inference_duration": starts[1 : n_inf + 1] - ends[:n_inf],
                "send_control_duration": diff("end_send_control", "start_send_control"),
                "get_obs_duration": diff("end_get_obs", "start_get_obs"),
            }
        return out


def make_benchmark(kind: str, polyak: float) -> PolyakBenchmark:
    """The benchmark for config value ``benchmark_type`` (``"polyak"`` or ``"trace"``).

    Raises:
        tmrl.errors.UserError: another value.
    """
    from tmrl.errors import UserError

    kind = str(kind).lower()
    if kind == "polyak":
        return PolyakBenchmark(polyak)
    if kind == "trace":
        return TraceBenchmark(polyak)
    raise UserError(f'benchmark_type is {kind!r}: set it to "polyak" or "trace" in the real-time config')


class StepObserver(Protocol):
    """What the environment tells at named points of a time step, with its clock's time ``t``.

    ``on_reset_*`` and ``on_step_*`` are called on the caller's thread; ``on_send_control_*`` and
    ``on_obs_*`` on the time-step thread, possibly at the same time.
    """

    def on_reset_start(self, t: float) -> None:
        """``reset()`` was called."""

    def on_reset_joined(self, t: float) -> None:
        """``reset()`` finished waiting for the running time step."""

    def on_reset_end(self, t: float) -> None:
        """``reset()`` is about to return."""

    def on_step_start(self, t: float) -> None:
        """``step()`` was called."""

    def on_step_joined(self, t: float) -> None:
        """``step()`` received the observation of the time step that ended."""

    def on_step_end(self, t: float) -> None:
        """``step()`` is about to return."""

    def on_send_control_start(self, t: float) -> None:
        """A time step starts: ``send_control`` is about to be called."""

    def on_send_control_end(self, t: float) -> None:
        """``send_control`` returned."""

    def on_obs_capture_start(self, t: float) -> None:
        """``get_obs_rew_terminated_info`` is about to be called."""

    def on_obs_captured(self, t: float) -> None:
        """The observation is captured (and preprocessed)."""


class NullObserver:
    """The observer of an environment without ``benchmark``: ignores everything."""

    def on_reset_start(self, t: float) -> None:
        pass

    def on_reset_joined(self, t: float) -> None:
        pass

    def on_reset_end(self, t: float) -> None:
        pass

    def on_step_start(self, t: float) -> None:
        pass

    def on_step_joined(self, t: float) -> None:
        pass

    def on_step_end(self, t: float) -> None:
        pass

    def on_send_control_start(self, t: float) -> None:
        pass

    def on_send_control_end(self, t: float) -> None:
        pass

    def on_obs_capture_start(self, t: float) -> None:
        pass

    def on_obs_captured(self, t: float) -> None:
        pass


class BenchmarkObserver:
    """Feeds every event to a benchmark (``"benchmark": True`` in the config).

    Args:
        benchmark: a :class:`PolyakBenchmark` or :class:`TraceBenchmark` (see
            :func:`make_benchmark`).
    """

    def __init__(self, benchmark: PolyakBenchmark) -> None:
        self.benchmark = benchmark

    def on_reset_start(self, t: float) -> None:
        self.benchmark.start_reset(t)

    def on_reset_joined(self, t: float) -> None:
        self.benchmark.end_reset_join(t)

    def on_reset_end(self, t: float) -> None:
        self.benchmark.end_reset(t)

    def on_step_start(self, t: float) -> None:
        self.benchmark.start_step(t)

    def on_step_joined(self, t: float) -> None:
        self.benchmark.end_step_join(t)

    def on_step_end(self, t: float) -> None:
        self.benchmark.end_step(t)

    def on_send_control_start(self, t: float) -> None:
        self.benchmark.start_send_control(t)

    def on_send_control_end(self, t: float) -> None:
        self.benchmark.end_send_control(t)

    def on_obs_capture_start(self, t: float) -> None:
        self.benchmark.start_get_obs(t)

    def on_obs_captured(self, t: float) -> None:
        self.benchmark.end_get_obs(t)

    def result(self) -> dict[str, Any]:
        """The benchmark's :meth:`~PolyakBenchmark.result`."""
        return self.benchmark.result()
