"""Where a built-in memory keeps its samples: :class:`RingStorage` (the preallocated ring arrays and
the write counter), :class:`RestoreWindow` (which saved rows a checkpoint restore writes where),
and the Protocols of the buffers a memory reads samples from (:class:`SampleBuffer`,
:class:`ColumnBuffer`, :data:`SampleColumns`).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any, Protocol, runtime_checkable

import numpy as np

from tmrl.errors import UserError
from tmrl.memory.tree import (
    _columns,
    _leaf_paths,
    _make_spec,
    _stack,
    _storage_dtype,
    _tree_leaves,
    _unflatten,
)

__all__ = ["ColumnBuffer", "RestoreWindow", "RingStorage", "SampleBuffer", "SampleColumns"]


# ==== the network buffer contract =================================================================

SampleColumns = tuple[Any, Any, np.ndarray, np.ndarray, np.ndarray]
"""What :meth:`ColumnBuffer.as_columns` returns: ``(act, obs, rew, terminated, truncated)``.
``act`` is an array of shape ``(n, *action_shape)`` (zeros where a sample's action was
``None``) or ``None`` when every action was ``None``; ``obs`` has the structure of one
observation with an array of shape ``(n, *leaf_shape)`` at each leaf; the others are 1-D."""


class SampleBuffer(Protocol):
    """What every buffer handed to :meth:`Memory.append_buffer` offers (``tmrl.networking.Buffer``
    and the plain objects of tests and benchmarks).

    Attributes:
        memory: the samples ``(act, new_obs, rew, terminated, truncated, info)``, oldest first.
        sources: ``None``, or the integer source id of the worker that produced each sample
            (optional: a buffer without the attribute counts as one source).
    """

    memory: Sequence[Any]
    sources: Sequence[int] | None


@runtime_checkable
class ColumnBuffer(Protocol):
    """A buffer that can also hand its samples over as stacked columns, without one tuple per
    sample (``tmrl.networking.Buffer`` received from the network).

    ``isinstance(buffer, ColumnBuffer)`` checks only ``as_columns``: on Python 3.11 a runtime
    check reads every member, and reading ``memory`` on a received buffer builds the tuples that
    the columns exist to avoid.
    """

    def as_columns(self) -> SampleColumns | None:
        """The samples as :data:`SampleColumns`, or ``None`` when they are not all in that form
        (then read ``memory``)."""
        ...


# ==== the parts of the array-shaped memories ======================================================


def _ring_write(buf: Any, counter: int, rows: Any) -> None:
    """Write ``rows`` into the ring ``buf`` (array or list of ``capacity`` slots) from the slot of
    absolute counter ``counter`` on, wrapping around at the end."""
    cap = len(buf)
    m = len(rows)
    pos = counter % cap
    first = min(m, cap - pos)
    buf[pos : pos + first] = rows[:first]
    if first < m:
        buf[: m - first] = rows[first:]


@dataclass(frozen=True)
class RestoreWindow:
    """The absolute counters ``[floor, total)`` that a restore fills from a checkpoint's rows.

    Attributes:
        total: the saved write counter.
        saved_oldest: the oldest counter the checkpoint holds.
        floor: the oldest counter restored: ``saved_oldest``, or later when this memory is smaller
            than the saved one.
    """

    total: int
    saved_oldest: int
    floor: int

    @classmethod
    def of(cls, meta: Mapping[str, Any], capacity: int) -> RestoreWindow:
        """The window of a saved ``ring_meta`` restored into ``capacity`` slots."""
        total = int(meta["total"])
        saved_oldest = int(meta.get("oldest", total - min(total, int(meta["capacity"]))))
        return cls(total, saved_oldest, max(saved_oldest, total - min(total, capacity)))

    def fill(self, name: str, buf: np.ndarray, rows: Callable[[str], tuple[int, np.ndarray]]) -> None:
        """Write the saved rows of array ``name`` for counters ``[floor, total)`` into ``buf``.

        Args:
            name: the array's key in ``ring_arrays``.
            buf: the ring array to fill.
            rows: ``rows(name)`` returns ``(first_counter, array)`` ending at ``total``.

        Raises:
            ValueError: the saved rows do not cover the window or have another row shape.
        """
        first, arr = rows(name)
        if first + len(arr) != self.total:
            raise ValueError(f"memory array {name} ends at sample {first + len(arr)}, expected {self.total}")
        if first > self.saved_oldest:
            raise ValueError(f"memory array {name} starts at sample {first}, expected {self.saved_oldest} or earlier")
        if arr.shape[1:] != buf.shape[1:]:
            raise ValueError(f"memory array {name} has rows of shape {arr.shape[1:]}, expected {buf.shape[1:]}")
        _ring_write(buf, self.floor, arr[self.floor - first :])


class RingStorage:
    """The preallocated ring arrays of a replay memory and its write counter.

    The sample with absolute counter ``c`` lives in slot ``c % capacity``. Observation leaves
    (nested tuples, lists and dicts flattened depth-first) and actions are allocated from the first
    sample that has them; float64 is stored as float32.

    Args:
        capacity: number of slots.
        store_info: also keep each sample's ``info`` (Python objects, not checkpointed).

    Attributes:
        capacity: number of slots.
        total: absolute counter of the next sample.
        floor: counters below it were never stored here (a restore into a bigger memory).
        obs_spec: JSON-able description of the observation structure (``None`` when empty).
        obs: one ring array per observation leaf, shape ``(capacity, *leaf_shape)``.
        act: the actions, ``(capacity, *action_shape)``; ``None`` before the first action.
        rew: per-slot float32 rewards.
        terminated: per-slot bool flags, the episode ended at this sample.
        truncated: per-slot bool flags, the episode was cut at this sample.
        count: the absolute counter each slot was written with (-1: never written).
        infos: per-slot infos when ``store_info``, else ``None``.
    """

    def __init__(self, capacity: int, store_info: bool = False) -> None:
        self.capacity = int(capacity)
        self.total = 0
        self.floor = 0
        self.obs_spec: list | None = None
        self.obs: list[np.ndarray] = []
        self.act: np.ndarray | None = None
        self.rew = np.zeros(self.capacity, dtype=np.float32)
        self.terminated = np.zeros(self.capacity, dtype=bool)
        self.truncated = np.zeros(self.capacity, dtype=bool)
        self.count = np.full(self.capacity, -1, dtype=np.int64)
        self.infos: list[Any] | None = [None] * self.capacity if store_info else None

    @property
    def size(self) -> int:
        """Number of filled slots."""
        return min(self.total, self.capacity)

    @property
    def oldest(self) -> int:
        """Absolute counter of the oldest sample held."""
        return max(self.total - self.size, self.floor)

    # --- rows to write -------------------------------------------------------------------------

    def obs_rows(self, obs: list[Any]) -> list[np.ndarray]:
        """One array per leaf from a list of observations (the first one fixes the structure).

        Args:
            obs: the observations, one per sample, all of the stored structure.

        Raises:
            UserError: the structure or a leaf's shape differs from the stored ones, or a leaf is
                not numeric.
        """
        spec = _make_spec(obs[0], [0]) if self.obs_spec is None else self.obs_spec
        columns: list[list[Any]] = []
        _columns(spec, obs, columns, "obs")
        paths = _leaf_paths(spec)
        return self._checked_leaves([_stack(col, path) for col, path in zip(columns, paths)], spec, paths)

    def obs_column_rows(self, tree: Any, keep: slice) -> list[np.ndarray]:
        """:meth:`obs_rows` for observations already stacked leaf by leaf (``tree`` has the
        structure of one observation, an array of all samples at each leaf), rows ``keep``."""
        spec = _make_spec(tree, [0]) if self.obs_spec is None else self.obs_spec
        leaves: list[Any] = []
        _tree_leaves(spec, tree, leaves, "obs")
        return self._checked_leaves([leaf[keep] for leaf in leaves], spec, _leaf_paths(spec))

    def _checked_leaves(self, arrays: list[np.ndarray], spec: list, paths: list[str]) -> list[np.ndarray]:
        if self.obs_spec is None:
            # Lazy allocation: shapes and dtypes come from the first sample.
            self.obs = [np.zeros((self.capacity, *a.shape[1:]), dtype=_storage_dtype(a)) for a in arrays]
            self.obs_spec = spec
        for arr, buf, path in zip(arrays, self.obs, paths):
            if arr.shape[1:] != buf.shape[1:]:
                raise UserError(
                    f"{path} has shape {arr.shape[1:]} but earlier samples had {buf.shape[1:]}: "
                    "observations must keep one shape"
                )
            if arr.dtype == object:
                _storage_dtype(arr)
        return arrays

    def act_rows(self, acts: list[Any]) -> np.ndarray | None:
        """The actions of a list of samples as one array (zeros for ``None``), or ``None`` when
        every action is ``None`` (the zeros already in the ring stand for them).

        Args:
            acts: the samples' actions (``None`` for a sample without one).

        Raises:
            UserError: actions change shape or are not numeric.
        """
        first = next((a for a in acts if a is not None), None)
        if first is None:
            return None
        if any(a is None for a in acts):
            ref = np.asarray(first) if self.act is None else self.act[0]
            zeros = np.zeros(ref.shape, dtype=_storage_dtype(ref))
            acts = [zeros if a is None else a for a in acts]
        arr = _stack(acts, "the action")
        _storage_dtype(arr)  # refuses non-numeric actions with the one-line error
        return self.act_column_rows(arr, slice(None))

    def act_column_rows(self, act: np.ndarray | None, keep: slice) -> np.ndarray | None:
        """Rows ``keep`` of actions already stacked (zeros where they were ``None``); allocates
        the action ring from the first ones.

        Args:
            act: the stacked actions ``(n, *action_shape)``, or ``None`` when every action was
                ``None`` (then ``None`` is returned).
            keep: the rows to keep.

        Raises:
            UserError: the action shape differs from the stored one.
        """
        if act is None:
            return None
        act = act[keep]
        if self.act is None:
            self.act = np.zeros((self.capacity, *act.shape[1:]), dtype=_storage_dtype(act))
        if act.shape[1:] != self.act.shape[1:]:
            raise UserError(
                f"an action has shape {act.shape[1:]} but earlier actions had {self.act.shape[1:]}: "
                "actions must keep one shape"
            )
        return act

    # --- writing and reading -------------------------------------------------------------------

    def write(self, start: int, obs: list[np.ndarray], act: np.ndarray | None, rew: np.ndarray,
              terminated: np.ndarray, truncated: np.ndarray, infos: list[Any] | None = None) -> None:
        """Write rows for the consecutive counters from ``start`` on (``total`` is not moved).

        Args:
            start: absolute counter of the first row.
            obs: rows of each leaf, from :meth:`obs_rows` or :meth:`obs_column_rows`.
            act: action rows, or ``None`` to leave the zeros of ``None`` actions.
            rew: 1-D rows of rewards.
            terminated: 1-D rows of ``terminated`` flags.
            truncated: 1-D rows of ``truncated`` flags.
            infos: the samples' infos (stored only when infos are kept).
        """
        for buf, rows in zip(self.obs, obs):
            _ring_write(buf, start, rows)
        if act is not None:
            _ring_write(self.act, start, act)
        _ring_write(self.rew, start, rew)
        _ring_write(self.terminated, start, terminated)
        _ring_write(self.truncated, start, truncated)
        _ring_write(self.count, start, start + np.arange(len(rew), dtype=np.int64))
        if self.infos is not None and infos is not None:
            _ring_write(self.infos, start, infos)

    def observations(self, slots: np.ndarray) -> Any:
        """The observations at ``slots``: the stored structure with batched leaves."""
        assert self.obs_spec is not None
        return _unflatten(self.obs_spec, [leaf[slots] for leaf in self.obs])

    # --- checkpoint part -----------------------------------------------------------------------

    def arrays(self) -> dict[str, np.ndarray]:
        """The per-slot arrays of this part, by checkpoint name (only those allocated)."""
        arrays = {"rew": self.rew, "terminated": self.terminated, "truncated": self.truncated, "count": self.count}
        if self.act is not None:
            arrays["act"] = self.act
        for i, leaf in enumerate(self.obs):
            arrays[f"obs.{i}"] = leaf
        return arrays

    def meta(self) -> dict[str, Any]:
        """This part's JSON-able checkpoint keys."""
        return {
            "capacity": self.capacity,
            "total": self.total,
            "obs_spec": self.obs_spec,
            "leaves": [[str(a.dtype), list(a.shape[1:])] for a in self.obs],
            "act": None if self.act is None else [str(self.act.dtype), list(self.act.shape[1:])],
            "oldest": self.oldest,
        }

    def restore(self, meta: Mapping[str, Any], window: RestoreWindow,
                rows: Callable[[str], tuple[int, np.ndarray]]) -> None:
        """Reallocate from a saved :meth:`meta` and fill the window's rows.

        Raises:
            ValueError: the saved rows do not fit (see :meth:`RestoreWindow.fill`).
        """
        cap = self.capacity
        self.obs_spec = meta["obs_spec"]
        self.obs = [np.zeros((cap, *shape), dtype=np.dtype(dt)) for dt, shape in meta["leaves"]]
        act = meta["act"]
        self.act = None if act is None else np.zeros((cap, *act[1]), dtype=np.dtype(act[0]))
        self.rew[:] = 0
        self.terminated[:] = False
        self.truncated[:] = False
        self.count[:] = -1
        if self.infos is not None:
            self.infos = [None] * cap
        for name, buf in self.arrays().items():
            window.fill(name, buf, rows)
        self.total = window.total
        self.floor = window.floor
