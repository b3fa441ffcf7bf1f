"""The training batch: what the replay memory hands to ``agent.train``.

A :class:`Batch` is a NamedTuple, so code written for the 6-tuple of tmrl 0.7
(``o, a, r, o2, d, t = batch``, ``batch[3]``) keeps working, and new code reads the fields by
name.
"""

from __future__ import annotations

from typing import Any, NamedTuple

__all__ = ["Batch"]


class Batch(NamedTuple):
    """One batch of transitions, collated on the training device.

    Attributes:
        obs: observations (a tensor, or a tuple/list/dict of tensors with a leading batch axis).
        act: actions ``(B, *action_shape)``.
        rew: rewards ``(B,)``.
        next_obs: the observations that followed, same structure as ``obs``.
        terminated: 1.0 where the episode ended for good (no bootstrap), ``(B,)``.
        truncated: 1.0 where the episode was cut short (bootstrap anyway), ``(B,)``.
    """

    obs: Any
    act: Any
    rew: Any
    next_obs: Any
    terminated: Any
    truncated: Any
