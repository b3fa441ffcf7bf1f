"""The real-time Gymnasium environment: elastic time steps around a :class:`RealTimeGymInterface`.

Timeline of one time step (``T = time_step_duration``, ``c = start_obs_capture``)::

    t_start            t_start + c              t_start + T = next t_start
      | send_control(a)   | get_obs_rew_terminated_info()   | send_control(a')
      |<-- step() returns here; the policy computes a' while the time step runs -->|

``step(a')`` waits for the running time step to end, starts the next one with ``a'`` and returns
the observation captured during the step that just ended. The policy's inference therefore
overlaps the time step, and the action buffer in the observation (``act_buf_len`` last actions,
oldest first) keeps the delayed problem Markov.

The clock is elastic: when ``step()`` comes late but within ``time_step_duration *
time_step_timeout_factor`` after the end of the time step, the next time step still starts at the
nominal time (in the past), so the cadence is kept; later than that, the clock restarts from now
with one :class:`TimeStepTimeoutWarning` (none right after ``wait()``).

Two variants with the semantics of rtgym 0.16:

* :class:`RealTimeEnv` (``real-time-gym-v1``): the interface is built on the caller's thread, and
  ``reset``, ``wait``, ``render`` and ``close`` run there; ``send_control`` and the observation
  capture run on one persistent time-step thread.
* :class:`RealTimeEnvTS` (``real-time-gym-ts-v1``): one persistent thread builds the interface and
  makes every call to it except ``render`` (for interfaces with thread affinity).

The environment sends its time-step thread (a :class:`~tmrl.realtime.runner.TimeStepRunner`, in
:mod:`tmrl.realtime.runner`) typed jobs (:class:`StartTimeStep`, :class:`ChainTimeStep`,
:class:`CallInterface`, :class:`StopThread`) and gets typed results back (:class:`Observed`,
:class:`Returned`, :class:`Raised`). Both threads tell the environment's
:class:`~tmrl.realtime.benchmark.StepObserver` what happens, for the benchmarks.
"""

from __future__ import annotations

import logging
import math
import numbers
import threading
import warnings
from collections import deque
from collections.abc import Callable, Mapping
from typing import Any

import gymnasium
import numpy as np
from gymnasium import spaces

from tmrl.errors import UserError
from tmrl.realtime.benchmark import (
    BenchmarkObserver,
    NullObserver,
    PolyakBenchmark,
    StepObserver,
    make_benchmark,
)
from tmrl.realtime.clock import Clock, PerfCounterClock, receive
from tmrl.realtime.interface import CONFIG_KEYS, DEFAULT_CONFIG_DICT, RealTimeGymInterface
from tmrl.realtime.runner import (  # re-exported: their home was this module
    CallInterface,
    ChainTimeStep,
    Job,
    Observed,
    Raised,
    Result,
    Returned,
    StartTimeStep,
    StopThread,
    TimeStepRunner,
    _next_start,
)

__all__ = [
    "BenchmarkDisabledError",
    "CallInterface",
    "ChainTimeStep",
    "Job",
    "Observed",
    "Raised",
    "RealTimeEnv",
    "RealTimeEnvTS",
    "Result",
    "Returned",
    "StartTimeStep",
    "StepAfterDoneError",
    "StopThread",
    "TimeStepRunner",
    "TimeStepTimeoutWarning",
    "read_config",
]

logger = logging.getLogger(__name__)

# How long close() waits for the time-step thread to stop before giving up (seconds of real time).
_CLOSE_JOIN_TIMEOUT = 10.0


class TimeStepTimeoutWarning(UserWarning):
    """``step()`` came too late: the elastic clock restarted from now.

    Args:
        message: what happened, in one line (the warning's text).
        late: seconds after the end of the time step when ``step()`` or ``reset()`` came.
        allowed: the seconds allowed (``time_step_duration * time_step_timeout_factor``).

    :func:`tmrl.realtime.timeouts.summarised_timeouts` turns them into one line per interval.
    """

    def __init__(self, message: str, late: float | None = None, allowed: float | None = None) -> None:
        super().__init__(message)
        self.late = late
        self.allowed = allowed


class StepAfterDoneError(UserError, RuntimeError):
    """``step()`` was called after the episode ended (a ``RuntimeError``, as in rtgym)."""


class BenchmarkDisabledError(UserError, AssertionError):
    """``benchmarks()`` was called without ``"benchmark": True`` (an ``AssertionError``, as in rtgym)."""


def _number(cfg: Mapping[str, Any], key: str, low: float, allow_low: bool = True) -> float:
    """``cfg[key]`` as a float ``>= low`` (``> low`` unless ``allow_low``).

    Raises:
        UserError: not a number, NaN or out of range.
    """
    try:
        value = float(cfg[key])
    except (TypeError, ValueError):
        raise UserError(f"real-time config: {key} is {cfg[key]!r}; set it to a number") from None
    if math.isnan(value) or value < low or (value == low and not allow_low):
        bound = f">= {low}" if allow_low else f"> {low}"
        raise UserError(f"real-time config: {key} is {cfg[key]!r}; set it to a number {bound}")
    return value


def read_config(config: Mapping[str, Any]) -> dict[str, Any]:
    """Complete ``config`` with the defaults and check the values a user can get wrong.

    Unknown keys are logged and kept. The same rules as :class:`RealTimeEnv` (which calls this).

    Args:
        config: a real-time config (see :data:`~tmrl.realtime.DEFAULT_CONFIG_DICT`); not mutated.

    Returns:
        A new dict with every key of :data:`~tmrl.realtime.DEFAULT_CONFIG_DICT`.

    Raises:
        UserError: a missing interface or an out-of-range value (one line).
    """
    if not isinstance(config, Mapping):
        raise UserError(
            f"the real-time config is a {type(config).__name__}: pass a dict, e.g. "
            "dict(tmrl.realtime.DEFAULT_CONFIG_DICT, interface=MyInterface)"
        )
    unknown = sorted(set(config) - CONFIG_KEYS)
    if unknown:
        logger.warning("real-time config: ignoring unknown keys %s", unknown)
    cfg = {**DEFAULT_CONFIG_DICT, **config}
    if not callable(cfg["interface"]) or cfg["interface"] is RealTimeGymInterface:
        raise UserError(
            'the real-time config has no interface: set config["interface"] to your interface class '
            "(e.g. dict(tmrl.realtime.DEFAULT_CONFIG_DICT, interface=MyInterface))"
        )
    _number(cfg, "time_step_duration", 0.0)
    _number(cfg, "start_obs_capture", 0.0)
    _number(cfg, "time_step_timeout_factor", 0.0)
    _number(cfg, "ep_max_length", 0.0, allow_low=False)
    _number(cfg, "benchmark_polyak", 0.0, allow_low=False)
    if (
        not isinstance(cfg["act_buf_len"], numbers.Integral)
        or isinstance(cfg["act_buf_len"], bool)
        or cfg["act_buf_len"] < 1
    ):
        raise UserError(
            f"real-time config: act_buf_len is {cfg['act_buf_len']!r}; set it to an integer >= 1 "
            "(set act_in_obs to False to leave actions out of observations)"
        )
    if not isinstance(cfg["interface_kwargs"], Mapping):
        raise UserError("real-time config: interface_kwargs must be a dict of keyword arguments")
    return cfg


class RealTimeEnv(gymnasium.Env):
    """A Gymnasium environment stepping a :class:`~tmrl.realtime.RealTimeGymInterface` in real time.

    Usually built by ``gymnasium.make("real-time-gym-v1", config=config)``.

    Args:
        config: a copy of :data:`~tmrl.realtime.DEFAULT_CONFIG_DICT` with your ``interface``;
            missing keys take their default. Never mutated.
        clock: where time comes from (tmrl addition); defaults to
            :class:`~tmrl.realtime.clock.PerfCounterClock`. Tests pass a
            :class:`~tmrl.realtime.clock.FakeClock`.

    Attributes:
        default_action: the action applied at reset and used to fill the action buffer.
        act_buf: the last ``act_buf_len`` actions, oldest first.
        current_step: steps since the last reset.
        observer: told of every time step's events (a
            :class:`~tmrl.realtime.benchmark.BenchmarkObserver` with ``"benchmark": True``, else a
            :class:`~tmrl.realtime.benchmark.NullObserver`); subclasses may override
            ``_make_observer()``.

    Raises:
        UserError: the config is invalid.
        Exception: whatever the interface's constructor or space getters raise.
    """

    metadata = {"render_modes": ["human"]}  # noqa: RUF012  (declared by gymnasium.Env)
    _INTERFACE_ON_WORKER = False
    """Whether every interface call (except render) runs on the time-step thread."""

    def __init__(self, config: Mapping[str, Any] | None = None, clock: Clock | None = None) -> None:
        cfg = read_config(DEFAULT_CONFIG_DICT if config is None else config)
        self._clock: Clock = PerfCounterClock() if clock is None else clock
        self._apply_config(cfg)
        self.is_waiting = False
        self.current_step = 0
        self.time_initialized = False
        self.running = False
        self.seed: int | None = None
        self.options: dict[str, Any] | None = None
        self.render_mode = "human"
        # Timestamps of the current time step (owned by the caller's thread).
        self._t_start = 0.0
        self._t_co = 0.0
        self._t_end = 0.0
        # A time step is running on the worker and its result has not been collected.
        self._in_flight = False
        self._result: Result | None = None
        self._closed = False
        self._interface: Any = None
        self.observer: StepObserver = self._make_observer()
        self._start_worker()
        self.init_action_buffer()

    def _apply_config(self, cfg: dict[str, Any]) -> None:
        """Set the attributes that a config (completed by :func:`read_config`) decides."""
        self.config = cfg
        self.interface_cls = cfg["interface"]
        self.interface_args = tuple(cfg["interface_args"])
        self.interface_kwargs = dict(cfg["interface_kwargs"])
        self.wait_on_done = bool(cfg["wait_on_done"])
        self.last_act_on_reset = bool(cfg["last_act_on_reset"])
        self.act_prepro_func: Callable[[Any], Any] | None = cfg.get("act_prepro_func")
        self.obs_prepro_func: Callable[[Any], Any] | None = cfg.get("obs_prepro_func")
        self.ep_max_length = cfg["ep_max_length"]
        self.time_step_duration = float(cfg["time_step_duration"])
        self.time_step_timeout_factor = float(cfg["time_step_timeout_factor"])
        self.start_obs_capture = float(cfg["start_obs_capture"])
        self.time_step_timeout = self.time_step_duration * self.time_step_timeout_factor
        self.act_in_obs = bool(cfg["act_in_obs"])
        self.act_buf_len = int(cfg["act_buf_len"])
        self.reset_act_buf = bool(cfg["reset_act_buf"])
        self.act_buf: deque[Any] = deque(maxlen=self.act_buf_len)
        self.benchmark = bool(cfg["benchmark"])
        self.benchmark_polyak = float(cfg["benchmark_polyak"])
        # built even when benchmarks are off, so that a wrong benchmark_type is reported at once
        self.bench: PolyakBenchmark = make_benchmark(cfg["benchmark_type"], self.benchmark_polyak)

    def _make_observer(self) -> StepObserver:
        """The observer of time steps: a :class:`~tmrl.realtime.benchmark.BenchmarkObserver`
        feeding ``self.bench`` when the config sets ``benchmark``, else a no-op."""
        return BenchmarkObserver(self.bench) if self.benchmark else NullObserver()

    def _start_worker(self) -> None:
        """Start the time-step thread and build the interface (on that thread for the TS variant)."""
        self._runner = TimeStepRunner(self._clock, self.observer, self.act_prepro_func, self.obs_prepro_func)
        self._jobs = self._runner.jobs
        self._results = self._runner.results
        self._thread = threading.Thread(
            target=self._runner.loop,
            args=(self._clock.now(),),
            name=f"tmrl-{type(self).__name__}",
            daemon=True,
        )
        if self._INTERFACE_ON_WORKER:
            self._thread.start()
            try:
                self._call_interface(self._build_interface)
            except BaseException:
                self._stop_worker()
                raise
        else:
            self._build_interface(None)
            self._thread.start()

    # interface and worker thread ---------------------------------------------------------------
    def _build_interface(self, _: Any) -> None:
        """Build the interface and read its spaces (on the thread that will own it)."""
        interface = self.interface_cls(*self.interface_args, **self.interface_kwargs)
        self._interface = interface
        self._runner.interface = interface
        self.default_action = interface.get_default_action()
        self.interface_action_space = interface.get_action_space()
        self.interface_observation_space = interface.get_observation_space()
        self.action_space = self.interface_action_space
        self.observation_space = self._get_observation_space()

    def _get_observation_space(self) -> spaces.Space:
        t = self.interface_observation_space
        if not self.act_in_obs:
            return t
        if not isinstance(t, spaces.Tuple):
            raise UserError(
                f"{self.interface_cls.__name__}.get_observation_space() returned a {type(t).__name__}: "
                "return a gymnasium.spaces.Tuple (the action buffer is appended to it)"
            )
        return spaces.Tuple((*t.spaces, *((self.interface_action_space,) * self.act_buf_len)))

    @property
    def interface(self) -> Any:
        """The interface object (with ``real-time-gym-ts-v1``, call it from the time-step thread only)."""
        return self._interface

    def _call_interface(self, fn: Callable[[Any], Any]) -> Any:
        """Run ``fn(interface)`` on the thread that owns the interface; no time step may be running."""
        if not self._INTERFACE_ON_WORKER:
            return fn(self._interface)
        self._jobs.put(CallInterface(fn))
        result = receive(self._results)
        if isinstance(result, Raised):
            raise result.error
        return result.value

    def _stop_worker(self) -> None:
        if self._thread.is_alive():
            self._jobs.put(StopThread())
            self._thread.join(_CLOSE_JOIN_TIMEOUT)
            if self._thread.is_alive():
                logger.warning("the real-time thread did not stop within %.0f s", _CLOSE_JOIN_TIMEOUT)

    # elastic clock -------------------------------------------------------------------------
    def _initialize_time(self) -> None:
        """At the first reset: pretend a time step just ended now."""
        now = self._clock.now()
        self._t_start = now - self.time_step_duration
        self._t_co = self._t_start + self.start_obs_capture
        self._t_end = now
        self.time_initialized = True

    def _set_timestamps(self, decision_time: float) -> None:
        """Place the next time step, as decided at ``decision_time`` (see :func:`_next_start`),
        warning when the clock restarts (unless the environment was waiting)."""
        self._t_start, timed_out = _next_start(decision_time, self._t_end, self.time_step_timeout)
        if timed_out:
            if not self.is_waiting:
                late = decision_time - self._t_end
                warnings.warn(
                    TimeStepTimeoutWarning(
                        f"time step timed out: step() or reset() came {1000 * late:.1f} ms after the end of the "
                        f"time step (allowed: {1000 * self.time_step_timeout:.1f} ms); the clock restarts from now "
                        "(make inference faster or raise time_step_timeout_factor)",
                        late=late,
                        allowed=self.time_step_timeout,
                    ),
                    stacklevel=4,
                )
            else:
                self.is_waiting = False
        self._t_co = self._t_start + self.start_obs_capture
        self._t_end = self._t_start + self.time_step_duration

    def _start_time_step(self, action: Any, decision_time: float, chained: bool = False) -> None:
        """Place the next time step (see :meth:`_set_timestamps`) and mark it running; unless
        ``chained`` (the time-step thread was already handed a :class:`ChainTimeStep` and decides
        the same start), hand it a :class:`StartTimeStep`. Called by ``reset()`` and ``step()``
        only (the timeout warning points at their caller)."""
        self._set_timestamps(decision_time)
        self._in_flight = True
        if not chained:
            self._jobs.put(StartTimeStep(action, self._t_start, self._t_co, self._t_end))

    def _join_thread(self) -> None:
        """Wait until the running time step (if any) has captured its observation and ended."""
        if self._in_flight:
            self._result = receive(self._results)
            self._in_flight = False
            self._clock.sleep_until(self._t_end)

    # gymnasium API -------------------------------------------------------------------------
    def _buffer_copy(self) -> list[Any]:
        # Copies, so that consecutive observations share no array (the same action appears in
        # several buffers, and users keep observations).
        return [a.copy() if isinstance(a, np.ndarray) else a for a in self.act_buf]

    def init_action_buffer(self) -> None:
        """Fill the action buffer with the default action."""
        for _ in range(self.act_buf_len):
            self.act_buf.append(self.default_action)

    def reset(  # type: ignore[override]  # positional seed allowed, as in rtgym
        self, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[tuple[Any, ...], dict[str, Any]]:
        """Start an episode: reset the interface, then start the first time step with the default
        action (or, with ``reset_act_buf`` False and ``last_act_on_reset`` True, with the last action
        given to ``step()``). Waits for a running time step to end first.

        Args:
            seed: seeds the environment's random generator (Gymnasium's ``np_random``) and is passed
                to the interface's ``reset``.
            options: passed to the interface's ``reset``.

        Returns:
            ``(obs, info)``: the interface's observation followed by the action buffer.
        """
        clock, observer = self._clock, self.observer
        if self._closed:
            raise UserError("this real-time environment is closed: make a new one")
        observer.on_reset_start(clock.now())
        self._join_thread()
        self._result = None
        observer.on_reset_joined(clock.now())
        super().reset(seed=seed)
        self.running = True
        self.seed = seed
        self.options = options
        self.current_step = 0
        if self.reset_act_buf:
            self.init_action_buffer()
        elif not self.last_act_on_reset:
            # The last action of the previous episode was never applied: the default action is.
            self.act_buf[-1] = self.default_action
        obs, info = self._call_interface(lambda itf: itf.reset(seed=seed, options=options))
        if self.act_in_obs:
            obs = [*obs, *self._buffer_copy()]
        if self.obs_prepro_func:
            # rtgym applies obs_prepro_func after appending the buffer here, before it in step().
            obs = self.obs_prepro_func(obs)
        obs = tuple(obs)
        if not self.time_initialized:
            self._initialize_time()
        self._start_time_step(self.act_buf[-1], clock.now())
        observer.on_reset_end(clock.now())
        return obs, info

    def step(self, action: Any) -> tuple[tuple[Any, ...], Any, Any, bool, dict[str, Any]]:
        """Wait for the running time step to end, start the next one with ``action``, and return
        what was observed during the step that ended.

        Call it again before the new time step ends to keep the cadence.

        Returns:
            ``(obs, rew, terminated, truncated, info)``; ``truncated`` is True at
            ``ep_max_length`` steps unless ``terminated`` is. On either, no new time step starts
            (``wait()`` is called when ``wait_on_done``).

        Raises:
            StepAfterDoneError: the episode has ended (a ``RuntimeError``); call ``reset()``.
            Exception: whatever the interface raised during the time step.
        """
        clock, observer = self._clock, self.observer
        t_call = clock.now()
        observer.on_step_start(t_call)
        self.current_step += 1
        self.act_buf.append(action)  # as in rtgym, even when the episode has ended
        truncating = bool(self.current_step >= self.ep_max_length)
        chained = self._in_flight and self.running
        observed = self._collect_time_step(action, t_call, truncating, chained)
        truncated = truncating if not observed.terminated else False
        if not (observed.terminated or truncated):
            # when chained, the same decision as the time-step thread's (same inputs, same rule)
            decision_time = max(t_call, observed.capture_end, self._t_end) if chained else clock.now()
            self._start_time_step(action, decision_time, chained=chained)
            clock.sleep_until(self._t_start)
        else:
            self._end_episode()
        obs = observed.obs
        if self.act_in_obs:
            obs = (*obs, *self._buffer_copy())
        observer.on_step_end(clock.now())
        return obs, observed.rew, observed.terminated, truncated, observed.info

    def _collect_time_step(self, action: Any, t_call: float, truncating: bool, chained: bool) -> Observed:
        """``step()``'s wait for the running time step: when ``chained``, hand ``action`` over
        first (the time-step thread sends it as soon as the running time step ends, whatever the
        delay of this thread's wake-up); tell the observer once the result is in.

        Raises:
            StepAfterDoneError: no time step was running (the episode has ended).
            Exception: whatever the interface raised during the time step.
        """
        if chained:
            self._jobs.put(
                ChainTimeStep(
                    action,
                    t_call,
                    truncating,
                    self.time_step_duration,
                    self.start_obs_capture,
                    self.time_step_timeout,
                )
            )
            self._result = receive(self._results)
            self._in_flight = False
        else:
            self._join_thread()
        self.observer.on_step_joined(self._clock.now())
        result, self._result = self._result, None
        if not self.running or result is None:
            self.running = False
            raise StepAfterDoneError("the episode is terminated or truncated: call reset() before step()")
        if isinstance(result, Raised):
            self.running = False  # the episode cannot go on; reset() starts a new one
            raise result.error
        if not isinstance(result, Observed):
            raise TypeError(f"the time-step thread answered a time step with {result!r}")
        return result

    def _end_episode(self) -> None:
        """After the last step of an episode: let the time step end, then pause if ``wait_on_done``."""
        self._clock.sleep_until(self._t_end)
        self.running = False
        if self.wait_on_done:
            self.wait()

    def wait(self) -> None:
        """Pause: wait for the running time step to end, then call the interface's ``wait()``.
        The next time step restarts the clock without a warning."""
        self._join_thread()
        self.is_waiting = True
        # wait() and render() are optional for interfaces that do not subclass the base class
        self._call_interface(lambda itf: itf.wait() if callable(getattr(itf, "wait", None)) else None)

    def stop(self) -> None:
        """Wait for the running time step to end."""
        self._join_thread()

    def benchmarks(self) -> dict[str, Any]:
        """Measured durations (see :mod:`tmrl.realtime.benchmark`).

        Returns:
            with ``benchmark_type`` ``"polyak"``: ``{name: (average, average_deviation)}`` for
            ``time_step_duration``, ``step_duration``, ``join_duration``,
            ``inference_duration``, ``send_control_duration``, ``get_obs_duration`` (seconds).

        Raises:
            BenchmarkDisabledError: the config did not set ``"benchmark": True``.
        """
        if not self.benchmark:
            raise BenchmarkDisabledError('benchmarks are off: set "benchmark": True in the real-time config')
        return self.bench.result()

    def render(self, mode: str = "human", join_thread: bool = False) -> Any:
        """Return the interface's ``render()``, called on the caller's thread (as rtgym does for both
        variants).

        Args:
            mode: accepted for rtgym compatibility and ignored.
            join_thread: first wait for the running time step to end.
        """
        if join_thread:
            self._join_thread()
        render = getattr(self._interface, "render", None)
        return render() if callable(render) else None

    def set_default_action(self, default_action: Any) -> None:
        """Change the action applied at the next reset (and used to fill the action buffer).

        Args:
            default_action: an element of the action space.
        """
        self.default_action = default_action

    def set_time_step_duration(
        self, time_step_duration: float, time_step_timeout_factor: float | None = None
    ) -> None:
        """Change the time-step duration (and optionally the timeout factor) from the next time step on.

        Args:
            time_step_duration: the new nominal duration of a time step, in seconds.
            time_step_timeout_factor: the new timeout factor (``None``: unchanged).
        """
        self._join_thread()
        if time_step_timeout_factor is not None:
            self.time_step_timeout_factor = float(time_step_timeout_factor)
        self.time_step_duration = float(time_step_duration)
        self.time_step_timeout = self.time_step_duration * self.time_step_timeout_factor

    def set_start_obs_capture(self, start_obs_capture: float) -> None:
        """Change when the observation is captured, from the next time step on.

        Args:
            start_obs_capture: seconds after a time step's start when the capture starts.
        """
        self._join_thread()
        self.start_obs_capture = float(start_obs_capture)

    def set_ep_max_length(self, ep_max_length: float) -> None:
        """Change the episode length limit, from the next step on.

        Args:
            ep_max_length: the new maximum number of steps of an episode.
        """
        self._join_thread()
        self.ep_max_length = ep_max_length

    def __del__(self) -> None:
        # Dropped without close(): stop the time-step thread (without waiting, as this may run
        # in the garbage collector). The interface is not closed: call close() for that.
        if not getattr(self, "_closed", True) and getattr(self, "_thread", None) is not None:
            self._closed = True
            self._jobs.put(StopThread())

    def close(self) -> None:
        """Wait for the running time step, close the interface (when it has ``close()``) and stop
        the time-step thread. Idempotent; the environment cannot be used afterwards."""
        if self._closed:
            return
        self._closed = True
        self.running = False
        try:
            self._join_thread()
            self._result = None
            if callable(getattr(self._interface, "close", None)):
                self._call_interface(lambda itf: itf.close())
        finally:
            self._stop_worker()


class RealTimeEnvTS(RealTimeEnv):
    """:class:`RealTimeEnv` whose interface is built and called on one persistent thread
    (``real-time-gym-ts-v1``), for interfaces with thread affinity. ``render()`` still runs on the
    caller's thread, as in rtgym."""

    _INTERFACE_ON_WORKER = True
