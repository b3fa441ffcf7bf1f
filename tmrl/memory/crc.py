"""``crc_debug``: checks a transition rebuilt by a memory against the full sample the worker stored
(pipeline debugging: :meth:`tmrl.memory.Memory.__getitem__` calls :func:`check_transition` when
the memory was built with ``crc_debug=True``).
"""

from __future__ import annotations

import logging
from collections.abc import Mapping
from typing import Any

import numpy as np
import torch

from tmrl.errors import UserError

__all__ = ["CRCMismatchError", "check_transition"]

# The memory package logs under one name, "tmrl.memory", as the single module it was before.
logger = logging.getLogger("tmrl.memory")

_TRANSITION_FIELDS = ("prev_obs", "act", "new_obs", "rew", "terminated", "truncated")


class CRCMismatchError(UserError):
    """``crc_debug``: a transition rebuilt by the memory differs from the one the worker saw."""


def _describe(x: Any) -> str:
    if x is None:
        return "None"
    if isinstance(x, (np.ndarray, torch.Tensor)):
        arr = np.asarray(x)
        flat = np.array2string(arr.ravel()[:6], separator=",", max_line_width=10_000)
        more = "..." if arr.size > 6 else ""
        return f"{arr.dtype}{tuple(arr.shape)} {flat}{more}"
    text = repr(x)
    return text if len(text) <= 60 else text[:57] + "..."


def _first_difference(orig: Any, rebuilt: Any, path: str) -> str | None:
    """Return a one-line description of the first place where ``orig`` and ``rebuilt`` differ."""
    if orig is None or rebuilt is None:
        if orig is None and rebuilt is None:
            return None
        return f"{path}: worker {_describe(orig)} vs memory {_describe(rebuilt)}"
    if isinstance(orig, Mapping) or isinstance(rebuilt, Mapping):
        if not (isinstance(orig, Mapping) and isinstance(rebuilt, Mapping)):
            return f"{path}: worker {type(orig).__name__} vs memory {type(rebuilt).__name__}"
        if set(orig) != set(rebuilt):
            return f"{path}: worker keys {sorted(map(str, orig))} vs memory keys {sorted(map(str, rebuilt))}"
        for key in orig:
            diff = _first_difference(orig[key], rebuilt[key], f"{path}[{key!r}]")
            if diff:
                return diff
        return None
    orig_seq = isinstance(orig, (tuple, list))
    rebuilt_seq = isinstance(rebuilt, (tuple, list))
    if orig_seq or rebuilt_seq:
        if not (orig_seq and rebuilt_seq):
            return f"{path}: worker {type(orig).__name__} vs memory {type(rebuilt).__name__}"
        if len(orig) != len(rebuilt):
            return f"{path}: worker has {len(orig)} elements, memory has {len(rebuilt)}"
        for i, (a, b) in enumerate(zip(orig, rebuilt)):
            diff = _first_difference(a, b, f"{path}[{i}]")
            if diff:
                return diff
        return None
    a = np.asarray(orig.detach().cpu() if isinstance(orig, torch.Tensor) else orig)
    b = np.asarray(rebuilt.detach().cpu() if isinstance(rebuilt, torch.Tensor) else rebuilt)
    if a.shape != b.shape:
        return f"{path}: shape {a.shape} in the worker's sample vs {b.shape} in the memory"
    if a.dtype.kind in "biuf" and b.dtype.kind in "biuf":
        # The memory may store floats in float32: compare at the stored precision.
        equal = np.array_equal(a.astype(b.dtype), b)
    else:
        equal = np.array_equal(a, b)
    if not equal:
        return f"{path}: worker {_describe(a)} vs memory {_describe(b)}"
    return None


def check_transition(item: Any, rebuilt: tuple, info: Any) -> bool:
    """``crc_debug`` check of one rebuilt transition against the full sample the worker stored.

    The worker (with ``crc_debug=True``) puts ``info["crc_sample"] = (prev_obs, act, new_obs, rew,
    terminated, truncated)``, observations taken before compression. This compares it with what
    the memory rebuilt, field by field and element by element (floats compared at the memory's
    precision).

    Args:
        item: the index that was sampled (for the message).
        rebuilt: ``(prev_obs, act, new_obs, rew, terminated, truncated)`` from the memory.
        info: the transition's info dict.

    Returns:
        ``True`` when the check ran and passed, ``False`` when ``info`` carries no ``crc_sample``.

    Raises:
        CRCMismatchError: naming the field and element that differ.
    """
    if not isinstance(info, Mapping) or "crc_sample" not in info:
        return False
    original = info["crc_sample"]
    if len(original) != 6:
        raise CRCMismatchError(
            f"crc_debug: info['crc_sample'] of item {item} has {len(original)} fields, expected "
            "(prev_obs, act, new_obs, rew, terminated, truncated): check the worker's crc_debug code"
        )
    for name, orig, mine in zip(_TRANSITION_FIELDS, original, rebuilt):
        if name == "prev_obs" and orig is None:
            continue  # the worker has no previous observation for a reset sample
        diff = _first_difference(orig, mine, name)
        if diff:
            ts = info.get("crc_sample_ts")
            where = f" (worker time step {ts[0]}, {ts[1]} since reset)" if ts is not None else ""
            raise CRCMismatchError(
                f"crc_debug: transition {item}{where} differs from the worker's sample at {diff}; "
                "fix the sample_compressor or the memory's get_transition so they match"
            )
    logger.debug("crc_debug: transition %s matches the worker's sample", item)
    return True
