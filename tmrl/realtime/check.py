"""``check_realtime_interface``: find the usual integration mistakes of a real-time interface.

It builds the interface, calls each method once on the caller's thread, compares what comes back
with the declared spaces, times the observation capture against the time step, and finally runs a
few steps of the real environment. Every problem is reported as one plain sentence.

As in :mod:`gymnasium.utils.env_checker`, the steps are public functions that can be called alone;
each returns the problems it found (an empty list when all is well):

* :func:`check_config`: the config's values and combinations;
* :func:`check_interface`: everything about an interface object, in this order (it stops where a
  problem makes the next checks meaningless): :func:`check_methods`, :func:`check_spaces`,
  :func:`check_reset`, :func:`check_send_control`, :func:`check_capture` (which uses
  :func:`check_step_result` and :func:`check_capture_timing`);
* :func:`check_obs`: one observation against the interface's observation space;
* :func:`check_env_steps`: a few steps of the real environment.
"""

from __future__ import annotations

import logging
import numbers
import warnings
from collections.abc import Mapping
from typing import Any

import numpy as np
from gymnasium import spaces

from tmrl.errors import UserError
from tmrl.realtime.clock import Clock, PerfCounterClock
from tmrl.realtime.env import RealTimeEnv, TimeStepTimeoutWarning, read_config
from tmrl.realtime.interface import DEFAULT_CONFIG_DICT

__all__ = [
    "REQUIRED_METHODS",
    "check_capture",
    "check_capture_timing",
    "check_config",
    "check_env_steps",
    "check_interface",
    "check_methods",
    "check_obs",
    "check_realtime_interface",
    "check_reset",
    "check_send_control",
    "check_spaces",
    "check_step_result",
]

logger = logging.getLogger(__name__)

REQUIRED_METHODS = (
    "send_control",
    "reset",
    "get_obs_rew_terminated_info",
    "get_observation_space",
    "get_action_space",
    "get_default_action",
)
"""The methods every interface must have."""


class _Borrowed:
    """Forwards everything to a caller's interface object except ``close``, which stays theirs."""

    def __init__(self, target: Any) -> None:
        self._target = target

    def __getattr__(self, name: str) -> Any:
        if name == "close":
            raise AttributeError(name)
        return getattr(self._target, name)


def _mismatch(space: spaces.Space, x: Any) -> str | None:
    """Why ``x`` is not an element of ``space`` (None when it is)."""
    try:
        if space.contains(x):
            return None
    except Exception:  # noqa: BLE001, S110  (a malformed value can make contains() itself fail)
        pass
    if isinstance(space, spaces.Box):
        if not isinstance(x, np.ndarray):
            return f"is a {type(x).__name__}, expected a numpy array of shape {space.shape} and dtype {space.dtype}"
        if x.shape != space.shape:
            return f"has shape {x.shape}, expected {space.shape}"
        if not np.can_cast(x.dtype, space.dtype):
            return f"has dtype {x.dtype}, expected {space.dtype}"
        if np.any(np.isnan(x)):
            return "contains NaN"
        return f"is outside the bounds [{space.low.min()}, {space.high.max()}] (min {x.min()}, max {x.max()})"
    return f"is not an element of {space}"


def _call(instance: Any, name: str, problems: list[str], *args: Any, **kwargs: Any) -> tuple[bool, Any]:
    """Call ``instance.name(*args, **kwargs)``; on an exception, add the problem to ``problems``.

    Returns:
        ``(True, result)``, or ``(False, None)`` when the call raised.
    """
    try:
        return True, getattr(instance, name)(*args, **kwargs)
    except NotImplementedError:
        problems.append(
            f"{name}() is not implemented (it raises NotImplementedError): override it in your interface"
        )
    except Exception as err:  # noqa: BLE001  (reported, whatever it is)
        problems.append(f"{name}() raised {type(err).__name__}: {err}")
    return False, None


def _with_defaults(config: Mapping[str, Any]) -> dict[str, Any]:
    return {**DEFAULT_CONFIG_DICT, **config}


# the config ------------------------------------------------------------------------------------
def _config_combinations(cfg: Mapping[str, Any]) -> list[str]:
    """Problems of valid values that do not go together (``cfg`` completed with the defaults)."""
    problems: list[str] = []
    T, soc = float(cfg["time_step_duration"]), float(cfg["start_obs_capture"])
    if soc > T:
        problems.append(
            f"start_obs_capture ({soc} s) is after the end of the time step ({T} s): step() would return late "
            "every time; set start_obs_capture <= time_step_duration"
        )
    if cfg["wait_on_done"] and not cfg["reset_act_buf"]:
        problems.append(
            "wait_on_done is set but reset_act_buf is False: after the pause the action buffer holds actions "
            "that are no longer applied; set reset_act_buf to True"
        )
    return problems


def check_config(config: Mapping[str, Any]) -> list[str]:
    """Check a real-time config without building its interface.

    Args:
        config: a real-time config (missing keys take their default).

    Returns:
        The reason :class:`~tmrl.realtime.RealTimeEnv` would reject it (alone), or else the
        values that do not go together (e.g. ``start_obs_capture`` after the end of the time step).
    """
    try:
        cfg = read_config(config)
    except UserError as err:
        return [str(err)]
    return _config_combinations(cfg)


# the interface ---------------------------------------------------------------------------------
def check_methods(interface: Any) -> list[str]:
    """Check that ``interface`` has every method of :data:`REQUIRED_METHODS` (calls none).

    Returns:
        One problem per missing method.
    """
    return [
        f"the interface has no method {m}()"
        for m in REQUIRED_METHODS
        if not callable(getattr(interface, m, None))
    ]


def _read_spaces(interface: Any, problems: list[str]) -> tuple[spaces.Tuple, spaces.Space, Any] | None:
    """``(observation_space, action_space, default_action)`` of ``interface``, adding what is wrong
    with them to ``problems``; None when they cannot be used for the next checks."""
    ok, obs_space = _call(interface, "get_observation_space", problems)
    if ok and not isinstance(obs_space, spaces.Tuple):
        problems.append(
            f"get_observation_space() returned a {type(obs_space).__name__}: return a gymnasium.spaces.Tuple"
        )
        ok = False
    ok_a, act_space = _call(interface, "get_action_space", problems)
    if ok_a and not isinstance(act_space, spaces.Space):
        problems.append(f"get_action_space() returned a {type(act_space).__name__}: return a gymnasium space")
        ok_a = False
    ok_d, default = _call(interface, "get_default_action", problems)
    if ok_a and ok_d:
        why = _mismatch(act_space, default)
        if why:
            problems.append(f"the default action {why}: it must be in the action space {act_space}")
    if not (ok and ok_a and ok_d):
        return None
    return obs_space, act_space, default


def check_spaces(interface: Any) -> list[str]:
    """Check ``get_observation_space()`` (a ``Tuple``), ``get_action_space()`` (a space) and
    ``get_default_action()`` (in the action space): one call each.

    Args:
        interface: the interface object (a :class:`~tmrl.realtime.RealTimeGymInterface`).

    Returns:
        One problem per wrong or failing method (empty when all three are right).
    """
    problems: list[str] = []
    _read_spaces(interface, problems)
    return problems


def check_obs(obs: Any, observation_space: spaces.Tuple, method_name: str) -> list[str]:
    """Check an observation that an interface method returned: a list or tuple with one element
    per space of ``observation_space``, each an element of its space.

    Args:
        obs: the observation returned.
        observation_space: the interface's observation space (without the action buffer).
        method_name: the method that returned it, named in the problems (e.g. ``"reset()"``).

    Returns:
        One problem per wrong element (or one for a wrong type or length).
    """
    if not isinstance(obs, (list, tuple)):
        return [f"{method_name} returned an observation of type {type(obs).__name__}: return a list"]
    n = len(observation_space.spaces)
    if len(obs) != n:
        why = (
            f"{method_name} returned {len(obs)} observation elements but get_observation_space() declares {n} "
            "(do not put the action buffer in the observation: the environment appends it)"
        )
        return [why]
    problems = []
    for i, (sub, x) in enumerate(zip(observation_space.spaces, obs)):
        why = _mismatch(sub, x)
        if why:
            problems.append(f"{method_name}: observation element {i} {why} (space: {sub})")
    return problems


def _info_problem(method_name: str, info: Any) -> list[str]:
    if isinstance(info, dict):
        return []
    return [f"{method_name} returned info of type {type(info).__name__}: return a dict"]


def _check_reset(interface: Any, observation_space: spaces.Tuple, problems: list[str]) -> bool:
    """:func:`check_reset` adding to ``problems``; False when reset() did not return a pair."""
    ok, res = _call(interface, "reset", problems, seed=None, options=None)
    if not ok:
        return True
    if not (isinstance(res, tuple) and len(res) == 2):
        problems.append("reset() must return a pair (obs, info)")
        return False
    problems += check_obs(res[0], observation_space, "reset()")
    problems += _info_problem("reset()", res[1])
    return True


def check_reset(interface: Any, observation_space: spaces.Tuple) -> list[str]:
    """Call ``interface.reset(seed=None, options=None)`` once and check that it returns
    ``(obs, info)`` with ``obs`` in ``observation_space`` (see :func:`check_obs`) and ``info`` a dict."""
    problems: list[str] = []
    _check_reset(interface, observation_space, problems)
    return problems


def check_send_control(interface: Any, action: Any) -> list[str]:
    """Call ``interface.send_control(action)`` once; a problem when it raises."""
    problems: list[str] = []
    _call(interface, "send_control", problems, action)
    return problems


def _is_step_result(result: Any) -> bool:
    return isinstance(result, tuple) and len(result) == 4


def check_step_result(result: Any, observation_space: spaces.Tuple) -> list[str]:
    """Check what ``get_obs_rew_terminated_info()`` returned: ``(obs, rew, terminated, info)``
    with ``obs`` in ``observation_space``, a real reward, a bool and a dict.

    Args:
        result: the value returned by the interface.
        observation_space: the interface's observation space (without the action buffer).

    Returns:
        One problem per wrong element (empty when the result is right).
    """
    what = "get_obs_rew_terminated_info()"
    if not _is_step_result(result):
        return [f"{what} must return a 4-tuple (obs, rew, terminated, info)"]
    obs, rew, terminated, info = result
    problems = check_obs(obs, observation_space, what)
    if isinstance(rew, (bool, np.bool_)) or not (
        isinstance(rew, numbers.Real)
        or (isinstance(rew, np.ndarray) and rew.shape == () and rew.dtype.kind in "fiu")
    ):
        problems.append(f"{what} returned a reward of type {type(rew).__name__}: return a float")
    if not isinstance(terminated, (bool, np.bool_)):
        problems.append(f"{what} returned terminated of type {type(terminated).__name__}: return a bool")
    return problems + _info_problem(what, info)


def check_capture_timing(capture_duration: float, config: Mapping[str, Any]) -> list[str]:
    """Check that an observation capture taking ``capture_duration`` seconds fits the time step.

    Args:
        capture_duration: the (worst) duration of ``get_obs_rew_terminated_info()``, in seconds.
        config: a real-time config (missing keys take their default).

    Returns:
        A problem when the capture is longer than the time step, or when starting it at
        ``start_obs_capture`` makes every step come later than the allowed lateness.
    """
    cfg = _with_defaults(config)
    T, soc = float(cfg["time_step_duration"]), float(cfg["start_obs_capture"])
    limit = T * (1.0 + float(cfg["time_step_timeout_factor"]))
    if capture_duration > T > 0:
        why = (
            f"capturing an observation takes {1000 * capture_duration:.1f} ms, longer than the time step "
            f"({1000 * T:.1f} ms): capture in a background thread and return the latest observation, "
            "or raise time_step_duration"
        )
        return [why]
    if soc + capture_duration > limit > 0:
        why = (
            f"start_obs_capture + capture time ({1000 * (soc + capture_duration):.1f} ms) exceeds the time "
            f"step plus its allowed lateness ({1000 * limit:.1f} ms): every step would time out; "
            "lower start_obs_capture"
        )
        return [why]
    return []


def check_capture(
    interface: Any,
    observation_space: spaces.Tuple,
    config: Mapping[str, Any],
    clock: Clock | None = None,
    repeats: int = 3,
) -> list[str]:
    """Call ``get_obs_rew_terminated_info()`` ``repeats`` times, timing each call; check the last
    result (:func:`check_step_result`) and the slowest call (:func:`check_capture_timing`).

    Args:
        interface: the interface object.
        observation_space: its observation space.
        config: a real-time config (missing keys take their default).
        clock: the clock to time with (default: real time).
        repeats: how many calls (at least 1).
    """
    clock = PerfCounterClock() if clock is None else clock
    problems: list[str] = []
    worst, result = 0.0, None
    for _ in range(max(1, repeats)):
        t0 = clock.now()
        ok, result = _call(interface, "get_obs_rew_terminated_info", problems)
        worst = max(worst, clock.now() - t0)
        if not ok:
            return problems
    problems += check_step_result(result, observation_space)
    if _is_step_result(result):
        problems += check_capture_timing(worst, config)
    return problems


def check_interface(interface: Any, config: Mapping[str, Any], clock: Clock | None = None) -> list[str]:
    """Check an interface object on the caller's thread, without the environment: its methods,
    spaces, ``reset()``, ``send_control(default_action)`` and capture, in this order, stopping
    where a problem makes the next checks meaningless. Never closes ``interface``.

    Args:
        interface: the interface object.
        config: a real-time config (missing keys take their default), for the timing.
        clock: the clock to time with (default: real time).
    """
    problems = check_methods(interface)
    if problems:
        return problems
    found = _read_spaces(interface, problems)
    if found is None:
        return problems
    obs_space, _, default = found
    if not _check_reset(interface, obs_space, problems):
        return problems
    problems += check_send_control(interface, default)
    return problems + check_capture(interface, obs_space, config, clock)


# the environment -------------------------------------------------------------------------------
def check_env_steps(config: Mapping[str, Any], n_steps: int = 5, clock: Clock | None = None) -> list[str]:
    """Run ``n_steps`` steps of a :class:`~tmrl.realtime.RealTimeEnv` made from ``config`` with
    the default action (resetting on done); check the observations against the environment's
    observation space and that no time step timed out. The environment is closed afterwards.

    Args:
        config: a real-time config with its interface.
        n_steps: how many steps.
        clock: the environment's clock (default: real time).
    """
    clock = PerfCounterClock() if clock is None else clock
    problems: list[str] = []
    env = None
    try:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always", TimeStepTimeoutWarning)
            env = RealTimeEnv(config, clock=clock)
            obs, _ = env.reset()
            if not env.observation_space.contains(obs):
                problems.append("the first observation of the environment is not in its observation space")
            for _ in range(n_steps):
                obs, _, terminated, truncated, _ = env.step(env.default_action)
                if not env.observation_space.contains(obs):
                    problems.append(
                        f"step {env.current_step}: the observation is not in the observation space"
                    )
                    break
                if terminated or truncated:
                    env.reset()
        late = [w for w in caught if issubclass(w.category, TimeStepTimeoutWarning)]
        if late:
            problems.append(
                f"{len(late)} of {n_steps} time steps timed out with an idle policy: the interface's calls are "
                "too slow for time_step_duration"
            )
    except Exception as err:  # noqa: BLE001  (reported, whatever it is)
        problems.append(f"running the environment raised {type(err).__name__}: {err}")
    finally:
        if env is not None:
            env.close()
    return problems


# all of it -------------------------------------------------------------------------------------
def _as_config(config_or_interface: Any) -> tuple[dict[str, Any], Any]:
    """``(config, interface object or None)`` for what :func:`check_realtime_interface` was given."""
    if isinstance(config_or_interface, Mapping):
        return dict(config_or_interface), None
    if isinstance(config_or_interface, type) or not hasattr(config_or_interface, "get_observation_space"):
        return dict(DEFAULT_CONFIG_DICT, interface=config_or_interface), None
    instance = config_or_interface
    config = dict(
        DEFAULT_CONFIG_DICT, interface=lambda: _Borrowed(instance), interface_args=(), interface_kwargs={}
    )
    return config, instance


def _check_all(config: dict[str, Any], instance: Any, n_steps: int, clock: Clock) -> list[str]:
    """The checks of :func:`check_realtime_interface` (``instance``: the caller's interface
    object, or None to build one from ``config`` and close it afterwards)."""
    try:
        cfg = read_config(config)
    except UserError as err:
        return [str(err)]
    problems = _config_combinations(cfg)
    owned = instance is None
    if owned:
        try:
            instance = cfg["interface"](*cfg["interface_args"], **cfg["interface_kwargs"])
        except Exception as err:  # noqa: BLE001  (reported, whatever it is)
            return problems + [f"building the interface raised {type(err).__name__}: {err}"]
    try:
        problems += check_interface(instance, cfg, clock)
    finally:
        if owned and callable(getattr(instance, "close", None)):
            instance.close()
    if problems or n_steps <= 0:
        return problems
    return problems + check_env_steps(cfg, n_steps, clock)


def check_realtime_interface(
    config_or_interface: Any,
    n_steps: int = 5,
    clock: Clock | None = None,
    raise_on_problem: bool = False,
) -> list[str]:
    """Check a real-time interface and its config; return the problems found, in plain words.

    Runs :func:`check_config`, :func:`check_interface` on a new interface (or on the one given)
    and, when nothing was found, :func:`check_env_steps`.

    Args:
        config_or_interface: a real-time config dict, an interface class (checked with the
            default config) or an interface object (never closed by the check).
        n_steps: steps of the real environment to run at the end (0 to skip).
        clock: the clock to time with (default: real time); a FakeClock makes the check instant.
        raise_on_problem: raise instead of returning a non-empty list.

    Returns:
        One sentence per problem; empty when everything looks right.

    Raises:
        UserError: ``raise_on_problem`` and problems were found (all in one line).
    """
    clock = PerfCounterClock() if clock is None else clock
    config, instance = _as_config(config_or_interface)
    try:
        problems = _check_all(config, instance, n_steps, clock)
    except Exception as err:  # noqa: BLE001  (the check must not crash on a broken interface)
        problems = [f"the check stopped on an unexpected {type(err).__name__}: {err}"]
    for p in problems:
        logger.warning("real-time interface check: %s", p)
    if problems and raise_on_problem:
        raise UserError("real-time interface check failed: " + "; ".join(problems))
    return problems
