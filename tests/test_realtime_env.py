"""Rules of the real-time environment, checked in virtual time (FakeClock) for both ids."""

from __future__ import annotations

import dataclasses
import gc
import subprocess
import sys
import threading
import warnings

import gymnasium
import numpy as np
import pytest
from gymnasium import spaces

import tmrl.realtime as rt
from tmrl.errors import UserError
from tmrl.realtime import DEFAULT_CONFIG_DICT, FakeClock, RealTimeGymInterface, TimeStepTimeoutWarning
from tmrl.realtime.benchmark import BenchmarkObserver, NullObserver, StepObserver
from tmrl.realtime.env import (
    CallInterface,
    ChainTimeStep,
    Observed,
    Raised,
    Returned,
    StartTimeStep,
    StopThread,
    TimeStepRunner,
)

IDS = ["real-time-gym-v1", "real-time-gym-ts-v1"]
T = 0.05  # time step
C = 0.03  # start_obs_capture


class Scripted(RealTimeGymInterface):
    """Records every call with the caller's virtual time and thread; observation k is [k]."""

    def __init__(self, clock, log, capture=0.0, terminate_at=(), fail_at=None, fail_init=False):
        if fail_init:
            raise ValueError("no device")
        self.clock, self.log, self.capture = clock, log, capture
        self.terminate_at, self.fail_at = set(terminate_at), fail_at
        self.k = 0

    def _rec(self, name, *extra):
        self.log.append((name, round(self.clock.now(), 9), threading.current_thread().name, *extra))

    def get_observation_space(self):
        return spaces.Tuple((spaces.Box(-np.inf, np.inf, (1,), np.float32),))

    def get_action_space(self):
        return spaces.Box(-1.0, 1.0, (1,), np.float32)

    def get_default_action(self):
        return np.full(1, -1.0, dtype=np.float32)

    def send_control(self, control):
        self._rec("send", float(control[0]))

    def reset(self, seed=None, options=None):
        self._rec("reset")
        self.k = 0
        return [np.zeros(1, np.float32)], {"seed": seed}

    def get_obs_rew_terminated_info(self):
        self._rec("obs")
        self.clock.sleep(self.capture)
        self.k += 1
        if self.k == self.fail_at:
            raise OSError("device unplugged")
        return [np.full(1, self.k, np.float32)], float(self.k), self.k in self.terminate_at, {"k": self.k}

    def wait(self):
        self._rec("wait")

    def render(self):
        self._rec("render")
        return "frame"

    def close(self):
        self._rec("close")


def a(x):
    return np.full(1, x, dtype=np.float32)


def times(log, name):
    return [entry[1] for entry in log if entry[0] == name]


def sent(log):
    return [entry[3] for entry in log if entry[0] == "send"]


@pytest.fixture
def make_env():
    envs = []

    def make(env_id, clock=None, **overrides):
        clock = clock or FakeClock()
        log = []
        kwargs = {"clock": clock, "log": log, **overrides.pop("iface", {})}
        cfg = dict(
            DEFAULT_CONFIG_DICT,
            interface=Scripted,
            interface_kwargs=kwargs,
            time_step_duration=T,
            start_obs_capture=C,
            ep_max_length=1000,
        )
        cfg.update(overrides)
        env = gymnasium.make(env_id, config=cfg, clock=clock, disable_env_checker=True)
        envs.append(env)
        return env, clock, log

    yield make
    for env in envs:
        env.close()


def test_ids_registered_with_tmrl_names():
    for env_id in IDS + ["tmrl/real-time-gym-v1", "tmrl/real-time-gym-ts-v1"]:
        assert env_id in gymnasium.registry
    assert gymnasium.registry["tmrl/real-time-gym-ts-v1"].entry_point == "tmrl.realtime.env:RealTimeEnvTS"


@pytest.mark.parametrize("env_id", IDS)
def test_observation_space_is_interface_tuple_plus_action_buffer(make_env, env_id):
    env, _, _ = make_env(env_id, act_buf_len=3)
    box = spaces.Box(-1.0, 1.0, (1,), np.float32)
    assert env.observation_space == spaces.Tuple(
        (spaces.Box(-np.inf, np.inf, (1,), np.float32), box, box, box)
    )
    assert env.action_space == box
    env2, _, _ = make_env(env_id, act_in_obs=False)
    assert len(env2.observation_space.spaces) == 1


@pytest.mark.parametrize("env_id", IDS)
def test_cadence_capture_time_and_overlap(make_env, env_id):
    env, clock, log = make_env(env_id)
    obs, info = env.reset(seed=3)
    assert info == {"seed": 3}
    assert clock.now() == 0.0  # reset returns as soon as the first time step has started
    returns = []
    for i in range(1, 5):
        clock.sleep(0.01)  # inference, overlapping the running time step
        obs, rew, _, _, info = env.step(a(i / 10))
        returns.append(round(clock.now(), 9))
        assert obs[0][0] == i and rew == i and info == {"k": i}  # observed during the step that ended
    # step() returns exactly when the next time step starts, on the nominal grid
    assert returns == pytest.approx([0.05, 0.10, 0.15, 0.20])
    env.unwrapped.stop()  # let the running time step finish before reading the log
    assert times(log, "send") == pytest.approx([0.0, 0.05, 0.10, 0.15, 0.20])
    assert sent(log) == pytest.approx([-1.0, 0.1, 0.2, 0.3, 0.4])  # default action first
    assert times(log, "obs") == pytest.approx([0.03, 0.08, 0.13, 0.18, 0.23])


@pytest.mark.parametrize("env_id", IDS)
def test_elastic_clock_keeps_cadence_when_late_within_timeout(make_env, env_id):
    env, clock, log = make_env(env_id, time_step_timeout_factor=1.0)
    env.reset()
    with warnings.catch_warnings():
        warnings.simplefilter("error", TimeStepTimeoutWarning)
        clock.sleep(0.01)
        env.step(a(0.1))  # returns at 0.05
        clock.sleep(0.08)  # 0.13: 0.03 late for the step ending at 0.10, timeout is 0.05
        env.step(a(0.2))
        assert clock.now() == pytest.approx(0.13)  # the late time step started at 0.10, in the past
        env.step(a(0.3))  # next one on the grid again
        assert clock.now() == pytest.approx(0.15)
    env.unwrapped.stop()
    assert times(log, "send") == pytest.approx([0.0, 0.05, 0.13, 0.15])
    assert times(log, "obs") == pytest.approx([0.03, 0.08, 0.13, 0.18])


@pytest.mark.parametrize("env_id", IDS)
def test_elastic_clock_restarts_from_now_with_one_warning(make_env, env_id):
    env, clock, log = make_env(env_id, time_step_timeout_factor=0.5)
    env.reset()
    clock.sleep(0.01)
    env.step(a(0.1))  # 0.05; this time step ends at 0.10, timeout at 0.125
    clock.sleep(0.10)  # 0.15
    with pytest.warns(TimeStepTimeoutWarning) as record:
        env.step(a(0.2))
    assert len(record) == 1 and "time_step_timeout_factor" in str(record[0].message)
    assert clock.now() == pytest.approx(0.15)
    with warnings.catch_warnings():
        warnings.simplefilter("error", TimeStepTimeoutWarning)
        env.step(a(0.3))
        env.step(a(0.4))
    assert clock.now() == pytest.approx(0.25)  # new grid from 0.15
    env.unwrapped.stop()
    assert times(log, "send") == pytest.approx([0.0, 0.05, 0.15, 0.20, 0.25])


@pytest.mark.parametrize("env_id", IDS)
@pytest.mark.parametrize("factor", [0.5, 1.0])
def test_timeout_factor_decides_what_a_late_step_does(make_env, env_id, factor):
    # The same lateness, 0.6 of a time step, is within the timeout with factor 1.0 (the grid
    # keeps its cadence) and beyond it with 0.5 (the clock restarts from now, with a warning).
    env, clock, log = make_env(env_id, time_step_timeout_factor=factor)
    env.reset()
    clock.sleep(0.01)
    env.step(a(0.1))  # returns at 0.05; the running time step ends at 0.10
    clock.sleep(0.08)  # 0.13: 0.03 late
    with warnings.catch_warnings(record=True) as record:
        warnings.simplefilter("always", TimeStepTimeoutWarning)
        env.step(a(0.2))
        env.step(a(0.3))
    env.unwrapped.stop()
    late = [w for w in record if issubclass(w.category, TimeStepTimeoutWarning)]
    if factor == 1.0:
        assert not late
        assert times(log, "send") == pytest.approx([0.0, 0.05, 0.13, 0.15])
    else:
        assert len(late) == 1
        assert times(log, "send") == pytest.approx([0.0, 0.05, 0.13, 0.18])


@pytest.mark.parametrize("env_id", IDS)
def test_slow_capture_delays_step_but_not_the_grid(make_env, env_id):
    env, clock, log = make_env(env_id, iface={"capture": 0.04})  # captured at 0.03, done at 0.07
    env.reset()
    env.step(a(0.1))
    assert clock.now() == pytest.approx(0.07)
    env.step(a(0.2))  # that time step started on the grid (0.05): capture at 0.08, done at 0.12
    assert clock.now() == pytest.approx(0.12)
    env.unwrapped.stop()
    assert times(log, "obs") == pytest.approx([0.03, 0.08, 0.13])


@pytest.mark.parametrize("env_id", IDS)
def test_truncation_at_ep_max_length_and_step_after_done(make_env, env_id):
    env, _, log = make_env(env_id, ep_max_length=3)
    env.reset()
    flags = [env.step(a(0.0))[2:4] for _ in range(3)]
    assert flags == [(False, False), (False, False), (False, True)]
    assert len(times(log, "send")) == 3  # no time step started after the episode ended
    with pytest.raises(RuntimeError, match="reset"):
        env.step(a(0.0))
    with pytest.raises(UserError):
        env.step(a(0.0))
    env.reset()
    assert env.step(a(0.0))[2:4] == (False, False)


@pytest.mark.parametrize("env_id", IDS)
def test_terminated_overrides_truncated(make_env, env_id):
    env, _, _ = make_env(env_id, ep_max_length=2, iface={"terminate_at": (2,)})
    env.reset()
    env.step(a(0.0))
    _, _, terminated, truncated, _ = env.step(a(0.0))
    assert terminated is True and truncated is False


@pytest.mark.parametrize("env_id", IDS)
@pytest.mark.parametrize("wait_on_done", [True, False])
def test_wait_on_done(make_env, env_id, wait_on_done):
    env, _, log = make_env(env_id, wait_on_done=wait_on_done, iface={"terminate_at": (1,)})
    env.reset()
    assert env.step(a(0.0))[2] is True
    assert len(times(log, "wait")) == (1 if wait_on_done else 0)
    env, _, log = make_env(env_id, ep_max_length=2, wait_on_done=wait_on_done)
    env.reset()
    env.step(a(0.0))
    assert env.step(a(0.0))[3] is True
    assert len(times(log, "wait")) == (1 if wait_on_done else 0)


@pytest.mark.parametrize("env_id", IDS)
def test_no_warning_after_wait_and_thread_ownership(make_env, env_id):
    env, clock, log = make_env(env_id)
    env.reset()
    env.step(a(0.1))
    env.unwrapped.wait()
    clock.sleep(10.0)
    with warnings.catch_warnings():
        warnings.simplefilter("error", TimeStepTimeoutWarning)
        env.reset()
    assert clock.now() == pytest.approx(10.10)  # wait() let the running time step end at 0.10
    env.step(a(0.2))
    env.unwrapped.stop()
    assert times(log, "send")[-2:] == pytest.approx([10.10, 10.15])  # restarted from the reset
    threads = {name: {e[2] for e in log if e[0] == name} for name in ("reset", "wait", "send", "obs")}
    main = threading.current_thread().name
    assert len(threads["send"] | threads["obs"]) == 1 and main not in threads["send"]
    if env_id == "real-time-gym-v1":
        assert threads["reset"] == threads["wait"] == {main}
    else:
        assert threads["reset"] == threads["wait"] == threads["send"]


@pytest.mark.parametrize("env_id", IDS)
def test_action_buffer_oldest_first_and_reset_act_buf(make_env, env_id):
    env, _, _ = make_env(env_id, act_buf_len=3, reset_act_buf=True)
    obs, _ = env.reset()
    assert [float(x[0]) for x in obs[1:]] == [-1.0, -1.0, -1.0]
    env.step(a(0.1))
    obs, *_ = env.step(a(0.2))
    assert [float(x[0]) for x in obs[1:]] == pytest.approx([-1.0, 0.1, 0.2])
    obs, _ = env.reset()
    assert [float(x[0]) for x in obs[1:]] == [-1.0, -1.0, -1.0]
    assert env.unwrapped.default_action[0] == -1.0


@pytest.mark.parametrize("env_id", IDS)
@pytest.mark.parametrize("last_act_on_reset", [False, True])
def test_buffer_kept_across_episodes_without_reset_act_buf(make_env, env_id, last_act_on_reset):
    env, _, log = make_env(
        env_id, act_buf_len=3, reset_act_buf=False, ep_max_length=3, last_act_on_reset=last_act_on_reset
    )
    env.reset()
    for x in (0.1, 0.2, 0.3):
        env.step(a(x))  # the last one ends the episode: 0.3 is never applied
    obs, _ = env.reset()
    env.unwrapped.stop()
    expected_last = 0.3 if last_act_on_reset else -1.0
    assert [float(x[0]) for x in obs[1:]] == pytest.approx([0.1, 0.2, expected_last])
    assert sent(log)[-1] == pytest.approx(expected_last)  # the action reset() applies


@pytest.mark.parametrize("env_id", IDS)
def test_set_default_action_applies_at_next_reset(make_env, env_id):
    env, _, log = make_env(env_id)
    env.unwrapped.set_default_action(a(0.5))
    obs, _ = env.reset()
    env.unwrapped.stop()
    assert sent(log) == [0.5] and float(obs[-1][0]) == 0.5


@pytest.mark.parametrize("env_id", IDS)
def test_set_time_step_duration_and_capture(make_env, env_id):
    env, _, log = make_env(env_id)
    env.reset()
    env.step(a(0.1))  # 0.05
    env.unwrapped.set_time_step_duration(0.1)
    env.unwrapped.set_start_obs_capture(0.02)
    env.step(a(0.2))
    env.step(a(0.3))
    env.unwrapped.stop()
    assert times(log, "send") == pytest.approx([0.0, 0.05, 0.10, 0.20])
    assert times(log, "obs")[-2:] == pytest.approx([0.12, 0.22])


@pytest.mark.parametrize("env_id", IDS)
def test_polyak_benchmarks_are_exact_in_virtual_time(make_env, env_id):
    env, clock, _ = make_env(env_id, benchmark=True, benchmark_polyak=0.5, iface={"capture": 0.002})
    env.reset()
    for _ in range(6):
        clock.sleep(0.01)
        env.step(a(0.0))
    b = env.unwrapped.benchmarks()
    assert set(b) == {
        "time_step_duration",
        "step_duration",
        "join_duration",
        "inference_duration",
        "send_control_duration",
        "get_obs_duration",
    }
    assert b["time_step_duration"] == pytest.approx((T, 0.0))
    assert b["inference_duration"] == pytest.approx((0.01, 0.0))
    assert b["get_obs_duration"] == pytest.approx((0.002, 0.0))
    assert b["step_duration"][0] == pytest.approx(T - 0.01)


@pytest.mark.parametrize("env_id", IDS)
def test_trace_benchmark_and_disabled_benchmark(make_env, env_id):
    env, _, _ = make_env(env_id, benchmark=True, benchmark_type="trace")
    env.reset()
    for _ in range(4):
        env.step(a(0.0))
    env.unwrapped.stop()
    trace = env.unwrapped.benchmarks()
    assert np.allclose(trace["deltas"]["time_step_duration"], T)
    assert len(trace["clock"]["start_send_control"]) == 5
    env2, _, _ = make_env(env_id)
    with pytest.raises(AssertionError, match="benchmark"):
        env2.unwrapped.benchmarks()


@pytest.mark.parametrize("env_id", IDS)
def test_render_runs_on_caller_thread(make_env, env_id):
    env, _, log = make_env(env_id)
    env.reset()
    assert env.unwrapped.render() == "frame"
    assert env.unwrapped.render(join_thread=True) == "frame"
    assert {e[2] for e in log if e[0] == "render"} == {threading.current_thread().name}
    env.step(a(0.0))  # the joined time step's observation is still delivered
    assert env.unwrapped.current_step == 1


@pytest.mark.parametrize("env_id", IDS)
def test_interface_error_reaches_the_caller(make_env, env_id):
    env, _, _ = make_env(env_id, iface={"fail_at": 2})
    env.reset()
    env.step(a(0.0))
    with pytest.raises(OSError, match="unplugged"):
        env.step(a(0.0))
    with pytest.raises(RuntimeError):
        env.step(a(0.0))
    env.reset()  # a new episode works
    env.step(a(0.0))


@pytest.mark.parametrize("env_id", IDS)
def test_close_stops_every_thread_and_closes_interface(env_id):
    before = set(threading.enumerate())
    clock, log = FakeClock(), []
    cfg = dict(DEFAULT_CONFIG_DICT, interface=Scripted, interface_kwargs={"clock": clock, "log": log})
    env = gymnasium.make(env_id, config=cfg, clock=clock)
    env.reset()
    env.step(a(0.0))  # a time step is running while we close
    assert set(threading.enumerate()) - before
    env.close()
    env.close()  # idempotent
    assert set(threading.enumerate()) == before
    assert times(log, "close") and len([e for e in log if e[0] == "close"]) == 1
    with pytest.raises(UserError, match="closed"):
        env.unwrapped.reset()


@pytest.mark.parametrize("env_id", IDS)
def test_env_dropped_without_close_stops_its_thread(env_id):
    clock = FakeClock()
    cfg = dict(DEFAULT_CONFIG_DICT, interface=Scripted, interface_kwargs={"clock": clock, "log": []})
    env = gymnasium.make(env_id, config=cfg, clock=clock)
    env.reset()
    env.step(a(0.0))
    thread = env.unwrapped._thread
    assert thread.is_alive()
    del env
    gc.collect()
    thread.join(timeout=30)
    assert not thread.is_alive()


class DuckTyped:
    """No base class, no wait(), render() or close(): still an interface."""

    def get_observation_space(self):
        return spaces.Tuple((spaces.Discrete(5),))

    def get_action_space(self):
        return spaces.Discrete(2)

    def get_default_action(self):
        return 0

    def send_control(self, control):
        self.last = control

    def reset(self, seed=None, options=None):
        return [0], {}

    def get_obs_rew_terminated_info(self):
        return [1], 0.0, False, {}


@pytest.mark.parametrize("env_id", IDS)
def test_duck_typed_interface(env_id):
    clock = FakeClock()
    env = gymnasium.make(
        env_id, config=dict(DEFAULT_CONFIG_DICT, interface=DuckTyped, ep_max_length=2), clock=clock
    )
    try:
        assert env.reset()[0] == (0, 0)
        assert env.step(1)[0] == (1, 1)
        _, _, terminated, truncated, _ = env.step(0)
        assert (terminated, truncated) == (False, True)
        env.unwrapped.wait()
        assert env.unwrapped.render() is None
    finally:
        env.close()


def test_ts_interface_constructor_error_leaves_no_thread():
    before = set(threading.enumerate())
    clock = FakeClock()
    cfg = dict(
        DEFAULT_CONFIG_DICT,
        interface=Scripted,
        interface_kwargs={"clock": clock, "log": [], "fail_init": True},
    )
    with pytest.raises(ValueError, match="no device"):
        rt.RealTimeEnvTS(cfg, clock=clock)
    with pytest.raises(ValueError, match="no device"):
        rt.RealTimeEnv(cfg, clock=clock)
    assert set(threading.enumerate()) == before


@pytest.mark.parametrize(
    "bad, match",
    [
        ({"interface": None}, "interface"),
        ({"act_buf_len": 0}, "act_buf_len"),
        ({"time_step_duration": -1}, "time_step_duration"),
        ({"ep_max_length": 0}, "ep_max_length"),
        ({"benchmark_type": "fancy"}, "benchmark_type"),
        ({"interface_kwargs": [1]}, "interface_kwargs"),
    ],
)
def test_config_mistakes_are_user_errors(bad, match):
    clock = FakeClock()
    cfg = dict(DEFAULT_CONFIG_DICT, interface=Scripted, interface_kwargs={"clock": clock, "log": []})
    cfg.update(bad)
    with pytest.raises(UserError, match=match) as err:
        rt.RealTimeEnv(cfg, clock=clock)
    assert "\n" not in str(err.value)


def test_default_config_is_never_mutated():
    snapshot = dict(DEFAULT_CONFIG_DICT)
    clock = FakeClock()
    cfg = dict(DEFAULT_CONFIG_DICT, interface=Scripted, interface_kwargs={"clock": clock, "log": []})
    env = rt.RealTimeEnv(cfg, clock=clock)
    env.close()
    rt.drone_config(time_step_duration=0.02)
    assert DEFAULT_CONFIG_DICT == snapshot
    assert DEFAULT_CONFIG_DICT["interface"] is RealTimeGymInterface


def test_prepro_hooks_as_in_rtgym():
    clock, log = FakeClock(), []
    cfg = dict(
        DEFAULT_CONFIG_DICT,
        interface=Scripted,
        interface_kwargs={"clock": clock, "log": log},
        act_prepro_func=lambda act: act * 2,
        obs_prepro_func=lambda obs: [o + 100 for o in obs],
    )
    env = rt.RealTimeEnv(cfg, clock=clock)
    try:
        obs, _ = env.reset()
        # at reset the hook sees the buffer too; in step() only the interface's part
        assert float(obs[0][0]) == 100 and float(obs[1][0]) == 99
        obs, *_ = env.step(a(0.25))
        assert float(obs[0][0]) == 101 and float(obs[1][0]) == 0.25
        env.stop()
        assert sent(log) == pytest.approx([-2.0, 0.5])
    finally:
        env.close()


def test_import_registers_ids_and_touches_nothing(tmp_path):
    code = (
        "import gymnasium, os\n"
        "assert 'real-time-gym-v1' not in gymnasium.registry\n"
        "import tmrl.realtime, tmrl.envs\n"
        "assert 'real-time-gym-v1' in gymnasium.registry\n"
        "print(sorted(os.listdir('.')))\n"
    )
    out = subprocess.run(
        [sys.executable, "-c", code], cwd=tmp_path, capture_output=True, text=True, check=True
    )
    assert out.stdout.strip() == "[]"
    assert not (tmp_path / "TmrlData").exists()


# the step observer ------------------------------------------------------------------------------
EVENTS = (
    "on_reset_start",
    "on_reset_joined",
    "on_reset_end",
    "on_step_start",
    "on_step_joined",
    "on_step_end",
    "on_send_control_start",
    "on_send_control_end",
    "on_obs_capture_start",
    "on_obs_captured",
)


def _recording(name):
    def hook(self, t):
        self.calls.append((name, threading.current_thread().name, round(t, 9)))
        getattr(BenchmarkObserver, name)(self, t)

    return hook


class RecordingObserver(BenchmarkObserver):
    """A BenchmarkObserver that also records (event, thread, time) for every call."""

    def __init__(self, benchmark):
        super().__init__(benchmark)
        self.calls = []


for _name in EVENTS:
    setattr(RecordingObserver, _name, _recording(_name))


class ObservedEnv(rt.RealTimeEnv):
    def _make_observer(self):
        return RecordingObserver(self.bench)


class ObservedEnvTS(rt.RealTimeEnvTS):
    def _make_observer(self):
        return RecordingObserver(self.bench)


def scripted_config(clock, log, **overrides):
    cfg = dict(
        DEFAULT_CONFIG_DICT,
        interface=Scripted,
        interface_kwargs={"clock": clock, "log": log},
        time_step_duration=T,
        start_obs_capture=C,
    )
    cfg.update(overrides)
    return cfg


@pytest.mark.parametrize("env_cls", [ObservedEnv, ObservedEnvTS])
def test_benchmark_observer_gets_its_calls_in_order(env_cls):
    clock = FakeClock()
    env = env_cls(scripted_config(clock, [], benchmark=True), clock=clock)
    try:
        env.reset()
        for _ in range(2):
            clock.sleep(0.01)
            env.step(a(0.0))
        env.stop()
        calls = env.observer.calls
    finally:
        env.close()
    main = threading.current_thread().name
    caller = [(name, t) for name, thread, t in calls if thread == main]
    worker = [(name, t) for name, thread, t in calls if thread != main]
    assert caller == [
        ("on_reset_start", 0.0),
        ("on_reset_joined", 0.0),
        ("on_reset_end", 0.0),
        ("on_step_start", 0.01),
        ("on_step_joined", pytest.approx(C)),  # the observation is in; step() then waits for 0.05
        ("on_step_end", pytest.approx(0.05)),
        ("on_step_start", pytest.approx(0.06)),
        ("on_step_joined", pytest.approx(T + C)),
        ("on_step_end", pytest.approx(0.10)),
    ]
    expected_worker = []
    for start in (0.0, 0.05, 0.10):
        expected_worker += [
            ("on_send_control_start", pytest.approx(start)),
            ("on_send_control_end", pytest.approx(start)),
            ("on_obs_capture_start", pytest.approx(start + C)),
            ("on_obs_captured", pytest.approx(start + C)),
        ]
    assert worker == expected_worker
    # the observer feeds the benchmark that benchmarks() reads
    assert env.observer.benchmark is env.bench
    assert env.benchmarks()["time_step_duration"] == pytest.approx((T, 0.0))
    assert env.benchmarks()["inference_duration"] == pytest.approx((0.01, 0.0))


def test_without_benchmark_the_env_calls_a_no_op_observer(monkeypatch):
    counts = {name: 0 for name in EVENTS}

    def counting(name):
        def hook(self, t):
            counts[name] += 1

        return hook

    for name in EVENTS:
        monkeypatch.setattr(NullObserver, name, counting(name))
    clock = FakeClock()
    env = rt.RealTimeEnv(scripted_config(clock, []), clock=clock)
    try:
        assert type(env.observer) is NullObserver
        env.reset()
        for _ in range(3):
            env.step(a(0.0))
        env.stop()
        with pytest.raises(rt.BenchmarkDisabledError):
            env.benchmarks()
    finally:
        env.close()
    assert counts == {
        **{name: 1 for name in EVENTS if name.startswith("on_reset")},
        **{name: 3 for name in EVENTS if name.startswith("on_step")},
        **{name: 4 for name in EVENTS[6:]},
    }
    clock = FakeClock()
    bench_env = rt.RealTimeEnv(scripted_config(clock, [], benchmark=True), clock=clock)
    try:
        assert (
            type(bench_env.observer) is BenchmarkObserver and bench_env.observer.benchmark is bench_env.bench
        )
    finally:
        bench_env.close()


def test_null_observer_fits_the_protocol():
    for name in EVENTS:
        assert callable(getattr(StepObserver, name))
        assert getattr(NullObserver(), name)(1.0) is None


# messages of the time-step thread ----------------------------------------------------------------
def test_time_step_thread_speaks_typed_messages():
    clock, log = FakeClock(), []
    runner = TimeStepRunner(clock, NullObserver(), None, None)
    runner.interface = Scripted(clock, log)
    thread = threading.Thread(target=runner.loop, args=(0.0,), daemon=True)
    thread.start()
    try:
        runner.jobs.put(StartTimeStep(a(0.5), 0.0, C, T))
        first = runner.results.get(timeout=30)
        assert isinstance(first, Observed)
        assert first.obs[0][0] == 1 and first.rew == 1.0 and first.terminated is False
        assert first.info == {"k": 1} and first.capture_end == pytest.approx(C)
        # chained: starts at the end of the previous time step although step() came earlier
        runner.jobs.put(ChainTimeStep(a(0.2), 0.01, False, T, C, T))
        second = runner.results.get(timeout=30)
        assert isinstance(second, Observed) and second.capture_end == pytest.approx(T + C)
        runner.jobs.put(ChainTimeStep(a(0.3), 0.1, True, T, C, T))  # truncating: nothing starts
        runner.jobs.put(CallInterface(lambda itf: itf.k))
        assert runner.results.get(timeout=30) == Returned(2)
        runner.jobs.put(CallInterface(lambda itf: itf.get_obs_rew_terminated_info()["nope"]))
        failed = runner.results.get(timeout=30)
        assert isinstance(failed, Raised) and isinstance(failed.error, TypeError)
        runner.jobs.put(("call", lambda itf: itf.k))  # an untyped message is refused, not run
        refused = runner.results.get(timeout=30)
        assert isinstance(refused, Raised) and "unknown job" in str(refused.error)
        runner.jobs.put(StopThread())
        assert runner.results.get(timeout=30) == Returned(None)
        thread.join(timeout=30)
        assert not thread.is_alive()
    finally:
        runner.jobs.put(StopThread())
    assert sent(log) == pytest.approx([0.5, 0.2])
    assert times(log, "send") == pytest.approx([0.0, T])
    with pytest.raises(dataclasses.FrozenInstanceError):
        first.rew = 2.0  # type: ignore[misc]


def test_env_sends_typed_jobs(monkeypatch):
    seen = []
    original = TimeStepRunner.run

    def spy(self, job, last):
        seen.append(type(job).__name__)
        return original(self, job, last)

    monkeypatch.setattr(TimeStepRunner, "run", spy)
    clock = FakeClock()
    env = rt.RealTimeEnvTS(scripted_config(clock, [], ep_max_length=2), clock=clock)
    try:
        env.reset()
        env.step(a(0.0))
        env.step(a(0.0))  # truncates
    finally:
        env.close()
    assert seen == [
        "CallInterface",  # build the interface
        "CallInterface",  # reset
        "StartTimeStep",
        "ChainTimeStep",
        "ChainTimeStep",  # the truncating step: nothing starts
        "CallInterface",  # close
    ]
