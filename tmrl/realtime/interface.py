"""The contract between a real-time application and :class:`tmrl.realtime.RealTimeEnv`.

An application (a game, a robot, a simulator) implements :class:`RealTimeGymInterface` and puts
its class in a copy of :data:`DEFAULT_CONFIG_DICT`. The methods and the configuration keys have
the names and meanings of rtgym 0.16, so an interface written for rtgym works unchanged, including
one that subclasses rtgym's own ``RealTimeGymInterface``: the environment only calls methods, it
never checks the base class.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from gymnasium import spaces

__all__ = ["CONFIG_KEYS", "DEFAULT_CONFIG_DICT", "RealTimeGymInterface"]


class RealTimeGymInterface:
    """Base class of user interfaces; override the methods your application needs.

    The environment calls ``send_control`` at the start of every time step and
    ``get_obs_rew_terminated_info`` ``start_obs_capture`` seconds later. Observations are lists
    matching the Tuple returned by ``get_observation_space``; never put the action buffer in them,
    the environment appends it.
    """

    def send_control(self, control: Any) -> None:
        """Apply ``control`` (an element of the action space) to the device; must not block.

        ``None`` means "do nothing".
        """
        raise NotImplementedError

    def reset(self, seed: int | None = None, options: dict[str, Any] | None = None) -> tuple[list[Any], dict]:
        """Start an episode.

        Args:
            seed: the seed given to ``env.reset`` (``None``: none), for a device that can use one.
            options: the options given to ``env.reset``.

        Returns:
            ``(obs, info)``: ``obs`` a list with one element per space of the observation Tuple
            (without the action buffer), ``info`` a dict.
        """
        raise NotImplementedError

    def wait(self) -> None:
        """Pause the device between episodes (called by ``env.wait()`` and on done when
        ``wait_on_done`` is set). The clock restarts without a warning after a wait."""

    def get_obs_rew_terminated_info(self) -> tuple[list[Any], float, bool, dict]:
        """Capture the latest observation.

        Returns:
            ``(obs, rew, terminated, info)`` with ``obs`` as in :meth:`reset`.
        """
        raise NotImplementedError

    def get_observation_space(self) -> spaces.Tuple:
        """The observation space without the action buffer: a ``gymnasium.spaces.Tuple``."""
        raise NotImplementedError

    def get_action_space(self) -> spaces.Space:
        """The action space, usually a ``gymnasium.spaces.Box``."""
        raise NotImplementedError

    def get_default_action(self) -> Any:
        """The action applied at reset and used to fill the action buffer (an element of the
        action space, e.g. ``np.zeros(2, dtype=np.float32)``)."""
        raise NotImplementedError

    def render(self) -> Any:
        """Render the device's state; returns whatever ``env.render()`` should return (``None``)."""
        return None

    def close(self) -> None:
        """Release the device (threads, sockets). tmrl addition: ``env.close()`` calls it when the
        interface defines it; rtgym never calls it."""


DEFAULT_CONFIG_DICT: dict[str, Any] = {
    # Your interface class, and what its constructor takes.
    "interface": RealTimeGymInterface,
    "interface_args": (),
    "interface_kwargs": {},
    # Nominal duration of one time step, in seconds.
    "time_step_duration": 0.05,
    # Seconds after the start of a time step at which the observation is captured.
    "start_obs_capture": 0.05,
    # How late (in time steps) a step() may come before the clock restarts from now.
    "time_step_timeout_factor": 1.0,
    # Episodes are truncated after this many steps.
    "ep_max_length": np.inf,
    # Append the last act_buf_len actions (oldest first) to every observation.
    "act_in_obs": True,
    "act_buf_len": 1,
    # At reset, fill the action buffer with the default action.
    "reset_act_buf": True,
    # Measure durations; read them with env.unwrapped.benchmarks().
    "benchmark": False,
    "benchmark_polyak": 0.1,
    "benchmark_type": "polyak",  # or "trace" (every timestamp, as numpy arrays)
    # Call wait() when an episode ends (terminated or truncated).
    "wait_on_done": False,
    # With reset_act_buf False: reset() applies the last action given to step() instead of the
    # default action.
    "last_act_on_reset": False,
}
"""Default configuration of a real-time environment. Copy it (``dict(DEFAULT_CONFIG_DICT)``) and
change the copy; the environment never mutates the dict it is given."""

CONFIG_KEYS: frozenset[str] = frozenset(DEFAULT_CONFIG_DICT) | {"act_prepro_func", "obs_prepro_func"}
"""Every key a configuration may hold: the defaults plus rtgym's two undocumented hooks
``act_prepro_func`` (applied to the action before ``send_control``) and ``obs_prepro_func``."""
