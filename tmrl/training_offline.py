"""The training loop of the trainer: epochs of rounds of training steps, fed by the workers.

:class:`TrainingOffline` owns the replay memory and the training agent. The networking
``Trainer`` builds it, calls :meth:`TrainingOffline.run_epoch` with an *interface* (see
docs/internals.md: ``retrieve_buffer()`` and ``broadcast_model(actor)``) and checkpoints it
between epochs (:mod:`tmrl.checkpoint`). The loop itself holds no networking code, so it runs
just as well with an in-process interface (tests, benchmarks, single-machine training).
"""

from __future__ import annotations

import contextlib
import copy
import cProfile
import io
import logging
import math
import pstats
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from typing import Any

import torch

from tmrl.errors import UserError
from tmrl.metrics import MetricsLogger
from tmrl.util import RateLimitedLog, reuse_freed_memory

__all__ = ["RoundMetrics", "TorchTrainingOffline", "TrainingCallback", "TrainingOffline", "profiled"]

logger = logging.getLogger(__name__)

_WAIT_LOG_INTERVAL_S = 30.0

BEHIND_FRACTION = 0.9
"""A round that does fewer than this fraction of the updates per sample asked, without waiting,
is behind (:meth:`TrainingOffline._fell_behind`)."""


def _mean_rows(rows: list[dict[str, Any]]) -> dict[str, float]:
    """Mean of each numeric metric over a round's training steps (NaN and None skipped).

    Tensors are averaged on their device and read once per round, not once per step.
    """
    values: dict[str, list[Any]] = {}
    for row in rows:
        for key, value in row.items():
            if value is not None:
                values.setdefault(key, []).append(value)
    out: dict[str, float] = {}
    for key, vals in values.items():
        stacked = _stack_scalars(vals)
        tensors = [] if stacked is not None else [
            v.detach().float().mean() for v in vals if isinstance(v, torch.Tensor) and v.numel() > 0]
        if stacked is not None or tensors:
            stacked = torch.stack(tensors) if stacked is None else stacked
            finite = stacked[torch.isfinite(stacked)]
            out[key] = float(finite.mean().item()) if finite.numel() else math.nan
            continue
        nums = []
        for v in vals:
            try:
                f = float(v)
            except (TypeError, ValueError):
                continue
            if math.isfinite(f):
                nums.append(f)
        if nums:
            out[key] = sum(nums) / len(nums)
    return out


def _stack_scalars(vals: list[Any]) -> torch.Tensor | None:
    """``vals`` as one float tensor when they are all 0-dim tensors on one device (what the
    built-in agents return), in one call instead of three per value (a round of 1000 updates
    spent 0.2 to 0.5 s here); ``None`` otherwise."""
    first = vals[0]
    if not isinstance(first, torch.Tensor):
        return None
    device = first.device
    for v in vals:
        if not isinstance(v, torch.Tensor) or v.dim() != 0 or v.device != device:
            return None
    with torch.no_grad():
        return torch.stack(vals).float()


@dataclass
class RoundMetrics:
    """What one round of training did (:meth:`TrainingOffline.run_round`).

    Attributes:
        epoch: the epoch the round belongs to (from 0).
        round: the round's number within its epoch (from 0).
        rounds: rounds per epoch.
        total_updates: training steps done since the start of training, after the round.
        total_samples: samples received since the start of training, after the round.
        memory_len: samples in the replay memory after the round.
        return_train: the workers' latest training episode return.
        return_test: the workers' latest test episode return.
        episode_length_train: the workers' latest training episode length (steps).
        episode_length_test: the workers' latest test episode length (steps).
        round_time: wall time of the round (s).
        idle_time: part of ``round_time`` spent waiting for samples (s).
        sampling_time: part of ``round_time`` spent building batches (s).
        training_time: part of ``round_time`` spent in ``agent.train`` (s).
        updates: training steps done during the round.
        samples: samples received during the round.
        agent: the means of the agent's metrics over the round (``loss_actor``, ...).
        skipped_updates: updates with a non-finite loss or gradient, so far.
        restored_states: non-finite parameters replaced by the last good ones, so far.
        memory_errors: sample batches the memory refused, so far.
        counters: the interface's ``counters()`` (``rejected_batches``...), when it has them.
        stopped: :meth:`TrainingOffline.stop` cut the round short.
        updates_per_sample_asked: the setting's ratio (``max_training_steps_per_env_step``).
        behind: the trainer fell behind that ratio in this round: the ratio never made it wait for
            samples, and it did fewer than :data:`BEHIND_FRACTION` of the updates the round's
            samples asked for.
        updates_per_sample: ``updates`` per sample received in the round once training had
            started (None when it received none).
    """

    epoch: int
    round: int
    rounds: int
    total_updates: int
    total_samples: int
    memory_len: int
    return_train: float
    return_test: float
    episode_length_train: float
    episode_length_test: float
    round_time: float
    idle_time: float
    sampling_time: float
    training_time: float
    updates: int
    samples: int
    agent: dict[str, float] = field(default_factory=dict)
    skipped_updates: int = 0
    restored_states: int = 0
    memory_errors: int = 0
    counters: dict[str, Any] = field(default_factory=dict)
    stopped: bool = False
    updates_per_sample_asked: float | None = None
    behind: bool = False
    updates_per_sample: float | None = None

    @property
    def updates_per_second(self) -> float:
        """``updates / round_time`` (NaN for a round of no duration)."""
        return self.updates / self.round_time if self.round_time > 0 else math.nan

    @property
    def samples_per_second(self) -> float:
        """``samples / round_time`` (NaN for a round of no duration)."""
        return self.samples / self.round_time if self.round_time > 0 else math.nan

    def as_row(self) -> dict[str, Any]:
        """The round as one flat row of metrics, as :meth:`TrainingOffline.run_epoch` returns and
        logs it: ``epoch``, ``round``, ``rounds``, the totals, the episode statistics, the times,
        ``updates_per_second``, ``samples_per_second``, the agent's means, ``skipped_updates``,
        ``restored_states``, ``memory_errors``, ``updates_per_sample`` (done),
        ``updates_per_sample_asked``, ``behind`` and the counters."""
        row: dict[str, Any] = {
            "epoch": self.epoch,
            "round": self.round,
            "rounds": self.rounds,
            "total_updates": self.total_updates,
            "total_samples": self.total_samples,
            "memory_len": self.memory_len,
            "return_train": self.return_train,
            "return_test": self.return_test,
            "episode_length_train": self.episode_length_train,
            "episode_length_test": self.episode_length_test,
            "round_time": self.round_time,
            "idle_time": self.idle_time,
            "sampling_time": self.sampling_time,
            "training_time": self.training_time,
            "updates_per_second": self.updates_per_second,
            "samples_per_second": self.samples_per_second,
        }
        row.update(self.agent)
        row["skipped_updates"] = self.skipped_updates
        row["restored_states"] = self.restored_states
        row["memory_errors"] = self.memory_errors
        row["updates_per_sample"] = self.updates_per_sample
        row["updates_per_sample_asked"] = self.updates_per_sample_asked
        row["behind"] = self.behind
        row.update(self.counters)
        return row


class TrainingCallback:
    """Observes the training loop without subclassing it (like Stable-Baselines3's callbacks).
    Override what you need and pass an instance to :meth:`TrainingOffline.add_callback`; each
    method gets the :class:`TrainingOffline` (its ``agent``, ``memory``, totals).
    """

    def on_epoch_start(self, training: TrainingOffline) -> None:
        """Before the first round of an epoch.

        Args:
            training: the training loop.
        """

    def on_round_end(self, training: TrainingOffline, metrics: RoundMetrics) -> bool | None:
        """After each round, once its row is logged. Return False to end the epoch now (it is
        then not counted, as after :meth:`TrainingOffline.stop`).

        Args:
            training: the training loop.
            metrics: the round's :class:`RoundMetrics`.
        """
        return None

    def on_epoch_end(self, training: TrainingOffline, rows: list[dict[str, Any]]) -> None:
        """After the last round of an epoch (or the round that stopped it).

        Args:
            training: the training loop.
            rows: the epoch's rows, as logged (``RoundMetrics.as_row()``).
        """


class _RoundFunction(TrainingCallback):
    """A plain function ``f(metrics)`` as a callback called after each round."""

    def __init__(self, fn: Callable[[RoundMetrics], Any]) -> None:
        self.fn = fn

    def on_round_end(self, training: TrainingOffline, metrics: RoundMetrics) -> bool | None:
        return self.fn(metrics)


def _actor_finite(actor: Any) -> bool:
    """Whether the actor's state (a torch module's ``state_dict``) is finite (``True`` for an
    actor that is not a module: its bytes are checked before they are sent)."""
    state_dict = getattr(actor, "state_dict", None)
    if not callable(state_dict):
        return True
    from tmrl.algorithms.guard import all_finite

    return all_finite(state_dict())


@dataclass
class _RoundClock:
    """Seconds of a round spent waiting for samples, building batches and training."""

    idle: float = 0.0
    sampling: float = 0.0
    training: float = 0.0


@contextlib.contextmanager
def profiled(enabled: bool, label: str, top: int = 25) -> Iterator[None]:
    """Profile the block with cProfile when ``enabled`` and log its ``top`` functions by
    cumulative time (``label`` names the block in the log line)."""
    if not enabled:
        yield
        return
    profiler = cProfile.Profile()
    profiler.enable()
    try:
        yield
    finally:
        profiler.disable()
        text = io.StringIO()
        pstats.Stats(profiler, stream=text).sort_stats("cumulative").print_stats(top)
        logger.info("profile of %s:\n%s", label, text.getvalue())


@dataclass(eq=False)
class TrainingOffline:
    """Training loop of off-policy algorithms.

    Args:
        env_cls: class of a (dummy) environment, built once to read its observation and action
            spaces; or a tuple ``(observation_space, action_space)``.
        memory_cls: class (or partial) of the replay memory, called with ``nb_steps=steps`` and
            ``device=device``.
        training_agent_cls: class (or partial) of the training agent, called with
            ``observation_space``, ``action_space`` and ``device``.
        epochs: total number of epochs (the trainer checkpoints after each).
        rounds: rounds per epoch (one row of metrics per round).
        steps: training steps per round.
        update_model_interval: training steps between two broadcasts of the actor's weights.
        update_buffer_interval: training steps between two retrievals of the samples received.
        max_training_steps_per_env_step: training pauses while updates per received sample
            exceed this ratio.
        sleep_between_buffer_retrieval_attempts: seconds between two retrievals while waiting
            for samples.
        profiling: profile each round with cProfile and log the top functions.
        agent_scheduler: ``f(agent, epoch)`` called at the start of each epoch, or ``None``.
        start_training: samples to receive before the first training step.
        device: device of the memory's batches and of the agent (``None``: left to them).
        max_env_steps_per_training_step: the workers' side of the ratio (0: no limit): samples
            collected per training step may not exceed this, plus ``start_training``. Sent to the
            workers with the weights (:meth:`pace`); for environments faster than real time.

    Attributes:
        memory: the replay memory.
        agent: the training agent.
        epoch: epochs completed.
        total_updates: training steps done.
        total_samples: samples received (plus those the memory held when built).
        metrics_logger: the :class:`~tmrl.metrics.MetricsLogger` used by :meth:`run_epoch` when
            it is given none; ``None`` logs one line per round through ``logging``.
        max_wait_s: ``None`` (default) waits for samples as long as it takes; a number of
            seconds makes a longer wait raise ``TimeoutError``.

    Raises:
        UserError: a required class is missing or an interval is not positive.
    """

    env_cls: Any = None
    memory_cls: Any = None
    training_agent_cls: Any = None
    epochs: int = 10
    rounds: int = 50
    steps: int = 2000
    update_model_interval: int = 100
    update_buffer_interval: int = 100
    max_training_steps_per_env_step: float = 1.0
    sleep_between_buffer_retrieval_attempts: float = 1.0
    profiling: bool = False
    agent_scheduler: Callable[[Any, int], None] | None = None
    start_training: int = 0
    device: str | None = None
    max_env_steps_per_training_step: float = 0.0

    FULL_CHECK_INTERVAL = 100
    """Updates between two checks of the agent's whole state at broadcasts (see :meth:`_broadcast`;
    the actor is checked at every one). A class attribute, not an argument: a check and a copy of a
    SAC 256x256 agent's state cost about 0.7 ms, half an update on the tutorial's settings, which
    broadcast after every update."""

    def __post_init__(self) -> None:
        for name in ("env_cls", "memory_cls", "training_agent_cls"):
            if getattr(self, name) is None:
                raise UserError(f"TrainingOffline needs {name}: pass it (e.g. with tmrl.util.partial)")
        for name in ("rounds", "steps", "update_model_interval", "update_buffer_interval"):
            if int(getattr(self, name)) < 1:
                raise UserError(f"TrainingOffline {name} must be at least 1, got {getattr(self, name)}")
        self.epoch = 0
        self.total_updates = 0
        self.metrics_logger: MetricsLogger | None = None
        self.max_wait_s: float | None = None
        self._stop = threading.Event()
        self._default_logger: MetricsLogger | None = None
        self._round_samples = self._round_training_samples = self._round_ratio_waits = 0
        self._broadcast_at = 0  # total_updates at the last broadcast
        self.callbacks: list[TrainingCallback] = []
        if float(self.max_env_steps_per_training_step) < 0:
            raise UserError("TrainingOffline max_env_steps_per_training_step must be >= 0 (0: no limit), got "
                            f"{self.max_env_steps_per_training_step}")
        self.memory_errors = 0
        self._said_behind = False
        self._memory_error_log = RateLimitedLog(logger, logging.WARNING, 60.0)
        self.memory = self.memory_cls(nb_steps=self.steps, device=self.device)
        if isinstance(self.env_cls, tuple):
            if len(self.env_cls) != 2:
                raise UserError("env_cls as a tuple must be (observation_space, action_space)")
            observation_space, action_space = self.env_cls
        else:
            env = self.env_cls()
            try:
                observation_space, action_space = env.observation_space, env.action_space
            finally:
                close = getattr(env, "close", None)
                if close is not None:
                    close()
        self.agent = self.training_agent_cls(
            observation_space=observation_space, action_space=action_space, device=self.device
        )
        self.total_samples = len(self.memory)
        self.restored_states = 0
        self._last_good_state: Any = None
        self._checked_at: int | None = None  # total_updates at the last ensure_finite()
        logger.info("training set up: %d samples in memory", self.total_samples)

    # --- non-finite parameters ---------------------------------------------------------------

    def ensure_finite(self) -> bool:
        """Check that the agent's state (models, targets, optimizers) is finite before it is
        broadcast or checkpointed; keep a copy of it when it is, restore the last good copy when it
        is not.

        Returns:
            ``True`` when the state is finite (possibly after a restore), ``False`` when it is not
            and there is no good copy to go back to (then do not broadcast nor save it).
        """
        state_dict = getattr(self.agent, "state_dict", None)
        if not callable(state_dict):
            return True
        from tmrl.algorithms.guard import all_finite, copy_state_into

        state = state_dict()
        self._checked_at = self.total_updates
        if all_finite(state):
            self._last_good_state = copy_state_into(self._last_good_state, state)
            return True
        if self._last_good_state is None:
            logger.error("the agent's parameters are not finite and there is no earlier good state to restore")
            return False
        self.agent.load_state_dict(copy.deepcopy(self._last_good_state))
        self.restored_states += 1
        logger.error(
            "the agent's parameters were not finite: restored the last good state (%d restores so far)",
            self.restored_states,
        )
        return True

    # --- control -------------------------------------------------------------------------------

    def stop(self) -> None:
        """Ask :meth:`run_epoch` to return as soon as possible (thread-safe). The epoch in
        progress is not counted; :attr:`stopped` becomes ``True``."""
        self._stop.set()

    @property
    def stopped(self) -> bool:
        """Whether :meth:`stop` was called."""
        return self._stop.is_set()

    # --- samples -------------------------------------------------------------------------------

    def update_buffer(self, interface: Any) -> int:
        """Move every sample the interface received into the memory.

        Returns:
            The number of samples received.
        """
        buffer = interface.retrieve_buffer()
        n = len(buffer)
        if n:
            try:
                self.memory.append(buffer)
            except Exception:  # noqa: BLE001 (samples from the network must never stop the trainer)
                self._memory_refused(n)
                return 0
            self.total_samples += n
            self._round_samples += n
            if self.total_updates > 0:
                self._round_training_samples += n
        return n

    def _memory_refused(self, n: int) -> None:
        """A buffer the memory could not store: dropped and counted, never fatal. The first one is
        logged with its traceback (it may be a bug in a custom memory), the next ones in a line
        a minute."""
        self.memory_errors += 1
        if self.memory_errors == 1:
            logger.exception("the replay memory refused %d samples (dropped); later refusals are counted in "
                           "memory_errors", n)
        else:
            self._memory_error_log("the replay memory refused %d more samples (%d refusals so far)", n,
                                   self.memory_errors)

    def pace(self) -> dict[str, Any] | None:
        """What the workers need to keep pace with training, sent with the weights (``None``
        when ``max_env_steps_per_training_step`` is 0): the limit, the most samples the trainer
        accepts to have received by now (``limit * total_updates + start_training``, rounded
        down; at least 1 before any update) and how many it has received."""
        limit = float(self.max_env_steps_per_training_step)
        if limit <= 0:
            return None
        budget = math.floor(limit * self.total_updates) + max(int(self.start_training), 1)
        return {"pace_limit": limit, "pace_budget": int(budget), "pace_received": int(self.total_samples)}

    def _broadcast(self, interface: Any) -> None:
        """Send the actor to the workers, unless its parameters are not finite.

        The actor's state is checked at every broadcast; the agent's whole state (with the copy
        :meth:`ensure_finite` keeps) at the first broadcast, then at the first one after every
        :attr:`FULL_CHECK_INTERVAL` updates, and whenever the actor is not finite (restored before
        it is sent)."""
        if (self._checked_at is None or self.total_updates - self._checked_at >= self.FULL_CHECK_INTERVAL
                or not _actor_finite(self.agent.get_actor())):
            if not self.ensure_finite():
                return
        interface.broadcast_model(self.agent.get_actor())
        self._broadcast_at = self.total_updates

    def _ready(self) -> bool:
        if self.total_samples <= 0 or self.total_samples < self.start_training:
            return False
        if self.total_updates / self.total_samples > self.max_training_steps_per_env_step:
            return False
        return len(self.memory) > 0

    def check_ratio(self, interface: Any) -> bool:
        """Wait, pulling samples, until training may go on: at least ``start_training`` samples
        received, a non-empty memory, and no more than ``max_training_steps_per_env_step``
        updates per received sample.

        Args:
            interface: the trainer's link: ``retrieve_buffer() -> Buffer`` (and ``broadcast_model``).

        Returns:
            ``True`` when training may go on, ``False`` when :meth:`stop` was called.

        Raises:
            TimeoutError: :attr:`max_wait_s` is set and was exceeded.
        """
        if self._ready():
            return not self._stop.is_set()
        if self.max_env_steps_per_training_step > 0 and self.total_updates != self._broadcast_at:
            # Paced workers wait for the trainer's count of updates: give them the current one, or
            # both sides could wait for each other.
            self._broadcast(interface)
        waiting_to_start = self.total_updates == 0
        if not waiting_to_start:
            self._round_ratio_waits += 1  # the ratio binds: the trainer keeps up with the samples
        if waiting_to_start:
            logger.info("waiting for samples: training starts after %d (%d received)",
                        max(int(self.start_training), 1), self.total_samples)
        else:  # the ratio of updates to samples is reached: a short, normal pause
            logger.debug("waiting for samples (%d received, %d updates done)", self.total_samples, self.total_updates)
        start = last_log = time.monotonic()
        while True:
            self.update_buffer(interface)
            if self._ready():
                break
            now = time.monotonic()
            if self.max_wait_s is not None and now - start > self.max_wait_s:
                raise TimeoutError(
                    f"no usable samples after waiting {now - start:.0f} s ({self.total_samples} received, "
                    f"start_training={self.start_training}): are the workers running?"
                )
            if now - last_log >= _WAIT_LOG_INTERVAL_S:
                logger.info("still waiting for samples: %d received so far", self.total_samples)
                last_log = now
            # Event.wait rather than time.sleep: stop() ends the wait at once.
            if self._stop.wait(max(0.0, float(self.sleep_between_buffer_retrieval_attempts))):
                return False
        if waiting_to_start:
            logger.info("%d samples received: training starts", self.total_samples)
        else:
            logger.debug("resuming training (%d samples received)", self.total_samples)
        return not self._stop.is_set()

    # --- the loop ------------------------------------------------------------------------------

    def _logger(self, given: MetricsLogger | None) -> MetricsLogger:
        if given is not None:
            return given
        if self.metrics_logger is not None:
            return self.metrics_logger
        if self._default_logger is None:
            self._default_logger = MetricsLogger(run_name="", folder=None, tensorboard=False)
        return self._default_logger

    def add_callback(self, callback: TrainingCallback | Callable[[RoundMetrics], Any]) -> None:
        """Observe the loop: ``callback`` is a :class:`TrainingCallback`, or a function called
        with each round's :class:`RoundMetrics` (as :meth:`TrainingCallback.on_round_end`)."""
        if not isinstance(callback, TrainingCallback):
            callback = _RoundFunction(callback)
        self.callbacks.append(callback)

    def run_epoch(self, interface: Any, logger: MetricsLogger | None = None) -> list[dict[str, Any]]:
        """Run one epoch: ``rounds`` rounds of ``steps`` training steps (see :meth:`run_round`).

        Args:
            interface: has ``retrieve_buffer() -> Buffer`` and ``broadcast_model(actor)``.
            logger: where each round's row goes; default :attr:`metrics_logger`, else a console
                line through ``logging``.

        Returns:
            One dict per round completed (:meth:`RoundMetrics.as_row`). After :meth:`stop` (or a
            callback that returned False), the rounds done so far; the epoch is then not counted.
        """
        sink = self._logger(logger)
        if self.agent_scheduler is not None:
            self.agent_scheduler(self.agent, self.epoch)
        for callback in self.callbacks:
            callback.on_epoch_start(self)
        rows: list[dict[str, Any]] = []
        stopped = False
        for rnd in range(self.rounds):
            result = self.run_round(interface, rnd)
            if result is None:  # stopped before the round trained at all
                stopped = True
                break
            row = result.as_row()
            rows.append(row)
            sink.log_round(row)
            wanted = [callback.on_round_end(self, result) for callback in self.callbacks]
            if result.stopped or any(w is False for w in wanted):
                stopped = True
                break
        if not stopped:
            self.epoch += 1
        for callback in self.callbacks:
            callback.on_epoch_end(self, rows)
        return rows

    def run_round(self, interface: Any, rnd: int = 0) -> RoundMetrics | None:
        """One round: up to ``steps`` training steps. Every ``update_buffer_interval`` steps the
        samples received are moved into the memory, every ``update_model_interval`` steps the
        actor is broadcast, and after each step the loop waits while training is ahead of the
        samples (:meth:`check_ratio`).

        Args:
            interface: the trainer's link: ``retrieve_buffer() -> Buffer`` and ``broadcast_model(actor)``.
            rnd: the round's number within the epoch (for the metrics).

        Returns:
            The round's metrics (``stopped`` is set when :meth:`stop` cut it short), or None
            when it was stopped before its first step.
        """
        t0 = time.perf_counter()
        self._round_samples = self._round_training_samples = self._round_ratio_waits = 0
        updates_before = self.total_updates
        if not self.check_ratio(interface):
            return None
        clock = _RoundClock(idle=time.perf_counter() - t0)
        rows: list[dict[str, Any]] = []
        with profiled(self.profiling, f"round {rnd}"):
            stopped = self._train_steps(interface, rows, clock)
        return self._round_metrics(interface, rnd, t0, updates_before, rows, clock, stopped)

    def _train_steps(self, interface: Any, rows: list[dict[str, Any]], clock: _RoundClock) -> bool:
        """The training steps of a round (their metrics go to ``rows``, their times to ``clock``).
        Returns True when :meth:`stop` ended them."""
        t_prev = time.perf_counter()
        for batch in self.memory:
            t_sample = time.perf_counter()
            clock.sampling += t_sample - t_prev
            if self.total_updates % self.update_buffer_interval == 0:
                self.update_buffer(interface)
            if self.total_updates == 0:
                logger.info("starting training")
            t_train = time.perf_counter()
            rows.append(self.agent.train(batch) or {})
            clock.training += time.perf_counter() - t_train
            self.total_updates += 1
            if self.total_updates % self.update_model_interval == 0:
                self._broadcast(interface)
            t_wait = time.perf_counter()
            if not self.check_ratio(interface):
                return True
            t_prev = time.perf_counter()
            clock.idle += t_prev - t_wait
        return False

    def _round_metrics(
        self,
        interface: Any,
        rnd: int,
        t0: float,
        updates_before: int,
        rows: list[dict[str, Any]],
        clock: _RoundClock,
        stopped: bool,
    ) -> RoundMetrics:
        round_time = time.perf_counter() - t0
        counters = getattr(interface, "counters", None)
        updates, samples = self.total_updates - updates_before, self._round_samples
        asked = float(self.max_training_steps_per_env_step)
        fed = self._round_training_samples
        behind = self._fell_behind(updates, fed, asked, self._round_ratio_waits)
        return RoundMetrics(
            epoch=self.epoch,
            round=rnd,
            rounds=self.rounds,
            total_updates=self.total_updates,
            total_samples=self.total_samples,
            memory_len=len(self.memory),
            return_train=self.memory.stat_train_return,
            return_test=self.memory.stat_test_return,
            episode_length_train=self.memory.stat_train_steps,
            episode_length_test=self.memory.stat_test_steps,
            round_time=round_time,
            idle_time=clock.idle,
            sampling_time=clock.sampling,
            training_time=clock.training,
            updates=updates,
            samples=samples,
            agent=_mean_rows(rows),
            skipped_updates=int(getattr(self.agent, "skipped_updates", 0)),
            restored_states=self.restored_states,
            memory_errors=self.memory_errors,
            counters=dict(counters()) if callable(counters) else {},  # rejected_batches... (networking)
            stopped=stopped,
            updates_per_sample_asked=asked,
            behind=behind,
            updates_per_sample=updates / fed if fed > 0 else None,
        )

    def _fell_behind(self, updates: int, samples: int, asked: float, ratio_waits: int) -> bool:
        """Whether a round fell behind the ratio the setting asks for, said once in the log (the
        round lines carry it each time): the ratio never made the trainer wait for samples in the
        round (``ratio_waits``: the waits once training had started) and it still did fewer than
        :data:`BEHIND_FRACTION` of ``asked`` updates per sample received since training started
        (``samples``). In real time the workers do not wait for the trainer, so such a round trains
        on fewer updates per sample than the setting's figures were measured with."""
        if samples <= 0 or asked <= 0 or ratio_waits > 0:
            return False
        done = updates / samples
        if done >= BEHIND_FRACTION * asked:
            return False
        if not self._said_behind:
            self._said_behind = True
            logger.warning(
                "the trainer is behind: %.2f updates per sample done, %.4g asked (MAX_TRAINING_STEPS_PER_ENVIRONMENT_"
                "STEP); it trains as fast as it can but the workers send samples faster. The round lines say "
                "\"behind\" while it lasts; a cheaper setting (docs/benchmarks.md compares their cost per step) or a "
                "faster trainer keeps the ratio", done, asked)
        return True


@dataclass(eq=False)
class TorchTrainingOffline(TrainingOffline):
    """:class:`TrainingOffline` for PyTorch agents: ``device=None`` selects ``"cuda"`` when
    available, else ``"cpu"``. Same arguments."""

    def __post_init__(self) -> None:
        if self.device is None:
            self.device = "cuda" if torch.cuda.is_available() else "cpu"
        reuse_freed_memory()  # each update's large tensors reuse the last one's memory (Linux)
        super().__post_init__()
