"""Compatibility names of the original ``tmrl.tools.check_environment``: the function behind
``python -m tmrl --check-environment``, for one TrackMania interface."""

from __future__ import annotations

from typing import Any

__all__ = ["check_env_tm20full", "check_env_tm20lidar"]


def _check(interface: str, **kwargs: Any) -> int:
    from tmrl.config.loader import load_config
    from tmrl.tm.tools import check_environment

    cfg = load_config()
    cfg["ENV"]["RTGYM_INTERFACE"] = interface
    return check_environment(cfg, **kwargs)


def check_env_tm20lidar(**kwargs: Any) -> int:
    """``--check-environment`` on the ``TM20LIDAR`` interface (keywords: see
    :func:`tmrl.tm.tools.check_environment`)."""
    return _check("TM20LIDAR", **kwargs)


def check_env_tm20full(**kwargs: Any) -> int:
    """``--check-environment`` on the ``TM20FULL`` interface."""
    return _check("TM20FULL", **kwargs)
