"""Replay memories: the user-facing :class:`Memory` API and the built-in array-shaped memories.

Two ways to use this module:

* Subclass :class:`TorchMemory` and implement ``append_buffer``, ``__len__`` and
  ``get_transition`` (the tutorial's way). Sampling then goes through the *slow path*: one
  ``get_transition`` call per item, the CRC check, the ``sample_preprocessor``, then
  :func:`collate_torch`.
* Use :class:`GenericTorchMemory` (any observation structure) or :class:`RealTimeTorchMemory`
  (rebuilds the action buffer of real-time environments). They store samples in preallocated
  NumPy ring buffers and build a whole batch with a few vectorised gathers (the *fast path*).
  They are composed of three parts, each with its share of the checkpoint state:
  :class:`RingStorage` (the ring arrays and the write counter), :class:`EpisodeLinks` (which
  slot precedes which, per worker and episode) and :class:`SlotSampler` (draws valid slots).

What a memory reads from the buffers it is given is typed by :class:`SampleBuffer` and, for
buffers received from the network that hand over stacked arrays, :class:`ColumnBuffer`.

Vocabulary (see docs/internals.md): a *sample* is ``(act, new_obs, rew, terminated, truncated,
info)`` as recorded by a worker; a *transition* is ``(prev_obs, act, rew, new_obs, terminated,
truncated, info)``; a *batch* is a collated list of transitions without ``info``, handed over as a
:class:`tmrl.batch.Batch` (a NamedTuple, so positional unpacking works).
"""

from __future__ import annotations

import logging
import uuid
from abc import ABC, abstractmethod
from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol, runtime_checkable

import numpy as np
import torch

from tmrl.batch import Batch
from tmrl.errors import UserError

__all__ = [
    "Batch",
    "CRCMismatchError",
    "ColumnBuffer",
    "EpisodeLinks",
    "GenericTorchMemory",
    "Memory",
    "RealTimeTorchMemory",
    "RestoreWindow",
    "RingStorage",
    "SampleBuffer",
    "SampleColumns",
    "SlotSampler",
    "TorchMemory",
    "check_transition",
    "collate_torch",
    "to_torch",
]

logger = logging.getLogger(__name__)

_TRANSITION_FIELDS = ("prev_obs", "act", "new_obs", "rew", "terminated", "truncated")


class CRCMismatchError(UserError):
    """``crc_debug``: a transition rebuilt by the memory differs from the one the worker saw."""


# ==== collation ===================================================================================


def _move(tensor: torch.Tensor, device: Any) -> torch.Tensor:
    """Move a CPU tensor to ``device``; through pinned memory and a non-blocking copy for CUDA."""
    if device is None:
        return tensor
    dev = torch.device(device)
    if dev.type == "cpu":
        return tensor
    if dev.type == "cuda":
        # Pinned host memory lets the host-to-device copy run asynchronously; the training step
        # that consumes the batch is queued on the same stream, so ordering is preserved.
        return tensor.pin_memory().to(dev, non_blocking=True)
    return tensor.to(dev)


def _array_to_tensor(arr: np.ndarray, device: Any) -> torch.Tensor:
    if arr.dtype == np.float64:
        # NumPy's default float is float64; models are float32, so batches are too.
        arr = arr.astype(np.float32)
    elif arr.dtype == object:
        raise UserError(
            "cannot collate a non-numeric observation or action element into a tensor: "
            "make the obs_preprocessor/sample_compressor produce arrays or numbers"
        )
    return _move(torch.from_numpy(np.ascontiguousarray(arr)), device)


def to_torch(tree: Any, device: Any = None) -> Any:
    """Convert a nested structure whose leaves are already-batched NumPy arrays into the same
    structure with tensors on ``device`` (float64 becomes float32; tuples stay tuples, lists stay
    lists, dicts stay dicts).

    Args:
        tree: nested tuples/lists/dicts of arrays (or tensors).
        device: target device; ``None`` leaves tensors on the CPU.

    Returns:
        The same structure with ``torch.Tensor`` leaves.
    """
    if isinstance(tree, torch.Tensor):
        return _move(tree, device)
    if isinstance(tree, np.ndarray):
        return _array_to_tensor(tree, device)
    if isinstance(tree, Mapping):
        return {k: to_torch(v, device) for k, v in tree.items()}
    if isinstance(tree, tuple) and hasattr(tree, "_fields"):  # namedtuple
        return type(tree)(*(to_torch(v, device) for v in tree))
    if isinstance(tree, (tuple, list)):
        return type(tree)(to_torch(v, device) for v in tree)
    return _array_to_tensor(np.asarray(tree), device)


def collate_torch(batch: Sequence[Any], device: Any = None) -> Any:
    """Collate a list of nested structures (NumPy arrays, numbers or tensors as leaves) into one
    structure of batched tensors on ``device``.

    Sequences are transposed (a batch of observation tuples becomes a tuple of stacked tensors),
    mappings are collated key by key, leaves are stacked along a new first dimension. float64
    leaves become float32. :meth:`Memory.__getitem__` returns ``rew``, ``terminated`` and
    ``truncated`` as ``np.float32``, so they collate to float32 tensors of shape ``(B,)``.

    Args:
        batch: a non-empty list of items with the same structure.
        device: target device (``"cpu"``, ``"cuda"``...); CUDA copies use pinned memory and
            ``non_blocking=True``.

    Returns:
        The collated structure.

    Raises:
        UserError: a leaf is ``None`` or not numeric.
    """
    elem = batch[0]
    if isinstance(elem, torch.Tensor):
        stacked = torch.stack(list(batch))
        if stacked.dtype == torch.float64:
            stacked = stacked.float()
        return _move(stacked, device)
    if isinstance(elem, np.ndarray):
        return _array_to_tensor(np.stack(batch), device)
    if isinstance(elem, Mapping):
        return {key: collate_torch([d[key] for d in batch], device) for key in elem}
    if isinstance(elem, tuple) and hasattr(elem, "_fields"):
        return type(elem)(*(collate_torch(list(col), device) for col in zip(*batch)))
    if isinstance(elem, (tuple, list)):
        return type(elem)(collate_torch(list(col), device) for col in zip(*batch))
    if elem is None:
        raise UserError(
            "cannot collate None: only the first sample of an episode may have a None action, "
            "and it never starts a transition; check the memory's get_transition"
        )
    return _array_to_tensor(np.asarray(batch), device)


# ==== CRC debugging ===============================================================================


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


# ==== the Memory API ==============================================================================


def _seed_from_global() -> int:
    # Drawn from NumPy's global generator so that np.random.seed(...) makes sampling reproducible.
    return int(np.random.randint(0, 2**31 - 1))


class Memory(ABC):
    """A replay memory: stores what workers send and samples training batches.

    Subclasses implement :meth:`append_buffer`, :meth:`__len__`, :meth:`get_transition` and
    :meth:`collate` (:class:`TorchMemory` provides ``collate``). When overriding ``__init__``, call
    ``super().__init__`` and accept at least the same arguments.

    Args:
        device: device on which batches are collated (``"cpu"``, ``"cuda"``...).
        nb_steps: number of batches one iteration over the memory yields (steps per round).
        sample_preprocessor: optional ``f(prev_obs, act, rew, new_obs, terminated, truncated)``
            returning the same six values, applied to every sampled transition (augmentation).
        memory_size: capacity, in samples.
        batch_size: transitions per batch.
        dataset_path: optional folder of a tmrl checkpoint (or saved memory) whose samples
            pre-fill built-in memories; ignored by user memories. Empty: start empty.
        crc_debug: check every sampled transition against the full sample the worker stored in
            ``info["crc_sample"]`` (pipeline debugging; slow).

    Attributes:
        data: list where user memories keep their samples (starts empty, as in the tutorial).
        stat_train_return: the workers' latest training episode return, copied by :meth:`append`.
        stat_test_return: the workers' latest test episode return, copied by :meth:`append`.
        stat_train_steps: the workers' latest training episode length, copied by :meth:`append`.
        stat_test_steps: the workers' latest test episode length, copied by :meth:`append`.
        rng: the NumPy generator used to draw batch indices.
    """

    def __init__(
        self,
        device: Any,
        nb_steps: int,
        sample_preprocessor: Callable[..., tuple] | None = None,
        memory_size: int = 1000000,
        batch_size: int = 256,
        dataset_path: str = "",
        crc_debug: bool = False,
    ) -> None:
        if int(memory_size) < 1:
            raise UserError(f"memory_size must be at least 1, got {memory_size}: fix MEMORY_SIZE")
        if int(batch_size) < 1:
            raise UserError(f"batch_size must be at least 1, got {batch_size}: fix BATCH_SIZE")
        self.device = device
        self.nb_steps = nb_steps
        self.sample_preprocessor = sample_preprocessor
        self.memory_size = int(memory_size)
        self.batch_size = int(batch_size)
        self.dataset_path = dataset_path
        self.crc_debug = bool(crc_debug)
        self.data: list[Any] = []
        self.stat_train_return = 0.0
        self.stat_test_return = 0.0
        self.stat_train_steps = 0
        self.stat_test_steps = 0
        self.rng = np.random.default_rng(_seed_from_global())
        if dataset_path and Path(dataset_path, "data.pkl").is_file():
            raise UserError(
                f"{Path(dataset_path, 'data.pkl')} is a pickled dataset, which tmrl never loads "
                "(pickle can run code): point dataset_path to a tmrl checkpoint folder or leave it empty"
            )

    # --- to implement --------------------------------------------------------------------------

    @abstractmethod
    def append_buffer(self, buffer: Any) -> None:
        """Store the samples of ``buffer`` (a ``tmrl.networking.Buffer``: ``buffer.memory`` is a
        list of ``(act, new_obs, rew, terminated, truncated, info)``, oldest first)."""
        raise NotImplementedError

    @abstractmethod
    def __len__(self) -> int:
        """Number of transitions that can be sampled: ``get_transition`` accepts ``0..len-1``."""
        raise NotImplementedError

    @abstractmethod
    def get_transition(self, item: int) -> tuple:
        """Rebuild one transition.

        Args:
            item: an index below ``len(self)`` (for the built-in memories: a slot number).

        Returns:
            ``(prev_obs, act, rew, new_obs, terminated, truncated, info)``; ``info`` must be the
            sample's info dict when CRC debugging is used.
        """
        raise NotImplementedError

    @abstractmethod
    def collate(self, batch: list[tuple], device: Any) -> tuple:
        """Turn a list of ``(prev_obs, act, rew, new_obs, terminated, truncated)`` into one batch
        of tensors on ``device``.

        Args:
            batch: the transitions (as :meth:`get_transition` returns them).
            device: where the tensors go.
        """
        raise NotImplementedError

    # --- provided ------------------------------------------------------------------------------

    def append(self, buffer: Any) -> None:
        """Copy the episode statistics of ``buffer`` and store its samples (nothing happens for an
        empty buffer)."""
        if len(buffer) == 0:
            return
        self.stat_train_return = buffer.stat_train_return
        self.stat_test_return = buffer.stat_test_return
        self.stat_train_steps = buffer.stat_train_steps
        self.stat_test_steps = buffer.stat_test_steps
        self.append_buffer(buffer)

    def __iter__(self) -> Iterator[Batch]:
        """Yield ``nb_steps`` batches."""
        for _ in range(int(self.nb_steps)):
            yield self.sample()

    def __getitem__(self, item: int) -> tuple:
        """One transition ready for collation: ``get_transition``, then the CRC check (when
        ``crc_debug``), then ``sample_preprocessor``; ``rew``, ``terminated`` and ``truncated``
        are returned as ``np.float32``.

        Returns:
            ``(prev_obs, act, rew, new_obs, terminated, truncated)``.
        """
        prev_obs, act, rew, new_obs, terminated, truncated, info = self.get_transition(item)
        if self.crc_debug:
            check_transition(item, (prev_obs, act, new_obs, rew, terminated, truncated), info)
        if self.sample_preprocessor is not None:
            prev_obs, act, rew, new_obs, terminated, truncated = self.sample_preprocessor(
                prev_obs, act, rew, new_obs, terminated, truncated
            )
        return prev_obs, act, np.float32(rew), new_obs, np.float32(terminated), np.float32(truncated)

    def sample_indices(self) -> np.ndarray:
        """Draw ``batch_size`` indices uniformly in ``range(len(self))`` (with replacement).

        Raises:
            ValueError: the memory holds no transition yet.
        """
        length = len(self)
        if length <= 0:
            raise ValueError("cannot sample from a memory that holds no transition yet")
        return self.rng.integers(0, length, size=self.batch_size)

    def sample(self, indices: Sequence[int] | np.ndarray | None = None) -> Batch:
        """Build one batch.

        Args:
            indices: the items to use; ``None`` draws ``batch_size`` of them with
                :meth:`sample_indices`.

        Returns:
            ``Batch(obs, act, rew, next_obs, terminated, truncated)`` collated by
            :meth:`collate` (a ``collate`` that returns something other than six values has
            its result returned as it is).
        """
        if indices is None:
            indices = self.sample_indices()
        collated = self.collate([self[int(i)] for i in indices], self.device)
        if isinstance(collated, (tuple, list)) and len(collated) == len(Batch._fields):
            return Batch(*collated)
        return collated


class TorchMemory(Memory, ABC):
    """A :class:`Memory` whose batches are PyTorch tensors (collated by :func:`collate_torch`).

    Same arguments as :class:`Memory`.
    """

    def collate(self, batch: list[tuple], device: Any) -> tuple:
        """Collate with :func:`collate_torch`.

        Args:
            batch: the transitions (as :meth:`get_transition` returns them).
            device: where the tensors go.
        """
        return collate_torch(batch, device)


# ==== nested observation structures ===============================================================

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


class EpisodeLinks:
    """Which slot precedes which: the per-worker episode chains over a :class:`RingStorage`.

    ``prev[j]`` is the absolute counter of the previous sample of the same worker and episode as
    slot ``j`` (-1 at an episode's first sample). The transition at slot ``j`` is valid when
    ``prev[j]`` is still held, so no transition spans a reset, two workers or an overwritten
    sample. Histories follow the links by index arithmetic, a batch at a time.

    Args:
        storage: the storage whose slots are linked (its ``capacity``, ``size``, ``oldest``).

    Attributes:
        storage: that storage.
        prev: the ring of links, int64.
        streams: per source id, ``(counter of its last sample, whether it ended an episode)``.
    """

    def __init__(self, storage: RingStorage) -> None:
        self.storage = storage
        self.prev = np.full(storage.capacity, -1, dtype=np.int64)
        self.streams: dict[int, tuple[int, bool]] = {}
        self._valid: np.ndarray | None = None

    def chain(self, start: int, done: np.ndarray, sources: Sequence[int] | None) -> np.ndarray:
        """Link new samples to their workers' streams and record where each stream now ends.

        Args:
            start: absolute counter of the first new sample (the others follow).
            done: whether each new sample ends its episode.
            sources: the source id of each new sample, or ``None`` (one source).

        Returns:
            The ``prev`` counter of each new sample (-1 at an episode's first sample).

        Raises:
            UserError: ``sources`` does not give one id per sample.
        """
        n = len(done)
        counters = start + np.arange(n, dtype=np.int64)
        src = np.zeros(n, dtype=np.int64) if sources is None else np.asarray(sources, dtype=np.int64)
        if src.shape != (n,):
            raise UserError(
                f"buffer.sources has {src.size} entries for {n} samples: it must be None or one "
                "source id per sample"
            )
        prev = np.empty(n, dtype=np.int64)
        for s in np.unique(src):  # one pass per worker, vectorised over its samples
            idx = np.flatnonzero(src == s)
            last, last_done = self.streams.get(int(s), (-1, True))
            p = np.empty(len(idx), dtype=np.int64)
            p[0] = last
            p[1:] = counters[idx[:-1]]
            pdone = np.empty(len(idx), dtype=bool)
            pdone[0] = last_done
            pdone[1:] = done[idx[:-1]]
            p[pdone] = -1
            prev[idx] = p
            self.streams[int(s)] = (int(counters[idx[-1]]), bool(done[idx[-1]]))
        return prev

    def write(self, start: int, prev: np.ndarray) -> None:
        """Store the links of the samples from counter ``start`` on (after the storage wrote
        their rows).

        Args:
            start: absolute counter of the first sample.
            prev: the previous-sample counter of each new sample, as :meth:`chain` returns them.
        """
        _ring_write(self.prev, start, prev)
        self._valid = None

    def prev_slots(self, slots: np.ndarray) -> np.ndarray:
        """The slots of the previous samples of ``slots`` (meaningful for valid slots only)."""
        return self.prev[slots] % self.storage.capacity

    def valid_slots(self) -> np.ndarray:
        """Slots ``j`` whose ``prev[j]`` is set and still held, in increasing slot order. Cached
        until the next :meth:`write` or :meth:`restore`."""
        if self._valid is None:
            # prev >= oldest also excludes prev == -1 (oldest >= 0).
            self._valid = np.flatnonzero(self.prev[: self.storage.size] >= self.storage.oldest)
        return self._valid

    def check_slots(self, indices: Any) -> np.ndarray:
        """``indices`` as an int64 array of slots of valid transitions.

        Raises:
            IndexError: a slot is out of range or holds no transition.
        """
        slots = np.asarray(indices, dtype=np.int64).reshape(-1)
        size = self.storage.size
        if slots.size and (slots.min() < 0 or slots.max() >= size):
            raise IndexError(f"slot out of range: the memory holds {size} samples")
        bad = self.prev[slots] < self.storage.oldest
        if bad.any():
            raise IndexError(
                f"slot {int(slots[bad][0])} holds no transition (first sample of an episode, or its "
                "previous sample was overwritten): use valid_slots()"
            )
        return slots

    def chain_ok(self, slots: np.ndarray, depth: int) -> np.ndarray:
        """For slots of valid transitions: whether following ``depth`` links stays inside the
        memory (or stops at an episode's first sample)."""
        cap, oldest = self.storage.capacity, self.storage.oldest
        ok = np.ones(len(slots), dtype=bool)
        ptr = self.prev[slots]
        for _ in range(depth - 1):
            live = ptr >= 0
            nxt = np.where(live, self.prev[ptr % cap], -1)
            ok &= ~(live & (nxt >= 0) & (nxt < oldest))
            ptr = np.where(live & (nxt >= oldest), nxt, -1)
        return ok

    def history_slots(self, slots: np.ndarray | Sequence[int], length: int) -> np.ndarray:
        """The slots of the ``length`` samples of the same episode ending at each of ``slots``,
        oldest first, the episode's first sample repeated before it starts (see
        :meth:`GenericTorchMemory.history_slots`)."""
        cap, oldest = self.storage.capacity, self.storage.oldest
        cur = np.asarray(slots, dtype=np.int64)
        out = np.empty((len(cur), length), dtype=np.int64)
        out[:, -1] = cur
        for k in range(2, length + 1):
            ptr = self.prev[cur]
            # Stop at the episode's start (ptr == -1) and, defensively, at overwritten samples
            # (the sampler never draws transitions whose needed history was overwritten).
            cur = np.where(ptr >= oldest, ptr % cap, cur)
            out[:, -k] = cur
        return out

    # --- checkpoint part -----------------------------------------------------------------------

    def arrays(self) -> dict[str, np.ndarray]:
        """This part's per-slot array (``prev``)."""
        return {"prev": self.prev}

    def meta(self) -> dict[str, Any]:
        """This part's JSON-able checkpoint keys (``streams``)."""
        return {"streams": [[k, v[0], v[1]] for k, v in self.streams.items()]}

    def restore(self, meta: Mapping[str, Any], window: RestoreWindow,
                rows: Callable[[str], tuple[int, np.ndarray]]) -> None:
        """Restore the links and streams from a saved :meth:`meta` and rows.

        Args:
            meta: what :meth:`meta` saved.
            window: which saved rows land in which slots (:class:`RestoreWindow`).
            rows: ``rows(name) -> (first counter, array)``: the saved rows of one array.

        Raises:
            ValueError: the saved rows do not fit (see :meth:`RestoreWindow.fill`).
        """
        self.prev[:] = -1
        window.fill("prev", self.prev, rows)
        self.streams = {int(k): (int(last), bool(done)) for k, last, done in meta["streams"]}
        self._valid = None


class SlotSampler:
    """Draws batches of slots of valid transitions, uniformly and with replacement, with the
    memory's generator.

    Args:
        links: the links that say which slots are valid.

    Attributes:
        links: those links.
        max_redraws: rounds of redrawing the slots whose history was overwritten before the
            memory is declared too small.
    """

    max_redraws = 64

    def __init__(self, links: EpisodeLinks) -> None:
        self.links = links

    def draw(self, rng: np.random.Generator, batch_size: int, depth: int = 1) -> np.ndarray:
        """Draw ``batch_size`` valid slots whose ``depth`` links are all still held.

        Args:
            rng: the generator to draw with (the memory's ``rng``).
            batch_size: how many slots.
            depth: how many links each transition's observations reach back.

        Returns:
            int64 array of slots.

        Raises:
            ValueError: no valid transition yet.
            UserError: the memory is too small to hold the history its transitions need.
        """
        valid = self.links.valid_slots()
        if len(valid) == 0:
            raise ValueError("cannot sample from a memory that holds no transition yet")
        slots = valid[rng.integers(0, len(valid), size=batch_size)]
        if depth <= 1:
            return slots
        for _ in range(self.max_redraws):
            bad = ~self.links.chain_ok(slots, depth)
            if not bad.any():
                return slots
            slots[bad] = valid[rng.integers(0, len(valid), size=int(bad.sum()))]
        raise UserError(
            f"memory_size={self.links.storage.capacity} is too small for histories of {depth} samples: "
            "increase memory_size"
        )

    # --- checkpoint part -----------------------------------------------------------------------

    @staticmethod
    def meta(rng: np.random.Generator) -> dict[str, Any]:
        """This part's JSON-able checkpoint keys (the state of ``rng``)."""
        return {"rng": rng.bit_generator.state}

    @staticmethod
    def restore(meta: Mapping[str, Any], rng: np.random.Generator) -> None:
        """Put ``rng`` back in its saved state (older checkpoints may lack it)."""
        if meta.get("rng") is not None:
            rng.bit_generator.state = meta["rng"]


# ==== built-in array-shaped memories ==============================================================


class GenericTorchMemory(TorchMemory):
    """Array-shaped replay memory for any observation structure.

    Three parts do the work: a :class:`RingStorage` gives every sample a slot in preallocated ring
    buffers (one NumPy array per observation leaf, plus actions, rewards and flags); the
    :class:`EpisodeLinks` hold the ``prev`` pointer of each slot (absolute counter of the previous
    sample of the same worker and episode, -1 at an episode's first sample); a
    :class:`SlotSampler` draws batches of valid slots. The transition at slot ``j`` is
    ``(obs[prev[j]], act[j], rew[j], obs[j], terminated[j], truncated[j])``; it is valid when
    ``prev[j]`` is still in the memory, so no transition spans a reset or an overwritten sample.
    Buffers whose ``sources`` are set are split into one stream per worker, so interleaved workers
    never mix.

    Items (``get_transition(item)``, ``sample(indices)``) are slot numbers of valid transitions;
    ``len(memory)`` is the number of valid transitions.

    float64 arrays are stored as float32. ``None`` actions (the first sample of an episode in a
    non-real-time environment) are stored as zeros; they never appear in a transition.

    Fast path: :meth:`sample` gathers a whole batch with vectorised indexing and converts it to
    tensors in one go (pinned memory and non-blocking copies on CUDA). With a
    ``sample_preprocessor`` or ``crc_debug``, it falls back to the per-item slow path.

    Args:
        device: as in :class:`Memory`.
        nb_steps: as in :class:`Memory`.
        sample_preprocessor: as in :class:`Memory`.
        memory_size: as in :class:`Memory`.
        batch_size: as in :class:`Memory`.
        dataset_path: as in :class:`Memory`.
        crc_debug: as in :class:`Memory`.
        store_info: keep each sample's ``info`` dict (Python objects, not checkpointed) so that
            ``get_transition`` returns it; implied by ``crc_debug``. Otherwise ``info`` is ``{}``.

    Attributes:
        uid: identity of this memory's history (a checkpoint appends to its own segments only).

    Subclassing (history-based memories): override :meth:`build_obs` and set
    :attr:`history_depth`; use :meth:`history_slots`, :meth:`obs_leaf` and :attr:`actions`.
    """

    history_depth: int = 1
    """How many ``prev`` links a transition's observations reach back (1: only ``prev[j]``).
    Transitions whose chain is cut by an overwritten sample within this depth are not sampled."""

    def __init__(
        self,
        device: Any = "cpu",
        nb_steps: int = 1,
        sample_preprocessor: Callable[..., tuple] | None = None,
        memory_size: int = 1000000,
        batch_size: int = 256,
        dataset_path: str = "",
        crc_debug: bool = False,
        store_info: bool = False,
    ) -> None:
        super().__init__(
            device=device,
            nb_steps=nb_steps,
            sample_preprocessor=sample_preprocessor,
            memory_size=memory_size,
            batch_size=batch_size,
            dataset_path=dataset_path,
            crc_debug=crc_debug,
        )
        self.uid = uuid.uuid4().hex
        self._storage = RingStorage(self.memory_size, store_info=store_info or crc_debug)
        self._links = EpisodeLinks(self._storage)
        self._sampler = SlotSampler(self._links)
        if dataset_path:
            if Path(dataset_path).exists():
                from tmrl.checkpoint import load_memory

                load_memory(self, dataset_path)
            else:
                logger.info("no dataset at %s: starting with an empty memory", dataset_path)

    # --- storage -------------------------------------------------------------------------------

    @property
    def capacity(self) -> int:
        """Number of slots (``memory_size``)."""
        return self.memory_size

    @property
    def size(self) -> int:
        """Number of filled slots (samples held, valid or not)."""
        return self._storage.size

    @property
    def total(self) -> int:
        """Absolute counter of the next sample (samples ever stored)."""
        return self._storage.total

    @property
    def actions(self) -> np.ndarray | None:
        """The ring array of actions, shape ``(capacity, *action_shape)`` (``None`` before the
        first non-``None`` action)."""
        return self._storage.act

    @property
    def counters(self) -> np.ndarray:
        """The absolute counter each slot was written with, shape ``(capacity,)`` (-1: empty)."""
        return self._storage.count

    _count = counters  # the name tests/test_checkpoint.py reads

    def obs_leaf(self, index: int) -> np.ndarray:
        """The ring array of the ``index``-th observation leaf (depth-first order), shape
        ``(capacity, *leaf_shape)``."""
        return self._storage.obs[index]

    @property
    def obs_spec(self) -> list | None:
        """The JSON-able description of the stored observation structure (``None`` when empty)."""
        return self._storage.obs_spec

    def append_buffer(self, buffer: SampleBuffer) -> None:
        """Store the samples of ``buffer`` (see the class docstring for the layout).

        A :class:`ColumnBuffer` hands its columns over as arrays (no tuple per sample), unless
        infos are kept, which only the samples carry; otherwise ``buffer.memory`` is read.

        Raises:
            UserError: a sample is not a 6-tuple, ``buffer.sources`` does not give one id per
                sample, or observations/actions change structure, shape or become non-numeric.
        """
        sources = getattr(buffer, "sources", None)
        columns = None
        if self._storage.infos is None and isinstance(buffer, ColumnBuffer):
            columns = buffer.as_columns()
        if columns is not None:
            self._append_columns(columns, sources)
        else:
            self._append_samples(buffer.memory, sources)

    def _append_columns(self, columns: SampleColumns, sources: Sequence[int] | None) -> None:
        """Store samples given as :data:`SampleColumns`."""
        acts, obs, rew, terminated, truncated = columns
        keep = self._kept(len(rew))
        self._store(
            obs=self._storage.obs_column_rows(obs, keep),
            act=self._storage.act_column_rows(acts, keep),
            rew=np.asarray(rew, dtype=np.float32),
            terminated=np.asarray(terminated, dtype=bool),
            truncated=np.asarray(truncated, dtype=bool),
            sources=sources,
        )

    def _append_samples(self, samples: Sequence[Any], sources: Sequence[int] | None) -> None:
        """Store samples given as ``(act, new_obs, rew, terminated, truncated, info)`` tuples."""
        if len(samples) == 0:
            return
        if not isinstance(samples[0], (tuple, list)) or len(samples[0]) != 6:
            raise UserError(
                "a sample must be (act, new_obs, rew, terminated, truncated, info): check that the "
                "sample_compressor returns these six values"
            )
        keep = self._kept(len(samples))
        infos = [s[5] for s in samples][keep] if self._storage.infos is not None else None
        self._store(
            obs=self._storage.obs_rows([s[1] for s in samples][keep]),
            act=self._storage.act_rows([s[0] for s in samples][keep]),
            rew=np.asarray([s[2] for s in samples], dtype=np.float32),
            terminated=np.asarray([bool(s[3]) for s in samples], dtype=bool),
            truncated=np.asarray([bool(s[4]) for s in samples], dtype=bool),
            sources=sources,
            infos=infos,
        )

    def _kept(self, n: int) -> slice:
        """The rows of ``n`` new samples that fit: only the newest ``capacity`` can be kept."""
        return slice(max(0, n - self.memory_size), n)

    def _store(self, obs: list[np.ndarray], act: np.ndarray | None, rew: np.ndarray, terminated: np.ndarray,
               truncated: np.ndarray, sources: Sequence[int] | None, infos: list[Any] | None = None) -> None:
        """Link ``len(rew)`` new samples, write the kept rows and move the write counter.

        Args:
            obs, act, infos: rows of the kept samples only (see :meth:`_kept`).
            rew, terminated, truncated: all new samples (the links need every episode end).
            sources: the buffer's ``sources``.
        """
        n = len(rew)
        start = self._storage.total
        prev = self._links.chain(start, terminated | truncated, sources)
        keep = self._kept(n)
        first = start + keep.start
        self._storage.write(first, obs, act, rew[keep], terminated[keep], truncated[keep], infos)
        self._links.write(first, prev[keep])
        self._storage.total += n

    # --- validity and histories ----------------------------------------------------------------

    def valid_slots(self) -> np.ndarray:
        """Slots ``j`` whose transition is valid (``prev[j]`` is set and still in the memory), in
        increasing slot order. Cached until the next append."""
        return self._links.valid_slots()

    def __len__(self) -> int:
        """Number of valid transitions."""
        return len(self._links.valid_slots())

    def history_slots(self, slots: np.ndarray | Sequence[int], length: int) -> np.ndarray:
        """The slots of the ``length`` samples of the same episode ending at each of ``slots``,
        oldest first: column ``-1`` is ``slots`` itself, column ``-2`` its ``prev``, and so on.
        Before the episode's first sample, that first sample is repeated.

        Args:
            slots: 1-D array of slots.
            length: history length (>= 1).

        Returns:
            int64 array of shape ``(len(slots), length)``.
        """
        return self._links.history_slots(slots, length)

    def build_obs(self, slots: np.ndarray) -> Any:
        """The observations stored at ``slots``, batched: the stored structure with each leaf of
        shape ``(len(slots), *leaf_shape)``. Subclasses override this to add histories.

        Args:
            slots: the slots whose observations to build.
        """
        return self._storage.observations(slots)

    # --- sampling ------------------------------------------------------------------------------

    def sample_indices(self) -> np.ndarray:
        """Draw ``batch_size`` valid slots uniformly (with replacement) with :attr:`rng`, among
        those whose :attr:`history_depth` links are all still held.

        Raises:
            ValueError: no valid transition yet.
            UserError: the memory is too small to hold the history its transitions need.
        """
        return self._sampler.draw(self.rng, self.batch_size, self.history_depth)

    def gather(self, slots: np.ndarray) -> Batch:
        """Rebuild the transitions at ``slots`` as batched NumPy arrays.

        Returns:
            ``Batch(obs, act, rew, next_obs, terminated, truncated)``; observation leaves and
            ``act`` have a leading batch dimension, ``rew`` is float32, the flags are bool.

        Raises:
            UserError: every stored action is ``None``.
        """
        act = self._storage.act
        if act is None:
            raise UserError("the memory holds no action yet: every stored action is None")
        n = len(slots)
        # One gather for both observations halves the per-leaf overhead; the halves are views.
        both = self.build_obs(np.concatenate([self._links.prev_slots(slots), slots]))
        return Batch(
            _tree_map(lambda a: a[:n], both),
            act[slots],
            self._storage.rew[slots],
            _tree_map(lambda a: a[n:], both),
            self._storage.terminated[slots],
            self._storage.truncated[slots],
        )

    def sample(self, indices: Sequence[int] | np.ndarray | None = None) -> Batch:
        """Build one batch of tensors on the memory's device.

        Args:
            indices: slots of valid transitions; ``None`` draws ``batch_size`` of them.

        Returns:
            ``Batch(obs, act, rew, next_obs, terminated, truncated)``: observations keep their
            structure with batched tensor leaves, ``act`` has shape ``(B, *action_shape)``,
            ``rew``/``terminated``/``truncated`` are float32 of shape ``(B,)``.

        Raises:
            IndexError: an index is not the slot of a valid transition.
        """
        if self.sample_preprocessor is not None or self.crc_debug:
            return super().sample(indices)
        slots = self.sample_indices() if indices is None else self._links.check_slots(indices)
        prev_obs, act, rew, new_obs, terminated, truncated = self.gather(slots)
        dev = self.device
        return Batch(
            to_torch(prev_obs, dev),
            to_torch(act, dev),
            to_torch(rew, dev),
            to_torch(new_obs, dev),
            to_torch(terminated.astype(np.float32), dev),
            to_torch(truncated.astype(np.float32), dev),
        )

    def get_transition(self, item: int) -> tuple:
        """Rebuild the transition at slot ``item``.

        Returns:
            ``(prev_obs, act, rew, new_obs, terminated, truncated, info)`` (NumPy, no batch
            dimension); ``info`` is ``{}`` unless infos are stored.

        Raises:
            IndexError: ``item`` is not the slot of a valid transition.
        """
        slots = self._links.check_slots([item])
        prev_obs, act, rew, new_obs, terminated, truncated = self.gather(slots)
        first = lambda a: a[0]
        infos = self._storage.infos
        info = infos[int(slots[0])] if infos is not None else None
        return (
            _tree_map(first, prev_obs),
            act[0],
            rew[0],
            _tree_map(first, new_obs),
            bool(terminated[0]),
            bool(truncated[0]),
            info if info is not None else {},
        )

    # --- checkpoint protocol (used by tmrl.checkpoint) ----------------------------------------

    def ring_arrays(self) -> dict[str, np.ndarray]:
        """Every per-slot array, by name, full capacity (only those allocated)."""
        return {**self._storage.arrays(), **self._links.arrays()}

    def ring_meta(self) -> dict[str, Any]:
        """JSON-able description of everything that is not per-slot rows."""
        return {
            "class": type(self).__qualname__,
            "uid": self.uid,
            **self._storage.meta(),
            **self._links.meta(),
            **self._sampler.meta(self.rng),
            "stats": [float(self.stat_train_return), float(self.stat_test_return),
                      int(self.stat_train_steps), int(self.stat_test_steps)],
        }

    def restore_ring(self, meta: dict[str, Any], rows: Callable[[str], tuple[int, np.ndarray]]) -> None:
        """Rebuild the memory from :meth:`ring_meta` output and saved rows.

        Args:
            meta: the saved :meth:`ring_meta`.
            rows: ``rows(name)`` returns ``(first_counter, array)``: the rows of array ``name``
                for consecutive absolute counters starting at ``first_counter`` and ending at
                ``meta["total"]``.

        Raises:
            ValueError: the saved data does not fit this memory (message says why).
        """
        window = RestoreWindow.of(meta, self.memory_size)
        self._storage.restore(meta, window, rows)
        self._links.restore(meta, window, rows)
        self.uid = meta["uid"]
        self._sampler.restore(meta, self.rng)
        if meta.get("stats") is not None:
            (self.stat_train_return, self.stat_test_return, self.stat_train_steps, self.stat_test_steps) = meta["stats"]


class RealTimeTorchMemory(GenericTorchMemory):
    """:class:`GenericTorchMemory` for real-time environments whose observation ends with an action
    buffer that the sample compressor removed.

    rtgym observations are ``(*obs, *act_buf)`` where ``act_buf`` holds the last ``act_buf_len``
    actions, oldest first. The compressor drops those ``act_buf_len`` elements; this memory
    rebuilds them from stored actions: the buffer of sample ``j`` is the actions of the
    ``act_buf_len`` samples of its episode ending at ``j``, with the episode's first action (the
    default action sent at reset) repeated before the episode starts. So the last action of an
    episode never leaks into the next one (rtgym's ``reset_act_buf=True``).

    Rebuilt observations are tuples: the stored elements (a non-sequence observation counts as
    one element), then ``act_buf_len`` action arrays.

    The other arguments are those of :class:`GenericTorchMemory`.

    Args:
        act_buf_len: length of the action buffer (rtgym's ``act_buf_len``).
    """

    def __init__(
        self,
        act_buf_len: int,
        device: Any = "cpu",
        nb_steps: int = 1,
        sample_preprocessor: Callable[..., tuple] | None = None,
        memory_size: int = 1000000,
        batch_size: int = 256,
        dataset_path: str = "",
        crc_debug: bool = False,
        store_info: bool = False,
    ) -> None:
        if int(act_buf_len) < 1:
            raise UserError(f"act_buf_len must be at least 1, got {act_buf_len}: fix ACT_BUF_LEN")
        self.act_buf_len = int(act_buf_len)
        self.history_depth = self.act_buf_len
        super().__init__(
            device=device,
            nb_steps=nb_steps,
            sample_preprocessor=sample_preprocessor,
            memory_size=memory_size,
            batch_size=batch_size,
            dataset_path=dataset_path,
            crc_debug=crc_debug,
            store_info=store_info,
        )

    def build_obs(self, slots: np.ndarray) -> tuple:
        """Stored observation elements followed by the rebuilt action buffer.

        Args:
            slots: the slots whose observations to build.
        """
        base = super().build_obs(slots)
        assert self.actions is not None
        acts = self.actions[self.history_slots(slots, self.act_buf_len)]  # (B, L, *act_shape)
        elements = tuple(base) if isinstance(base, (tuple, list)) else (base,)
        return elements + tuple(acts[:, i] for i in range(self.act_buf_len))
