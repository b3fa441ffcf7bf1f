"""tmrl: distributed real-time reinforcement learning.

Importing this package has no side effects: it reads no file, writes no folder and leaves
logging alone. Configuration is read when a command or an object needs it.

Two names of the original package's top level are kept, resolved on first use:

- ``tmrl.get_environment()``: the Gymnasium environment that ``config.json`` describes (what
  ``--worker`` runs), built from ``tmrl.config.config_objects``;
- ``tmrl.GenericGymEnv``: :class:`tmrl.envs.GenericGymEnv`.
"""

from __future__ import annotations

from typing import Any

from tmrl._version import __version__

__all__ = ["GenericGymEnv", "__version__", "get_environment"]


def get_environment() -> Any:
    """The environment of the configuration (``ENV`` in ``config.json``): for TrackMania, the
    real-time TrackMania environment; for the simulator, the simulated track; for ``GYM``, the
    named Gymnasium environment.

    Reads ``config.json`` (through ``tmrl.config.config_objects``) when called, not at import.

    Returns:
        gymnasium.Env: a new environment instance.

    Raises:
        tmrl.config.loader.ConfigError: the configuration is invalid.
    """
    from tmrl.config import config_objects

    return config_objects.ENV_CLS()


def __getattr__(name: str) -> Any:
    if name == "GenericGymEnv":
        from tmrl.envs import GenericGymEnv

        return GenericGymEnv
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
