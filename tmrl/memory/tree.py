"""Nested observation structures: the spec that describes one (tuples, lists and dicts of leaves),
the helpers that flatten observations into one column per leaf and rebuild the structure from
batched leaves, and the storage dtype of a leaf. Used by :class:`tmrl.memory.storage.RingStorage`
and the built-in memories.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from typing import Any

import numpy as np

from tmrl.errors import UserError

# A spec describes a nested observation: ("leaf", index) | ("tuple"|"list", [children]) |
# ("dict", [keys], [children]). It is JSON-able (lists instead of tuples) for checkpoints.


def _make_spec(obj: Any, counter: list[int]) -> list:
    if isinstance(obj, Mapping):
        keys = list(obj)
        return ["dict", keys, [_make_spec(obj[k], counter) for k in keys]]
    if isinstance(obj, (tuple, list)):
        kind = "tuple" if isinstance(obj, tuple) else "list"
        return [kind, [_make_spec(x, counter) for x in obj]]
    counter[0] += 1
    return ["leaf", counter[0] - 1]


def _columns(spec: list, objs: list[Any], out: list[list[Any]], path: str) -> None:
    """Append, for each leaf of ``spec`` in order, the list of that leaf over all ``objs``."""
    kind = spec[0]
    if kind == "leaf":
        out.append(objs)
        return
    if kind == "dict":
        keys, children = spec[1], spec[2]
        try:
            for key, child in zip(keys, children):
                _columns(child, [o[key] for o in objs], out, f"{path}[{key!r}]")
        except (KeyError, TypeError) as err:
            raise UserError(
                f"observation element {path} changed structure between samples (missing key {err}): "
                "observations must keep one structure"
            ) from None
        return
    children = spec[1]
    for o in objs:
        if not isinstance(o, (tuple, list)) or len(o) != len(children):
            raise UserError(
                f"observation element {path} changed structure between samples (expected a sequence "
                f"of {len(children)}, got {type(o).__name__}): observations must keep one structure"
            )
    for i, child in enumerate(children):
        _columns(child, [o[i] for o in objs], out, f"{path}[{i}]")


def _tree_leaves(spec: list, tree: Any, out: list[Any], path: str) -> None:
    """Append the leaves of ``tree`` (one observation's structure) in ``spec``'s order; raise
    the error of :func:`_columns` when the structure differs."""
    kind = spec[0]
    if kind == "leaf":
        if isinstance(tree, (Mapping, tuple, list)):
            raise UserError(
                f"observation element {path} changed structure between samples (expected an array, "
                f"got {type(tree).__name__}): observations must keep one structure"
            )
        out.append(tree)
        return
    if kind == "dict":
        if not isinstance(tree, Mapping) or any(k not in tree for k in spec[1]):
            raise UserError(
                f"observation element {path} changed structure between samples (keys differ): "
                "observations must keep one structure"
            )
        for key, child in zip(spec[1], spec[2]):
            _tree_leaves(child, tree[key], out, f"{path}[{key!r}]")
        return
    children = spec[1]
    if not isinstance(tree, (tuple, list)) or len(tree) != len(children):
        raise UserError(
            f"observation element {path} changed structure between samples (expected a sequence "
            f"of {len(children)}, got {type(tree).__name__}): observations must keep one structure"
        )
    for i, child in enumerate(children):
        _tree_leaves(child, tree[i], out, f"{path}[{i}]")


def _unflatten(spec: list, leaves: Sequence[Any]) -> Any:
    kind = spec[0]
    if kind == "leaf":
        return leaves[spec[1]]
    if kind == "dict":
        return {k: _unflatten(c, leaves) for k, c in zip(spec[1], spec[2])}
    items = [_unflatten(c, leaves) for c in spec[1]]
    return tuple(items) if kind == "tuple" else items


def _leaf_paths(spec: list, path: str = "obs") -> list[str]:
    kind = spec[0]
    if kind == "leaf":
        return [path]
    if kind == "dict":
        return [p for k, c in zip(spec[1], spec[2]) for p in _leaf_paths(c, f"{path}[{k!r}]")]
    return [p for i, c in enumerate(spec[1]) for p in _leaf_paths(c, f"{path}[{i}]")]


def _tree_map(fn: Callable[[Any], Any], tree: Any) -> Any:
    if isinstance(tree, Mapping):
        return {k: _tree_map(fn, v) for k, v in tree.items()}
    if isinstance(tree, (tuple, list)):
        return type(tree)(_tree_map(fn, v) for v in tree)
    return fn(tree)


def _storage_dtype(arr: np.ndarray) -> np.dtype:
    if arr.dtype == np.float64:
        return np.dtype(np.float32)  # halves the memory; models train in float32 anyway
    if arr.dtype == object:
        raise UserError(
            "an observation or action element is not numeric (or changes shape between samples): "
            "built-in memories store arrays and numbers only; fix the sample_compressor"
        )
    return arr.dtype


def _stack(column: list[Any], what: str) -> np.ndarray:
    try:
        arr = np.asarray(column)
    except ValueError:
        raise UserError(
            f"{what} changes shape between samples: every sample must give it the same shape"
        ) from None
    return arr
