"""``GenericGymEnv``: the wrapper every worker and trainer builds its environment with.

It accepts any registered Gymnasium id (``Pendulum-v1``...) and the real-time ids of
:mod:`tmrl.realtime` (imported here, which registers them), and optionally rescales observations
and converts float64 observations to float32 (including inside tuples, lists and dicts).
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import gymnasium
import numpy as np
from gymnasium import spaces

import tmrl.realtime  # noqa: F401  (registers the real-time ids)
from tmrl.errors import UserError

__all__ = ["AffineObservation", "Float64ToFloat32", "GenericGymEnv", "ScaleObservation", "to_float32"]


def _map_space(space: spaces.Space, box_fn: Any) -> spaces.Space:
    """Apply ``box_fn`` to every Box of a (possibly nested Tuple/Dict) space."""
    if isinstance(space, spaces.Box):
        return box_fn(space)
    if isinstance(space, spaces.Tuple):
        return spaces.Tuple(tuple(_map_space(s, box_fn) for s in space.spaces))
    if isinstance(space, spaces.Dict):
        return spaces.Dict({k: _map_space(s, box_fn) for k, s in space.spaces.items()})
    return space


def _map_obs(space: spaces.Space, obs: Any, box_fn: Any) -> Any:
    """Apply ``box_fn(box, value)`` to every value that sits at a Box of ``space``."""
    if isinstance(space, spaces.Box):
        return box_fn(space, obs)
    if isinstance(space, spaces.Tuple) and isinstance(obs, (tuple, list)):
        return type(obs)(_map_obs(s, o, box_fn) for s, o in zip(space.spaces, obs))
    if isinstance(space, spaces.Dict) and isinstance(obs, Mapping):
        return {k: _map_obs(space.spaces[k], v, box_fn) if k in space.spaces else v for k, v in obs.items()}
    return obs


class AffineObservation(gymnasium.ObservationWrapper):
    """Map every Box part of the observation (nested Tuple/Dict included) to
    ``(obs + shift) * scale`` (tmrl 0.7's ``AffineObservationWrapper``, extended to nested
    spaces).

    Args:
        env: the environment to wrap.
        shift: added to every Box element first.
        scale: then multiplied.
    """

    def __init__(self, env: gymnasium.Env, shift: float, scale: float) -> None:
        super().__init__(env)
        self.shift = float(shift)
        self.scale = float(scale)

        def box(b: spaces.Box) -> spaces.Box:
            low, high = (b.low + self.shift) * self.scale, (b.high + self.shift) * self.scale
            return spaces.Box(np.minimum(low, high), np.maximum(low, high), dtype=b.dtype)

        self.observation_space = _map_space(env.observation_space, box)

    def observation(self, observation: Any) -> Any:
        shift, scale = self.shift, self.scale
        return _map_obs(
            self.env.observation_space,
            observation,
            lambda b, x: ((np.asarray(x) + shift) * scale).astype(b.dtype, copy=False),
        )


class ScaleObservation(AffineObservation):
    """Multiply every Box part of the observation (nested Tuple/Dict included) by ``scale``.

    Args:
        env: the environment to wrap.
        scale: the factor.
    """

    def __init__(self, env: gymnasium.Env, scale: float) -> None:
        super().__init__(env, 0.0, scale)


def to_float32(x: Any) -> Any:
    """Convert float64 arrays to float32 (same shape), and Python or numpy scalar numbers to
    float32 arrays of shape (1,), through nested tuples, lists and dicts. Other leaves (strings,
    integer and bool arrays, None) are returned unchanged.

    The original tmrl also adds a leading dimension to float64 arrays; this keeps their shape,
    so that they stay inside the converted observation space.

    Args:
        x: an observation: a leaf or nested tuples, lists and dicts.
    """
    if isinstance(x, np.ndarray):
        return x.astype(np.float32) if x.dtype == np.float64 else x
    if isinstance(x, (float, int, np.floating)) and not isinstance(x, bool):
        return np.asarray([x], dtype=np.float32)
    if isinstance(x, (tuple, list)):
        return type(x)(to_float32(v) for v in x)
    if isinstance(x, Mapping):
        return {k: to_float32(v) for k, v in x.items()}
    return x


class Float64ToFloat32(gymnasium.ObservationWrapper):
    """Observations (and the spaces' float Boxes) in float32; see :func:`to_float32`.

    Args:
        env: the environment to wrap.
    """

    def __init__(self, env: gymnasium.Env) -> None:
        super().__init__(env)

        def box(b: spaces.Box) -> spaces.Box:
            if not np.issubdtype(b.dtype, np.floating):
                return b
            return spaces.Box(b.low.astype(np.float32), b.high.astype(np.float32), dtype=np.float32)

        self.observation_space = _map_space(env.observation_space, box)
        self.action_space = _map_space(env.action_space, box)

    def observation(self, observation: Any) -> Any:
        return to_float32(observation)


class GenericGymEnv(gymnasium.Wrapper):
    """A Gymnasium environment made from its id, optionally rescaled and converted to float32.

    Args:
        id: a registered Gymnasium id: ``"Pendulum-v1"``, ``"real-time-gym-v1"``,
            ``"real-time-gym-ts-v1"`` (or tmrl's ``"tmrl/real-time-gym-v1"``...).
        gym_kwargs: keyword arguments of ``gymnasium.make`` (for real-time ids:
            ``{"config": config}``). The passive environment checker is off unless
            ``disable_env_checker`` is given.
        obs_scale: when non-zero, every Box part of the observation is multiplied by it.
        to_float32: convert float64 observations to float32 (see :func:`to_float32`).

    Attributes:
        default_action: the inner environment's ``default_action`` (real-time environments);
            reading it raises ``AttributeError`` otherwise, so ``getattr(env, "default_action",
            None)`` works.

    Raises:
        UserError: the id is not registered.
    """

    def __init__(
        self,
        id: str = "Pendulum-v1",
        gym_kwargs: Mapping[str, Any] | None = None,
        obs_scale: float = 0.0,
        to_float32: bool = False,
    ) -> None:
        kwargs = dict(gym_kwargs or {})
        kwargs.setdefault("disable_env_checker", True)
        try:
            env = gymnasium.make(id, **kwargs)
        except gymnasium.error.Error as err:
            raise UserError(
                f"cannot make Gymnasium environment {id!r} ({err}); use a registered id such as "
                "'Pendulum-v1' or 'real-time-gym-v1', and import the package that registers yours"
            ) from None
        if obs_scale:
            env = ScaleObservation(env, obs_scale)
        if to_float32:
            env = Float64ToFloat32(env)
        super().__init__(env)

    def wait(self) -> None:
        """Pause a real-time environment between episodes (rtgym's ``wait()``); environments that
        have no such pause ignore it."""
        wait = getattr(self.env.unwrapped, "wait", None)
        if callable(wait):
            wait()

    @property
    def default_action(self) -> Any:
        try:
            return self.env.get_wrapper_attr("default_action")
        except AttributeError:
            raise AttributeError(
                f"environment {self.env.spec.id if self.env.spec else self.env!r} has no default_action"
            ) from None
