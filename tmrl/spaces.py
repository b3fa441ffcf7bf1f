"""The schema of a run: what the trainer accepts as samples, derived from its spaces.

A worker's samples cross the network and come from a peer the trainer does not have to trust
(anyone with the password can send). Before a batch reaches the replay memory, the trainer checks
it against a :class:`SampleSchema` built from *its own* observation and action spaces, never from
the data received: so the first payload cannot decide the memory's shapes, and a batch of another
shape, dtype, or with NaN, infinite or out-of-range values is dropped whole.

What a sample looks like on the wire depends on the worker's ``obs_preprocessor`` and
``sample_compressor`` (the compressor drops what the memory rebuilds: action buffers, image
histories). The schema runs the same two functions once on a sample drawn from the spaces and
describes what comes out: a tree of containers with, at each leaf, a shape and a dtype. Those
functions are the trainer's own code (the same ``config.json``), so nothing received is executed.

The module also describes spaces for the weights envelope (:func:`describe_spaces`,
:func:`check_spaces`). It depends on NumPy only; spaces are read by duck typing (Gymnasium's
``Box``, ``Discrete``, ``Tuple``, ``Dict``... and any space with ``sample()``).
"""

from __future__ import annotations

import copy
import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from tmrl.errors import UserError

__all__ = [
    "LeafSpec",
    "Rows",
    "SampleColumns",
    "PinnedSampleSchema",
    "SampleRejected",
    "SampleSchema",
    "SpacesMismatchError",
    "check_spaces",
    "describe_spaces",
]


# ================================================================================================
# Spaces description (sent with the weights)


class SpacesMismatchError(UserError):
    """The worker's observation or action space differs from the trainer's."""


def _describe_space(space: Any) -> Any:
    name = type(space).__name__
    if hasattr(space, "spaces") and isinstance(space.spaces, (tuple, list)):
        return {"type": name, "spaces": [_describe_space(s) for s in space.spaces]}
    if hasattr(space, "spaces") and isinstance(space.spaces, dict):
        return {
            "type": name,
            "keys": [str(k) for k in space.spaces],
            "spaces": [_describe_space(s) for s in space.spaces.values()],
        }
    out: dict[str, Any] = {"type": name}
    shape = getattr(space, "shape", None)
    if shape is not None:
        out["shape"] = [int(x) for x in shape]
    dtype = getattr(space, "dtype", None)
    if dtype is not None:
        out["dtype"] = str(np.dtype(dtype))
    n = getattr(space, "n", None)
    if n is not None and np.ndim(n) == 0:
        out["n"] = int(n)
    return out


def describe_spaces(observation_space: Any, action_space: Any) -> dict[str, Any]:
    """A small data-only description (types, shapes, dtypes) of an actor's spaces.

    Args:
        observation_space: the actor's observation space (a Gymnasium space).
        action_space: its action space.
    """
    return {"observation": _describe_space(observation_space), "action": _describe_space(action_space)}


def _space_str(d: Any) -> str:
    if not isinstance(d, dict):
        return repr(d)[:200]
    if "spaces" in d:
        inner = ", ".join(_space_str(s) for s in d["spaces"]) if isinstance(d["spaces"], list) else "?"
        return f"{d.get('type')}({inner})"
    parts = [
        f"shape={tuple(d['shape'])}" if isinstance(d.get("shape"), list) else "",
        str(d.get("dtype", "")),
        f"n={d['n']}" if "n" in d else "",
    ]
    return f"{d.get('type')}({', '.join(p for p in parts if p)})"[:300]


def check_spaces(mine: dict[str, Any], theirs: Any) -> None:
    """Raise :class:`SpacesMismatchError` naming both sides when the descriptions differ.

    Args:
        mine: this side's :func:`describe_spaces`.
        theirs: the other side's (``None`` or anything else than a dict: nothing to compare).
    """
    if not isinstance(theirs, dict):
        return
    for key in ("observation", "action"):
        if key in theirs and theirs[key] != mine[key]:
            raise SpacesMismatchError(
                f"the trainer's {key} space is {_space_str(theirs[key])} but this worker's is "
                f"{_space_str(mine[key])}: run the worker and the trainer with the same environment "
                f"(and the same config.json)"
            )


# ================================================================================================
# Sample schema


class SampleRejected(ValueError):
    """A sample batch does not fit the run's schema; the message names the first problem."""


@dataclass(frozen=True)
class LeafSpec:
    """One array of a sample: its path (``obs[1]``, ``act``), shape per sample, dtype, and the
    bounds its values must lie in (``None``: finite for floats, the dtype's range for integers).

    Args:
        path: where the array is in a sample (``obs[1]``, ``act``).
        shape: its shape per sample.
        dtype: its dtype.
        low: lower bounds (``None``: finite for floats, the dtype's range for integers).
        high: upper bounds (likewise).
    """

    path: str
    shape: tuple[int, ...]
    dtype: np.dtype
    low: np.ndarray | None = None
    high: np.ndarray | None = None

    def describe(self) -> dict[str, Any]:
        """Data-only description (for the wire and for logs)."""
        return {"path": self.path, "shape": list(self.shape), "dtype": str(self.dtype)}


@dataclass
class SampleColumns:
    """A batch of ``n`` samples as arrays, checked and cast to the schema's dtypes.

    Attributes:
        act: the actions that are not ``None``, shape ``(k, *action_shape)`` (``None`` when
            every action is ``None``).
        act_none: ``None`` when no action is ``None``, else a bool mask of shape ``(n,)`` (True
            where the sample's action is ``None``: the first sample of an episode).
        obs: the observations: the schema's tree (tuples, lists, dicts) with an array of shape
            ``(n, *leaf_shape)`` at each leaf.
        rew: float64 rewards ``(n,)``; ``terminated``, ``truncated``: bool ``(n,)``.
    """

    act: np.ndarray | None
    act_none: np.ndarray | None
    obs: Any
    rew: np.ndarray
    terminated: np.ndarray
    truncated: np.ndarray


# Tree nodes of a schema: ("seq", [children]) for tuples and lists, ("dict", keys, [children]),
# or a LeafSpec.


def _leaf_from_value(value: Any, path: str) -> LeafSpec:
    arr = np.asarray(value)
    if arr.dtype.kind not in "biuf":
        raise UserError(
            f"{path} of a sample is {arr.dtype} data: observations and actions must be numbers or "
            "arrays of numbers (fix the obs_preprocessor or sample_compressor)"
        )
    return LeafSpec(path, tuple(int(x) for x in arr.shape), arr.dtype)


def _tree_from_value(value: Any, path: str, depth: int = 0) -> Any:
    if depth > 20:
        raise UserError(f"{path} of a sample is nested more than 20 levels deep")
    if isinstance(value, (tuple, list)):
        return ("seq", [_tree_from_value(v, f"{path}[{i}]", depth + 1) for i, v in enumerate(value)])
    if isinstance(value, dict):
        keys = list(value)
        if not all(type(k) is str for k in keys):
            raise UserError(f"{path} of a sample is a dict whose keys are not all strings")
        return ("dict", keys, [_tree_from_value(value[k], f"{path}[{k!r}]", depth + 1) for k in keys])
    return _leaf_from_value(value, path)


def _tree_leaves(tree: Any) -> list[LeafSpec]:
    if isinstance(tree, LeafSpec):
        return [tree]
    children = tree[1] if tree[0] == "seq" else tree[2]
    return [leaf for child in children for leaf in _tree_leaves(child)]


def _tree_describe(tree: Any) -> Any:
    if isinstance(tree, LeafSpec):
        return tree.describe()
    if tree[0] == "seq":
        return {"seq": [_tree_describe(c) for c in tree[1]]}
    return {"dict": list(tree[1]), "values": [_tree_describe(c) for c in tree[2]]}


def _action_bounds(action_space: Any, leaf: LeafSpec) -> LeafSpec:
    """``leaf`` with the bounds of a Box or Discrete action space, when the action on the wire is
    the space's own (a compressor may change it: then only finiteness is checked)."""
    low, high = getattr(action_space, "low", None), getattr(action_space, "high", None)
    n = getattr(action_space, "n", None)
    if low is not None and high is not None:
        try:
            low = np.broadcast_to(np.asarray(low, dtype=np.float64), leaf.shape)
            high = np.broadcast_to(np.asarray(high, dtype=np.float64), leaf.shape)
        except ValueError:  # the compressor changed the action's shape
            return leaf
        if leaf.dtype.kind == "f":
            # A little slack: a float32 action at a float64 bound may round just outside it.
            low = low - 1e-5 * (1.0 + np.abs(low))
            high = high + 1e-5 * (1.0 + np.abs(high))
        return LeafSpec(leaf.path, leaf.shape, leaf.dtype, low, high)
    elif n is not None and np.ndim(n) == 0 and leaf.shape == ():
        start = int(getattr(action_space, "start", 0))
        return LeafSpec(leaf.path, leaf.shape, leaf.dtype, np.asarray(start), np.asarray(start + int(n) - 1))
    return leaf


def _shape_str(shape: tuple[int, ...]) -> str:
    return str(tuple(int(x) for x in shape))


def _check_leaf(spec: LeafSpec, arr: Any, n: int) -> np.ndarray:
    """``arr`` (``n`` values of ``spec``) cast to ``spec.dtype``, or :class:`SampleRejected`."""
    if not isinstance(arr, np.ndarray):
        try:
            arr = np.asarray(arr)
        except (ValueError, TypeError, OverflowError):
            raise SampleRejected(f"{spec.path} changes shape between samples") from None
    kind = arr.dtype.kind
    if kind not in "biuf":
        raise SampleRejected(f"{spec.path} holds {arr.dtype} data where the run expects {spec.dtype}")
    if arr.shape != (n, *spec.shape):
        got = _shape_str(arr.shape[1:]) if arr.ndim and len(arr) == n else f"{arr.shape} for {n} samples"
        raise SampleRejected(f"{spec.path} has shape {got} where the run expects {_shape_str(spec.shape)}")
    want = spec.dtype.kind
    if want == "f":
        if kind != "f":
            raise SampleRejected(f"{spec.path} holds {arr.dtype} values where the run expects {spec.dtype}")
        # Cast first: a float64 value beyond float32's range becomes inf in a float32 memory.
        out = arr.astype(spec.dtype, copy=False)
        finite = np.isfinite(out)
        if not finite.all():
            raise SampleRejected(f"{spec.path} holds a non-finite value (sample {_first_false(finite)})")
    elif want in "iu":
        if kind not in "iu":
            raise SampleRejected(f"{spec.path} holds {arr.dtype} values where the run expects {spec.dtype}")
        if arr.size and arr.dtype != spec.dtype:
            info = np.iinfo(spec.dtype)
            if arr.min() < info.min or arr.max() > info.max:
                raise SampleRejected(f"{spec.path} holds values outside the range of {spec.dtype}")
        out = arr.astype(spec.dtype, copy=False)
    else:  # bool
        if kind != "b":
            raise SampleRejected(f"{spec.path} holds {arr.dtype} values where the run expects bool")
        out = arr
    if spec.low is not None and spec.high is not None and out.size:
        inside = (out >= spec.low) & (out <= spec.high)
        if not inside.all():
            raise SampleRejected(
                f"{spec.path} holds a value outside the action space (sample {_first_false(inside)})"
            )
    return out


def _first_false(mask: np.ndarray) -> int:
    """Index of the first sample (leading axis) where ``mask`` has a False."""
    flat = mask.reshape(len(mask), -1).all(axis=1) if mask.ndim > 1 else mask
    return int(np.argmin(flat))


class Rows(list):  # type: ignore[type-arg]
    """A column given as one value per sample (irregular data that was not stacked on the wire):
    :meth:`SampleSchema.check` transposes containers and stacks leaves."""


def _transpose(spec: Any, rows: Rows, n: int) -> Any:
    """``rows`` (one container per sample) as the container of columns that ``spec`` expects."""
    if len(rows) != n:
        raise SampleRejected(f"{_node_path(spec)} has {len(rows)} values for {n} samples")
    if spec[0] == "seq":
        k = len(spec[1])
        if not all(isinstance(r, (tuple, list)) and len(r) == k for r in rows):
            raise SampleRejected(f"{_node_path(spec)} is not a sequence of {k} in every sample")
        return tuple(Rows(r[i] for r in rows) for i in range(k))
    keys = spec[1]
    if not all(isinstance(r, dict) and len(r) == len(keys) and all(k in r for k in keys) for r in rows):
        raise SampleRejected(f"{_node_path(spec)} does not have the keys {keys} in every sample")
    return {k: Rows(r[k] for r in rows) for k in keys}


def _check_tree(spec: Any, value: Any, n: int) -> Any:
    if isinstance(value, Rows):
        if isinstance(spec, LeafSpec):
            if any(isinstance(v, (tuple, list, dict)) or v is None for v in value):
                raise SampleRejected(f"{spec.path} is not an array in every sample")
            return _check_leaf(spec, list(value), n)
        value = _transpose(spec, value, n)
    if isinstance(spec, LeafSpec):
        if isinstance(value, (tuple, list, dict)) or value is None:
            raise SampleRejected(f"{spec.path} is a {type(value).__name__} where the run expects an array")
        return _check_leaf(spec, value, n)
    if spec[0] == "seq":
        children = spec[1]
        if not isinstance(value, (tuple, list)) or len(value) != len(children):
            raise SampleRejected(
                f"{_node_path(spec)} has {_node_str(value)} where the run expects a sequence of {len(children)}"
            )
        checked = [_check_tree(c, v, n) for c, v in zip(children, value)]
        return tuple(checked) if isinstance(value, tuple) else checked
    keys, children = spec[1], spec[2]
    if not isinstance(value, dict) or set(value) != set(keys) or len(value) != len(keys):
        raise SampleRejected(f"{_node_path(spec)} has {_node_str(value)} where the run expects keys {keys}")
    return {k: _check_tree(c, value[k], n) for k, c in zip(keys, children)}


def _node_path(spec: Any) -> str:
    leaves = _tree_leaves(spec)
    if not leaves:
        return "obs"
    path = leaves[0].path
    return path[: path.rfind("[")] if "[" in path else path


def _node_str(value: Any) -> str:
    if isinstance(value, (tuple, list)):
        return f"a sequence of {len(value)}"
    if isinstance(value, dict):
        return f"keys {sorted(map(str, value))[:10]}"
    return "an array" if isinstance(value, np.ndarray) else type(value).__name__


def _sample_value(space: Any, what: str) -> Any:
    sample = getattr(space, "sample", None)
    if not callable(sample):
        raise UserError(f"the {what} space {space!r} has no sample(): use a Gymnasium space")
    try:
        probe = copy.deepcopy(space)  # seeded on a copy: the user's space keeps its RNG stream
        probe.seed(0)
        sample = probe.sample
    except Exception:  # noqa: BLE001, S110 (a space that cannot be copied or seeded: sample it as is)
        pass
    return sample()


class SampleSchema:
    """What a run's samples look like on the wire, derived from the trainer's spaces.

    Args:
        observation_space: the observation space of the trainer's environment.
        action_space: its action space.
        obs_preprocessor: the workers' ``obs_preprocessor`` (``None``: none).
        sample_compressor: the workers' ``sample_compressor`` (``None``: none).

    Raises:
        UserError: the spaces cannot be sampled, or the preprocessor or compressor fails on a
            sample of them, or produces something that is not numbers.
    """

    def __init__(
        self,
        observation_space: Any,
        action_space: Any,
        obs_preprocessor: Callable[[Any], Any] | None = None,
        sample_compressor: Callable[..., tuple] | None = None,
    ):
        act = _sample_value(action_space, "action")
        obs = _sample_value(observation_space, "observation")
        try:
            if obs_preprocessor is not None:
                obs = obs_preprocessor(obs)
            if sample_compressor is not None:
                act, obs, *_ = sample_compressor(act, obs, 0.0, False, False, {})
        except Exception as err:  # noqa: BLE001 (user code: any failure is reported in one line)
            detail = " ".join(str(err).split())[:200]
            raise UserError(
                f"cannot derive the run's sample schema: the obs_preprocessor or sample_compressor "
                f"fails on a sample of the spaces ({type(err).__name__}: {detail}); give the trainer the "
                "same ones as the workers"
            ) from None
        self.action = _action_bounds(action_space, _leaf_from_value(act, "act"))
        self.obs = _tree_from_value(obs, "obs")
        self.leaves = _tree_leaves(self.obs)

    def describe(self) -> dict[str, Any]:
        """A data-only description: ``{"act": leaf, "obs": tree}`` (leaves give path, shape, dtype)."""
        return {"act": self.action.describe(), "obs": _tree_describe(self.obs)}

    def __repr__(self) -> str:
        leaves = ", ".join(f"{leaf.path}{_shape_str(leaf.shape)}:{leaf.dtype}" for leaf in self.leaves)
        return f"SampleSchema(act{_shape_str(self.action.shape)}:{self.action.dtype}, {leaves})"

    def check(
        self,
        n: int,
        act: Any,
        act_none: np.ndarray | None,
        obs: Any,
        rew: Any,
        terminated: Any,
        truncated: Any,
    ) -> SampleColumns:
        """Check a batch of ``n`` samples given as columns and cast them to the schema's dtypes.

        Args:
            n: number of samples.
            act: the actions that are not ``None`` stacked (``(k, *shape)``), or ``None``.
            act_none: ``None`` or a bool mask ``(n,)`` of the samples whose action is ``None``.
            obs: the observations as a tree of stacked arrays (the schema's structure).
            rew: rewards, an array (or sequence) of ``n`` values.
            terminated: ``terminated`` flags, ``n`` values.
            truncated: ``truncated`` flags, ``n`` values.

        Returns:
            The checked :class:`SampleColumns` (arrays are cast; unchanged ones are not copied).

        Raises:
            SampleRejected: the first problem found (shape, dtype, non-finite or out-of-range value).
        """
        with np.errstate(over="ignore", invalid="ignore"):  # overflows are what the checks find
            return self._check(n, act, act_none, obs, rew, terminated, truncated)

    def _check(
        self, n: int, act: Any, act_none: Any, obs: Any, rew: Any, terminated: Any, truncated: Any
    ) -> SampleColumns:
        known = n if act_none is None else n - int(np.count_nonzero(act_none))
        if act_none is not None and (not isinstance(act_none, np.ndarray) or act_none.shape != (n,)):
            raise SampleRejected("malformed mask of None actions")
        checked_act = None
        if known:
            if act is None:
                raise SampleRejected("act is missing")
            checked_act = _check_leaf(self.action, act, known)
        checked_obs = _check_tree(self.obs, obs, n)
        rew = _as_array(rew, "rew")
        if rew.shape != (n,) or rew.dtype.kind not in "iuf":
            raise SampleRejected(f"rew must be {n} real numbers, not {rew.dtype} of shape {rew.shape}")
        rew = rew.astype(np.float64, copy=False)
        finite = np.isfinite(rew.astype(np.float32))  # the memory stores rewards as float32
        if not finite.all():
            raise SampleRejected(f"rew holds a non-finite value (sample {_first_false(finite)})")
        flags = [_check_flags(_as_array(f, name), name, n) for f, name in ((terminated, "terminated"), (truncated, "truncated"))]
        return SampleColumns(checked_act, act_none, checked_obs, rew, flags[0], flags[1])


def _as_array(value: Any, what: str) -> np.ndarray:
    if isinstance(value, (tuple, dict)) or (isinstance(value, list) and not isinstance(value, Rows)):
        raise SampleRejected(f"{what} is a {type(value).__name__} where the run expects an array")
    try:
        return np.asarray(value)
    except (ValueError, TypeError, OverflowError):
        raise SampleRejected(f"{what} is not an array of numbers") from None


def _check_flags(arr: np.ndarray, what: str, n: int) -> np.ndarray:
    if arr.shape != (n,):
        raise SampleRejected(f"{what} must be {n} flags, not shape {arr.shape}")
    if arr.dtype.kind == "b":
        return arr
    if arr.dtype.kind in "iu" and (not arr.size or (arr.min() >= 0 and arr.max() <= 1)):
        return arr.astype(bool)
    raise SampleRejected(f"{what} must be booleans, not {arr.dtype}")


def finite_stat(value: Any) -> float | None:
    """``value`` as a float when it is a finite real number (not a bool), else ``None``."""
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, float, np.integer, np.floating)):
        return None
    try:
        f = float(value)
    except (OverflowError, ValueError):
        return None
    return f if math.isfinite(f) else None


MAX_PINNED_SAMPLE_BYTES = 64 << 20
"""Largest sample a pinned schema accepts (all leaves together), in bytes."""


def _first_sample(tree: Any) -> Any:
    """The first sample of a tree of stacked columns (leaves ``(n, ...)``)."""
    if isinstance(tree, Rows):
        return tree[0]
    if isinstance(tree, (tuple, list)):
        return type(tree)(_first_sample(t) for t in tree)
    if isinstance(tree, dict):
        return {k: _first_sample(v) for k, v in tree.items()}
    return np.asarray(tree)[0]


class PinnedSampleSchema(SampleSchema):
    """A schema whose observation and action shapes are fixed by the first batch it checks.

    For library scripts that give the ``Trainer`` neither the workers' ``obs_preprocessor`` nor
    their ``sample_compressor`` (tmrl 0.7's scripts do not): the trainer then cannot derive what a
    compressed sample looks like. Every batch is still checked (numbers only, finite floats,
    actions within the action space when they have its shape, flags, rewards), and every batch
    after the first must have the first one's structure, shapes and dtypes, so that the memory
    never sees two layouts. The first batch does decide the shapes here: give the ``Trainer`` the
    workers' functions for a :class:`SampleSchema` derived from the spaces instead.

    Args:
        action_space: the run's action space (for the bounds of actions).
    """

    def __init__(self, action_space: Any):  # noqa: D107 (documented on the class)
        self.action_space = action_space
        self.pinned = False
        self.action = LeafSpec("act", (), np.dtype(np.float32))
        self.obs: Any = None
        self.leaves: list[LeafSpec] = []

    def describe(self) -> dict[str, Any]:
        """As :meth:`SampleSchema.describe`; ``{"pinned": False}`` before the first batch."""
        return super().describe() if self.pinned else {"pinned": False}

    def __repr__(self) -> str:
        return super().__repr__() if self.pinned else "PinnedSampleSchema(shapes fixed by the first batch)"

    def _pin(self, n: int, act: Any, act_none: Any, obs: Any) -> None:
        known = n if act_none is None else n - int(np.count_nonzero(act_none))
        if known == 0 or act is None:
            raise SampleRejected("the first batch has no action to fix the action's shape from")
        try:
            tree = _tree_from_value(_first_sample(obs), "obs")
            action = _leaf_from_value(np.asarray(act)[0], "act")
        except (UserError, IndexError, TypeError, ValueError) as err:
            raise SampleRejected(f"the first batch cannot fix the sample layout ({err})") from None
        leaves = [action, *_tree_leaves(tree)]
        size = sum(int(np.prod(leaf.shape, dtype=np.int64)) * leaf.dtype.itemsize for leaf in leaves)
        if any(0 in leaf.shape for leaf in leaves) or size > MAX_PINNED_SAMPLE_BYTES:
            raise SampleRejected(f"the first batch has samples of {size} bytes or an empty array: refused")
        self.action = _action_bounds(self.action_space, action)
        self.obs, self.leaves, self.pinned = tree, _tree_leaves(tree), True

    def _check(
        self, n: int, act: Any, act_none: Any, obs: Any, rew: Any, terminated: Any, truncated: Any
    ) -> SampleColumns:
        if not self.pinned:
            self._pin(n, act, act_none, obs)
            try:
                return super()._check(n, act, act_none, obs, rew, terminated, truncated)
            except SampleRejected:
                self.pinned = False  # a bad first batch fixes nothing
                raise
        return super()._check(n, act, act_none, obs, rew, terminated, truncated)
