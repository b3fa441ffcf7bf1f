"""A real-time console a person can read (issue 40): time steps that run late are summarised, one
line per interval with their count and the worst overrun, never a warning and its source line per
time step; the environment still issues every warning for code that counts them.

The environment tests drive a real :class:`~tmrl.realtime.RealTimeEnv` whose policy is
deliberately slower than its time step, so that every step runs late.
"""

from __future__ import annotations

import itertools
import re
import time
import warnings

import numpy as np
import pytest
from gymnasium import spaces

from tmrl.realtime import DEFAULT_CONFIG_DICT, RealTimeEnv, RealTimeGymInterface, TimeStepTimeoutWarning
from tmrl.realtime.timeouts import TimeoutSummary, summarised_timeouts

LINE = re.compile(r"^(\d+) time steps? ran late (just now|in the last \d+ s) \(worst ([\d.]+) ms after the end of "
                  r"its time step, ([\d.]+) ms allowed\): the clock restarted")


class Still(RealTimeGymInterface):
    """A device that does nothing, instantly."""

    def get_observation_space(self):
        return spaces.Tuple((spaces.Box(-1.0, 1.0, (1,), np.float32),))

    def get_action_space(self):
        return spaces.Box(-1.0, 1.0, (1,), np.float32)

    def get_default_action(self):
        return np.zeros(1, np.float32)

    def send_control(self, control):
        pass

    def reset(self, seed=None, options=None):
        return [np.zeros(1, np.float32)], {}

    def get_obs_rew_terminated_info(self):
        return [np.zeros(1, np.float32)], 0.0, False, {}


def slow_env(time_step: float = 0.01) -> RealTimeEnv:
    return RealTimeEnv(dict(DEFAULT_CONFIG_DICT, interface=Still, time_step_duration=time_step,
                            start_obs_capture=time_step, time_step_timeout_factor=0.5, ep_max_length=10**9,
                            act_buf_len=1, wait_on_done=False))


def drive_slowly(env: RealTimeEnv, seconds: float, inference: float) -> int:
    """Step ``env`` for ``seconds`` with a policy that thinks for ``inference`` seconds."""
    env.reset()
    steps, t0 = 0, time.monotonic()
    while time.monotonic() - t0 < seconds:
        time.sleep(inference)  # the slow policy (the "load"), not synchronisation
        env.step(np.zeros(1, np.float32))
        steps += 1
    return steps


def test_a_slow_policy_gives_one_line_per_interval_with_the_count_and_the_worst_overrun(capfd):
    lines: list[tuple[float, str]] = []
    env = slow_env(0.01)
    try:
        with summarised_timeouts(interval=1.0, log=lambda line: lines.append((time.monotonic(), line))) as summary:
            t0 = time.monotonic()
            steps = drive_slowly(env, 3.2, inference=0.03)  # 20 ms late at each 10 ms step (5 ms allowed)
            elapsed = time.monotonic() - t0
    finally:
        env.close()
    assert summary.total >= 0.8 * steps and steps >= 20, (summary.total, steps)
    # at most one line per interval: the first at once, then one per second, then what was left
    assert 2 <= len(lines) <= elapsed / 1.0 + 2, [line for _, line in lines]
    assert all(b - a >= 0.95 for (a, _), (b, _) in itertools.pairwise(lines[:-1])), lines
    counted = 0
    for _, line in lines:
        m = LINE.match(line)
        assert m, line
        counted += int(m.group(1))
        assert float(m.group(3)) >= 5.0 and float(m.group(4)) == 5.0  # late beyond the 5 ms allowed
    assert counted == summary.total  # every late step is in a line, none twice
    err = capfd.readouterr().err
    assert "TimeStepTimeoutWarning" not in err and "env.step" not in err, err[-2000:]


def test_every_warning_is_still_issued_for_code_that_counts_them():
    env = slow_env(0.01)
    try:
        # the inner catcher is what tmrl.realtime.check does
        with summarised_timeouts(interval=1.0, log=lambda line: None) as summary, \
                warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always", TimeStepTimeoutWarning)
            drive_slowly(env, 0.5, inference=0.03)
    finally:
        env.close()
    late = [w.message for w in caught if issubclass(w.category, TimeStepTimeoutWarning)]
    assert late and all(w.late > w.allowed == pytest.approx(0.005) for w in late)
    assert summary.total == 0  # the inner catcher took them


def test_other_warnings_pass_and_the_filters_are_restored(recwarn):
    before = list(warnings.filters)
    with summarised_timeouts(interval=1.0, log=lambda line: None):
        warnings.warn("something else", UserWarning, stacklevel=1)
    assert warnings.filters == before
    assert [str(w.message) for w in recwarn] == ["something else"]


class FakeClock:
    def __init__(self) -> None:
        self.t = 100.0

    def __call__(self) -> float:
        return self.t


def test_the_summary_line_counts_and_times():
    clock, lines = FakeClock(), []
    summary = TimeoutSummary(interval=10.0, log=lines.append, clock=clock)
    summary.add(0.030, 0.020)  # the first one of a quiet period: at once
    assert len(lines) == 1 and lines[0].startswith("1 time step ran late just now (worst 30.0 ms")
    for i in range(49):  # a burst within the interval: nothing yet
        clock.t += 0.1
        summary.add(0.025 + (0.05 if i == 20 else 0.0), 0.020)
    assert len(lines) == 1
    clock.t = 110.5
    summary.add(0.021, 0.020)  # the interval is over: the burst and this one, in one line
    assert lines[1].startswith("50 time steps ran late in the last 10 s (worst 75.0 ms after the end of its time "
                               "step, 20.0 ms allowed)"), lines[1]
    clock.t += 1.0
    summary.add(0.022, 0.020)
    summary.flush()  # at the end: what is left
    assert len(lines) == 3 and lines[2].startswith("1 time step ran late in the last 1 s (worst 22.0 ms")
    summary.flush()
    assert len(lines) == 3 and summary.total == 52 and summary.lines == 3
