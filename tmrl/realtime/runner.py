"""The time-step thread of :class:`~tmrl.realtime.env.RealTimeEnv`: the typed messages between
the environment and that thread, the elastic clock's rule (:func:`_next_start`), and
:class:`TimeStepRunner`, what the thread runs.

The environment sends :data:`Job` messages (:class:`StartTimeStep`, :class:`ChainTimeStep`,
:class:`CallInterface`, :class:`StopThread`) and gets :data:`Result` messages back
(:class:`Observed`, :class:`Returned`, :class:`Raised`), in order. All names are re-exported by
:mod:`tmrl.realtime.env`, their former home.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from tmrl.realtime.benchmark import StepObserver
from tmrl.realtime.clock import Clock

__all__ = [
    "CallInterface",
    "ChainTimeStep",
    "Job",
    "Observed",
    "Raised",
    "Result",
    "Returned",
    "StartTimeStep",
    "StopThread",
    "TimeStepRunner",
]


def _next_start(decision_time: float, t_end: float, timeout: float) -> tuple[float, bool]:
    """The elastic rule: where the next time step starts, and whether the clock restarted.

    ``decision_time`` is when the next time step could start at the earliest (the later of the
    ``step()`` call, the end of the capture and the nominal end ``t_end``). Within ``timeout``
    after ``t_end``, the next time step starts at ``t_end`` (the cadence is kept); later, at
    ``decision_time``.
    """
    if decision_time < t_end + timeout:
        return t_end, False
    return decision_time, True



# Messages between the environment and its time-step thread -----------------------------------
# Jobs go from the environment to the thread, results come back, both in order (one result per
# job, except ChainTimeStep, which sends none when no time step starts).


@dataclass(frozen=True, eq=False)
class StartTimeStep:
    """Job: run a time step with timestamps decided by the caller.

    Attributes:
        action: the action to send (before ``act_prepro_func``).
        t_start: when to call ``send_control``.
        t_co: when to capture the observation.
        t_end: the nominal end of the time step.
    """

    action: Any
    t_start: float
    t_co: float
    t_end: float


@dataclass(frozen=True, eq=False)
class ChainTimeStep:
    """Job: start the next time step right after the one just captured, deciding its start with
    the same rule as the caller (:func:`_next_start`), so the control goes out at the end of the
    previous time step without waiting for the caller's thread to wake up. Nothing starts (and no
    result comes back) when the episode ended or the previous time step failed or terminated.

    Attributes:
        action: the action to send.
        t_call: when ``step()`` was called.
        truncating: this step truncates the episode (no time step starts).
        duration: ``time_step_duration``.
        capture: ``start_obs_capture``.
        timeout: how late the time step may start before the clock restarts (seconds).
    """

    action: Any
    t_call: float
    truncating: bool
    duration: float
    capture: float
    timeout: float


@dataclass(frozen=True)
class CallInterface:
    """Job: run ``fn(interface)`` on the time-step thread; the result is :class:`Returned` or
    :class:`Raised`."""

    fn: Callable[[Any], Any]


@dataclass(frozen=True)
class StopThread:
    """Job: end the time-step thread (after answering :class:`Returned` ``(None)``)."""


@dataclass(frozen=True, eq=False)
class Observed:
    """Result: what a time step captured.

    Attributes:
        obs: the interface's observation (after ``obs_prepro_func``), as a tuple.
        rew: the reward.
        terminated: whether the episode ended.
        info: the interface's info dict.
        capture_end: when the capture returned (clock time).
    """

    obs: tuple[Any, ...]
    rew: Any
    terminated: Any
    info: Any
    capture_end: float


@dataclass(frozen=True)
class Returned:
    """Result: what a :class:`CallInterface` returned (None for :class:`StopThread`)."""

    value: Any = None


@dataclass(frozen=True)
class Raised:
    """Result: the exception a job raised, for the caller to re-raise."""

    error: BaseException


Job = StartTimeStep | ChainTimeStep | CallInterface | StopThread
"""What the environment sends to its time-step thread."""
Result = Observed | Returned | Raised
"""What the time-step thread sends back."""


class TimeStepRunner:
    """What the time-step thread runs: :data:`Job` messages from the environment, :data:`Result`
    messages back, in order. Holds no reference to the environment, so that an environment
    dropped without ``close()`` is collected (and its ``__del__`` stops the thread).

    Args:
        clock: the environment's clock.
        observer: told of ``send_control`` and of the capture (see
            :class:`~tmrl.realtime.benchmark.StepObserver`).
        act_prepro_func: applied to an action before ``send_control`` (rtgym's hook), or None.
        obs_prepro_func: applied to a captured observation (rtgym's hook), or None.

    Attributes:
        interface: the interface the jobs act on (set by the environment once built).
        jobs: the channel of :data:`Job` messages.
        results: the channel of :data:`Result` messages.
    """

    def __init__(
        self,
        clock: Clock,
        observer: StepObserver,
        act_prepro_func: Callable[[Any], Any] | None,
        obs_prepro_func: Callable[[Any], Any] | None,
    ) -> None:
        self.clock = clock
        self.observer = observer
        self.act_prepro_func = act_prepro_func
        self.obs_prepro_func = obs_prepro_func
        self.interface: Any = None
        self.jobs = clock.channel()
        self.results = clock.channel()

    def loop(self, t0: float) -> None:
        """The time-step thread: runs jobs in order from ``t0`` on until :class:`StopThread`."""
        self.clock.sleep_until(t0)
        # (t_end, capture_end) of the last time step when it may be chained, else None
        last: tuple[float, float] | None = None
        while True:
            job = self.jobs.get()
            if isinstance(job, StopThread):
                self.results.put(Returned(None))
                return
            last = self.run(job, last)
            job = None  # a finished job may hold the environment (a bound method): let it go

    def run(self, job: Job, last: tuple[float, float] | None) -> tuple[float, float] | None:
        """Run one job other than :class:`StopThread`.

        Args:
            job: the job.
            last: ``(t_end, capture_end)`` of the last time step when it may be chained, else None.

        Returns:
            The new ``last``.
        """
        if isinstance(job, ChainTimeStep):
            if last is None or job.truncating:
                return last  # the episode ended: no time step starts
            t_end, capture_end = last
            t_start, _ = _next_start(max(job.t_call, capture_end, t_end), t_end, job.timeout)
            return self.time_step(
                StartTimeStep(job.action, t_start, t_start + job.capture, t_start + job.duration)
            )
        if isinstance(job, StartTimeStep):
            return self.time_step(job)
        if isinstance(job, CallInterface):
            try:
                value = job.fn(self.interface)
            except BaseException as err:  # noqa: BLE001  (handed to the caller, who re-raises it)
                self.results.put(Raised(err))
            else:
                self.results.put(Returned(value))
        else:
            self.results.put(Raised(TypeError(f"the time-step thread got an unknown job: {job!r}")))
        return None

    def time_step(self, step: StartTimeStep) -> tuple[float, float] | None:
        """Send the control at ``step.t_start``, capture the observation at ``step.t_co`` and post
        it as :class:`Observed` (or :class:`Raised`).

        Returns:
            ``(t_end, capture_end)`` when a next time step may follow, else None.
        """
        clock, observer = self.clock, self.observer
        try:
            clock.sleep_until(step.t_start)
            observer.on_send_control_start(clock.now())
            action = step.action
            self.interface.send_control(self.act_prepro_func(action) if self.act_prepro_func else action)
            observer.on_send_control_end(clock.now())
            clock.sleep_until(step.t_co)
            observer.on_obs_capture_start(clock.now())
            obs, rew, terminated, info = self.interface.get_obs_rew_terminated_info()
            if self.obs_prepro_func:
                obs = self.obs_prepro_func(obs)
            obs = tuple(obs)
            capture_end = clock.now()
            observer.on_obs_captured(capture_end)
        except BaseException as err:  # noqa: BLE001  (handed to the caller, who re-raises it)
            self.results.put(Raised(err))
            return None
        self.results.put(Observed(obs, rew, terminated, info, capture_end))
        return None if terminated else (step.t_end, capture_end)
