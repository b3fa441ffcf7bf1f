"""Compatibility name of the original ``tmrl.tools.record``: ``record_reward_dist``, the
function behind ``python -m tmrl --record-reward``."""

from __future__ import annotations

import os

__all__ = ["record_reward_dist"]


def record_reward_dist(path_reward: str | os.PathLike[str] | None = None, use_keyboard: bool = False) -> int:
    """Record the reward trajectory while you drive one lap (see
    :func:`tmrl.tm.tools.record_reward`); ``path_reward`` defaults to the data folder's
    ``reward/reward.npy``."""
    from tmrl.tm.tools import record_reward

    return record_reward(None, use_keyboard=use_keyboard, path=path_reward)
