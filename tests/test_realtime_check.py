"""check_realtime_interface: each kind of mistake is reported in plain words."""

from __future__ import annotations

import ast
import inspect

import numpy as np
import pytest
from gymnasium import spaces

from tmrl.errors import UserError
from tmrl.realtime import DEFAULT_CONFIG_DICT, FakeClock, RealTimeGymInterface, check_realtime_interface
from tmrl.realtime import check as check_mod

CLOCK = FakeClock()


class Good(RealTimeGymInterface):
    capture = 0.0  # virtual seconds spent capturing
    control = 0.0  # virtual seconds spent sending a control

    def __init__(self):
        self.closed = False

    def get_observation_space(self):
        return spaces.Tuple((spaces.Box(-1.0, 1.0, (2,), np.float32), spaces.Discrete(3)))

    def get_action_space(self):
        return spaces.Box(-1.0, 1.0, (1,), np.float32)

    def get_default_action(self):
        return np.zeros(1, np.float32)

    def send_control(self, control):
        CLOCK.sleep(self.control)

    def obs(self):
        return [np.zeros(2, np.float32), 1]

    def reset(self, seed=None, options=None):
        return self.obs(), {}

    def get_obs_rew_terminated_info(self):
        CLOCK.sleep(self.capture)
        return self.obs(), 0.5, False, {}

    def close(self):
        self.closed = True


def check(interface, **config):
    cfg = dict(DEFAULT_CONFIG_DICT, interface=interface, **config)
    return check_realtime_interface(cfg, n_steps=3, clock=CLOCK)


def only(problems, *words):
    assert len(problems) == 1, problems
    for w in words:
        assert w in problems[0], problems
    return problems[0]


def test_good_interface_has_no_problem():
    assert check(Good) == []
    assert check_realtime_interface(Good, n_steps=2, clock=CLOCK) == []


def test_instance_is_checked_and_not_closed():
    itf = Good()
    assert check_realtime_interface(itf, n_steps=2, clock=CLOCK) == []
    assert not itf.closed


def test_missing_and_unimplemented_methods():
    class NoSend:
        def __getattr__(self, name):
            if name == "send_control":
                raise AttributeError(name)
            return getattr(Good(), name)

    only(check(NoSend), "no method send_control")

    class NoDefault(Good):
        def get_default_action(self):
            raise NotImplementedError

    only(check(NoDefault), "get_default_action", "not implemented")


def test_observation_space_not_a_tuple():
    class Flat(Good):
        def get_observation_space(self):
            return spaces.Box(-1, 1, (2,))

    only(check(Flat), "get_observation_space", "Tuple")


def test_default_action_outside_action_space():
    class Far(Good):
        def get_default_action(self):
            return np.full(1, 5.0, np.float32)

    only(check(Far), "default action", "outside the bounds")

    class Shape(Good):
        def get_default_action(self):
            return np.zeros(2, np.float32)

    only(check(Shape), "default action", "shape (2,)")


def test_reset_observation_count_and_elements():
    class WithBuffer(Good):
        def reset(self, seed=None, options=None):
            return self.obs() + [np.zeros(1, np.float32)], {}

    only(check(WithBuffer), "reset()", "3 observation elements", "declares 2", "action buffer")

    class WrongDtype(Good):
        def reset(self, seed=None, options=None):
            return [np.zeros(2, np.complex128), 1], {}

    only(check(WrongDtype), "reset()", "element 0", "dtype complex128")

    class OutOfBounds(Good):
        def reset(self, seed=None, options=None):
            return [np.full(2, 3.0, np.float32), 1], {}

    only(check(OutOfBounds), "element 0", "outside the bounds")

    class NotPair(Good):
        def reset(self, seed=None, options=None):
            return self.obs()

    only(check(NotPair), "reset() must return a pair")

    class InfoList(Good):
        def reset(self, seed=None, options=None):
            return self.obs(), []

    only(check(InfoList), "reset()", "info", "dict")


def test_step_results():
    class Three(Good):
        def get_obs_rew_terminated_info(self):
            return self.obs(), 0.0, False

    only(check(Three), "4-tuple")

    class BadObs(Good):
        def get_obs_rew_terminated_info(self):
            return [np.zeros(3, np.float32), 1], 0.0, False, {}

    only(check(BadObs), "get_obs_rew_terminated_info()", "element 0", "shape (3,)")

    class ArrayReward(Good):
        def get_obs_rew_terminated_info(self):
            return self.obs(), np.zeros(2), False, {}

    only(check(ArrayReward), "reward", "float")

    class IntTerminated(Good):
        def get_obs_rew_terminated_info(self):
            return self.obs(), 0.0, 0, {}

    only(check(IntTerminated), "terminated", "bool")

    class NoneInfo(Good):
        def get_obs_rew_terminated_info(self):
            return self.obs(), 0.0, False, None

    only(check(NoneInfo), "info", "dict")


def test_capture_slower_than_time_step():
    class Slow(Good):
        capture = 0.08

    only(check(Slow, time_step_duration=0.05, start_obs_capture=0.05), "80.0 ms", "longer than the time step")


def test_capture_start_plus_duration_beyond_timeout():
    class Slowish(Good):
        capture = 0.04

    only(
        check(Slowish, time_step_duration=0.05, start_obs_capture=0.05, time_step_timeout_factor=0.5),
        "start_obs_capture + capture",
        "time out",
    )


def test_slow_control_makes_steps_time_out():
    class SlowControl(Good):
        control = 0.2

    only(check(SlowControl, time_step_duration=0.05), "timed out")


def test_config_problems():
    only(check(Good, start_obs_capture=0.08, time_step_duration=0.05), "start_obs_capture", "after the end")
    only(check(Good, wait_on_done=True, reset_act_buf=False), "wait_on_done", "reset_act_buf")
    only(check(Good, act_buf_len=0), "act_buf_len")


def test_constructor_and_method_errors():
    class Broken(Good):
        def __init__(self):
            raise OSError("port busy")

    only(check(Broken), "building the interface", "port busy")

    class Raises(Good):
        def send_control(self, control):
            raise ValueError("bad control")

    assert any("send_control() raised ValueError: bad control" in p for p in check(Raises))


def test_raise_on_problem_gives_one_line():
    class Far(Good):
        def get_default_action(self):
            return np.full(1, 5.0, np.float32)

    with pytest.raises(UserError, match="default action") as err:
        check_realtime_interface(dict(DEFAULT_CONFIG_DICT, interface=Far), clock=CLOCK, raise_on_problem=True)
    assert "\n" not in str(err.value)


# the public checks, each called alone ------------------------------------------------------------
OBS_SPACE = Good().get_observation_space()
CFG = dict(DEFAULT_CONFIG_DICT, interface=Good)


def one_line(problems, *words):
    problem = only(problems, *words)
    assert "\n" not in problem
    return problem


def test_check_config_alone():
    assert check_mod.check_config(CFG) == []
    one_line(check_mod.check_config(dict(CFG, act_buf_len=0)), "act_buf_len")
    one_line(
        check_mod.check_config(dict(CFG, start_obs_capture=0.08, time_step_duration=0.05)), "after the end"
    )
    one_line(check_mod.check_config({"interface": None}), "no interface")


def test_check_methods_alone():
    assert check_mod.check_methods(Good()) == []

    class NoCapture:
        def __getattr__(self, name):
            if name == "get_obs_rew_terminated_info":
                raise AttributeError(name)
            return getattr(Good(), name)

    one_line(check_mod.check_methods(NoCapture()), "no method get_obs_rew_terminated_info()")


def test_check_spaces_alone():
    assert check_mod.check_spaces(Good()) == []

    class Far(Good):
        def get_default_action(self):
            return np.full(1, 5.0, np.float32)

    one_line(check_mod.check_spaces(Far()), "default action", "outside the bounds")

    class NotASpace(Good):
        def get_action_space(self):
            return (-1.0, 1.0)

    one_line(check_mod.check_spaces(NotASpace()), "get_action_space()", "gymnasium space")


def test_check_obs_alone():
    assert check_mod.check_obs(Good().obs(), OBS_SPACE, "reset()") == []
    one_line(
        check_mod.check_obs([np.zeros(3, np.float32), 1], OBS_SPACE, "reset()"), "element 0", "shape (3,)"
    )
    one_line(check_mod.check_obs([np.zeros(2, np.float32), 7], OBS_SPACE, "mine()"), "mine()", "element 1")
    one_line(check_mod.check_obs({"a": 1}, OBS_SPACE, "reset()"), "dict", "return a list")


def test_check_reset_alone():
    assert check_mod.check_reset(Good(), OBS_SPACE) == []

    class Nan(Good):
        def reset(self, seed=None, options=None):
            return [np.full(2, np.nan, np.float32), 1], {}

    one_line(check_mod.check_reset(Nan(), OBS_SPACE), "reset()", "NaN")

    class NotPair(Good):
        def reset(self, seed=None, options=None):
            return self.obs()

    one_line(check_mod.check_reset(NotPair(), OBS_SPACE), "must return a pair")


def test_check_send_control_alone():
    assert check_mod.check_send_control(Good(), np.zeros(1, np.float32)) == []

    class Raises(Good):
        def send_control(self, control):
            raise ValueError("bad control")

    one_line(
        check_mod.check_send_control(Raises(), np.zeros(1, np.float32)), "send_control() raised ValueError"
    )


def test_check_step_result_alone():
    assert check_mod.check_step_result(Good().get_obs_rew_terminated_info(), OBS_SPACE) == []
    one_line(check_mod.check_step_result((Good().obs(), 0.0, False), OBS_SPACE), "4-tuple")
    one_line(check_mod.check_step_result((Good().obs(), 0.0, "no", {}), OBS_SPACE), "terminated", "bool")
    bad_obs = ([np.zeros(2, np.float64) + 9, 1], 0.0, False, {})
    one_line(check_mod.check_step_result(bad_obs, OBS_SPACE), "get_obs_rew_terminated_info()", "element 0")


def test_check_capture_timing_alone():
    assert check_mod.check_capture_timing(0.01, {"time_step_duration": 0.05, "start_obs_capture": 0.03}) == []
    one_line(check_mod.check_capture_timing(0.08, {"time_step_duration": 0.05}), "80.0 ms", "longer than")
    late = {"time_step_duration": 0.05, "start_obs_capture": 0.05, "time_step_timeout_factor": 0.5}
    one_line(check_mod.check_capture_timing(0.04, late), "start_obs_capture + capture", "time out")


def test_check_capture_alone_calls_and_times_the_capture():
    class Counting(Good):
        calls = 0

        def get_obs_rew_terminated_info(self):
            self.calls += 1
            return super().get_obs_rew_terminated_info()

    itf = Counting()
    assert check_mod.check_capture(itf, OBS_SPACE, CFG, clock=CLOCK) == []
    assert itf.calls == 3

    class Slow(Good):
        capture = 0.08

    one_line(
        check_mod.check_capture(Slow(), OBS_SPACE, dict(CFG, time_step_duration=0.05), clock=CLOCK), "80.0 ms"
    )

    class Fails(Good):
        def get_obs_rew_terminated_info(self):
            raise OSError("camera gone")

    one_line(check_mod.check_capture(Fails(), OBS_SPACE, CFG, clock=CLOCK), "OSError: camera gone")


def test_check_interface_alone_never_closes():
    itf = Good()
    assert check_mod.check_interface(itf, CFG, clock=CLOCK) == []
    assert not itf.closed

    class BadObs(Good):
        def get_obs_rew_terminated_info(self):
            return [np.zeros(3, np.float32), 1], 0.0, False, {}

    one_line(check_mod.check_interface(BadObs(), CFG, clock=CLOCK), "element 0", "shape (3,)")


def test_check_env_steps_alone():
    assert check_mod.check_env_steps(CFG, n_steps=3, clock=CLOCK) == []

    class SlowControl(Good):
        control = 0.2

    cfg = dict(CFG, interface=SlowControl, time_step_duration=0.05)
    one_line(check_mod.check_env_steps(cfg, n_steps=3, clock=CLOCK), "timed out")

    class Drifting(Good):
        k = 0

        def get_obs_rew_terminated_info(self):
            self.k += 1
            return [np.full(2, 2 * self.k, np.float32), 1], 0.0, False, {}  # out of bounds from step 1 on

    one_line(
        check_mod.check_env_steps(dict(CFG, interface=Drifting), clock=CLOCK), "step 1", "observation space"
    )


def test_check_module_imports_no_private_name():
    tree = ast.parse(inspect.getsource(check_mod))
    private = [
        (node.module, alias.name)
        for node in ast.walk(tree)
        if isinstance(node, ast.ImportFrom)
        for alias in node.names
        if alias.name.startswith("_")
    ]
    assert private == []
