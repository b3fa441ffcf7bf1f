"""Configuration: the schema of ``config.json``, the data folder, loading and overrides.

Importing this package reads nothing. The functions most callers need are reachable from here
(loaded on first use from :mod:`tmrl.config.loader`, so that ``python -m tmrl.config.schema``
runs cleanly); :mod:`tmrl.config.config_constants` and :mod:`tmrl.config.config_objects` are the
original tmrl's compatibility modules, which read the configuration when imported.
"""

from __future__ import annotations

from typing import Any

__all__ = [
    "ConfigError",
    "apply_override",
    "config_path",
    "data_folder",
    "data_paths",
    "ensure_data_folder",
    "install",
    "load_config",
]


def __getattr__(name: str) -> Any:
    if name in __all__:
        from tmrl.config import loader

        return getattr(loader, name)
    raise AttributeError(f"module 'tmrl.config' has no attribute {name!r}")
