"""``check_realtime_interface``: find the usual integration mistakes of a real-time interface.

It builds the interface, calls each method once on the caller's thread, compares what comes back
with the declared spaces, times the observation capture against the time step, and finally runs a
few steps of the real environment. Every problem is reported as one plain sentence.
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
from tmrl.realtime.env import RealTimeEnv, TimeStepTimeoutWarning, _read_config
from tmrl.realtime.interface import DEFAULT_CONFIG_DICT

__all__ = ["check_realtime_interface"]

logger = logging.getLogger(__name__)

_REQUIRED = (
    "send_control",
    "reset",
    "get_obs_rew_terminated_info",
    "get_observation_space",
    "get_action_space",
    "get_default_action",
)


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


def _check_obs(what: str, obs: Any, obs_space: spaces.Tuple, problems: list[str]) -> None:
    if not isinstance(obs, (list, tuple)):
        problems.append(f"{what} returned an observation of type {type(obs).__name__}: return a list")
        return
    n = len(obs_space.spaces)
    if len(obs) != n:
        problems.append(
            f"{what} returned {len(obs)} observation elements but get_observation_space() declares {n} "
            "(do not put the action buffer in the observation: the environment appends it)"
        )
        return
    for i, (sub, x) in enumerate(zip(obs_space.spaces, obs)):
        why = _mismatch(sub, x)
        if why:
            problems.append(f"{what}: observation element {i} {why} (space: {sub})")


def _check_is_dict(what: str, info: Any, problems: list[str]) -> None:
    if not isinstance(info, dict):
        problems.append(f"{what} returned info of type {type(info).__name__}: return a dict")


def check_realtime_interface(
    config_or_interface: Any,
    n_steps: int = 5,
    clock: Clock | None = None,
    raise_on_problem: bool = False,
) -> list[str]:
    """Check a real-time interface and its config; return the problems found, in plain words.

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
    problems: list[str] = []
    owned = True
    if isinstance(config_or_interface, Mapping):
        config = dict(config_or_interface)
    elif isinstance(config_or_interface, type) or not hasattr(config_or_interface, "get_observation_space"):
        config = dict(DEFAULT_CONFIG_DICT, interface=config_or_interface)
    else:
        instance = config_or_interface
        config = dict(
            DEFAULT_CONFIG_DICT, interface=lambda: _Borrowed(instance), interface_args=(), interface_kwargs={}
        )
        owned = False
    try:
        problems += _check(config, config_or_interface if not owned else None, n_steps, clock)
    except Exception as err:  # noqa: BLE001  (the check must not crash on a broken interface)
        problems.append(f"the check stopped on an unexpected {type(err).__name__}: {err}")
    for p in problems:
        logger.warning("real-time interface check: %s", p)
    if problems and raise_on_problem:
        raise UserError("real-time interface check failed: " + "; ".join(problems))
    return problems


def _check(config: dict[str, Any], instance: Any, n_steps: int, clock: Clock) -> list[str]:
    problems: list[str] = []
    try:
        cfg = _read_config(config)
    except UserError as err:
        return [str(err)]
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

    owned = instance is None
    if owned:
        try:
            instance = cfg["interface"](*cfg["interface_args"], **cfg["interface_kwargs"])
        except Exception as err:  # noqa: BLE001  (reported, whatever it is)
            return problems + [f"building the interface raised {type(err).__name__}: {err}"]
    try:
        problems += _check_instance(instance, cfg, clock)
    finally:
        if owned and callable(getattr(instance, "close", None)):
            instance.close()
    if problems or n_steps <= 0:
        return problems
    return problems + _run_env(cfg, n_steps, clock)


def _call(instance: Any, name: str, problems: list[str], *args: Any, **kwargs: Any) -> tuple[bool, Any]:
    try:
        return True, getattr(instance, name)(*args, **kwargs)
    except NotImplementedError:
        problems.append(
            f"{name}() is not implemented (it raises NotImplementedError): override it in your interface"
        )
    except Exception as err:  # noqa: BLE001  (reported, whatever it is)
        problems.append(f"{name}() raised {type(err).__name__}: {err}")
    return False, None


def _check_instance(instance: Any, cfg: dict[str, Any], clock: Clock) -> list[str]:
    problems: list[str] = []
    missing = [m for m in _REQUIRED if not callable(getattr(instance, m, None))]
    if missing:
        return [f"the interface has no method {m}()" for m in missing]

    ok, obs_space = _call(instance, "get_observation_space", problems)
    if ok and not isinstance(obs_space, spaces.Tuple):
        problems.append(
            f"get_observation_space() returned a {type(obs_space).__name__}: return a gymnasium.spaces.Tuple"
        )
        ok = False
    ok_a, act_space = _call(instance, "get_action_space", problems)
    if ok_a and not isinstance(act_space, spaces.Space):
        problems.append(f"get_action_space() returned a {type(act_space).__name__}: return a gymnasium space")
        ok_a = False
    ok_d, default = _call(instance, "get_default_action", problems)
    if ok_a and ok_d:
        why = _mismatch(act_space, default)
        if why:
            problems.append(f"the default action {why}: it must be in the action space {act_space}")
    if not (ok and ok_a and ok_d):
        return problems

    ok, res = _call(instance, "reset", problems, seed=None, options=None)
    if ok:
        if not (isinstance(res, tuple) and len(res) == 2):
            problems.append("reset() must return a pair (obs, info)")
            return problems
        _check_obs("reset()", res[0], obs_space, problems)
        _check_is_dict("reset()", res[1], problems)

    _call(instance, "send_control", problems, default)

    worst = 0.0
    for _ in range(3):
        t0 = clock.now()
        ok, res = _call(instance, "get_obs_rew_terminated_info", problems)
        worst = max(worst, clock.now() - t0)
        if not ok:
            return problems
    if not (isinstance(res, tuple) and len(res) == 4):
        problems.append("get_obs_rew_terminated_info() must return a 4-tuple (obs, rew, terminated, info)")
        return problems
    obs, rew, terminated, info = res
    what = "get_obs_rew_terminated_info()"
    _check_obs(what, obs, obs_space, problems)
    if isinstance(rew, (bool, np.bool_)) or not (
        isinstance(rew, numbers.Real)
        or (isinstance(rew, np.ndarray) and rew.shape == () and rew.dtype.kind in "fiu")
    ):
        problems.append(f"{what} returned a reward of type {type(rew).__name__}: return a float")
    if not isinstance(terminated, (bool, np.bool_)):
        problems.append(f"{what} returned terminated of type {type(terminated).__name__}: return a bool")
    _check_is_dict(what, info, problems)

    T, soc = float(cfg["time_step_duration"]), float(cfg["start_obs_capture"])
    limit = T * (1.0 + float(cfg["time_step_timeout_factor"]))
    if worst > T > 0:
        problems.append(
            f"capturing an observation takes {1000 * worst:.1f} ms, longer than the time step "
            f"({1000 * T:.1f} ms): capture in a background thread and return the latest observation, "
            "or raise time_step_duration"
        )
    elif soc + worst > limit > 0:
        problems.append(
            f"start_obs_capture + capture time ({1000 * (soc + worst):.1f} ms) exceeds the time step plus its "
            f"allowed lateness ({1000 * limit:.1f} ms): every step would time out; lower start_obs_capture"
        )
    return problems


def _run_env(cfg: dict[str, Any], n_steps: int, clock: Clock) -> list[str]:
    problems: list[str] = []
    env = None
    try:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always", TimeStepTimeoutWarning)
            env = RealTimeEnv(cfg, clock=clock)
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
