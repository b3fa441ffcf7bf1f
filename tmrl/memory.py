"""Replay memories: the user-facing :class:`Memory` API and the built-in array-shaped memories.

Two ways to use this module:

* Subclass :class:`TorchMemory` and implement ``append_buffer``, ``__len__`` and
  ``get_transition`` (the tutorial's way). Sampling then goes through the *slow path*: one
  ``get_transition`` call per item, the CRC check, the ``sample_preprocessor``, then
  :func:`collate_torch`.
* Use :class:`GenericTorchMemory` (any observation structure) or :class:`RealTimeTorchMemory`
  (rebuilds the action buffer of real-time environments). They store samples in preallocated
  NumPy ring buffers and build a whole batch with a few vectorised gathers (the *fast path*).

Vocabulary (see docs/internals.md): a *sample* is ``(act, new_obs, rew, terminated, truncated,
info)`` as recorded by a worker; a *transition* is ``(prev_obs, act, rew, new_obs, terminated,
truncated, info)``; a *batch* is a collated list of transitions without ``info``.
"""

from __future__ import annotations

import logging
import uuid
from abc import ABC, abstractmethod
from collections.abc import Callable, Iterator, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch

from tmrl.errors import UserError

__all__ = [
    "CRCMismatchError",
    "GenericTorchMemory",
    "Memory",
    "RealTimeTorchMemory",
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
        stat_train_return, stat_test_return, stat_train_steps, stat_test_steps: the latest
            episode statistics of the workers, copied by :meth:`append`.
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

        Returns:
            ``(prev_obs, act, rew, new_obs, terminated, truncated, info)``; ``info`` must be the
            sample's info dict when CRC debugging is used.
        """
        raise NotImplementedError

    @abstractmethod
    def collate(self, batch: list[tuple], device: Any) -> tuple:
        """Turn a list of ``(prev_obs, act, rew, new_obs, terminated, truncated)`` into one batch
        of tensors on ``device``."""
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

    def __iter__(self) -> Iterator[tuple]:
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

    def sample(self, indices: Sequence[int] | np.ndarray | None = None) -> tuple:
        """Build one batch.

        Args:
            indices: the items to use; ``None`` draws ``batch_size`` of them with
                :meth:`sample_indices`.

        Returns:
            ``(prev_obs, act, rew, new_obs, terminated, truncated)`` collated by :meth:`collate`.
        """
        if indices is None:
            indices = self.sample_indices()
        batch = [self[int(i)] for i in indices]
        return self.collate(batch, self.device)


class TorchMemory(Memory, ABC):
    """A :class:`Memory` whose batches are PyTorch tensors (collated by :func:`collate_torch`).

    Same arguments as :class:`Memory`.
    """

    def collate(self, batch: list[tuple], device: Any) -> tuple:
        """Collate with :func:`collate_torch`."""
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


# ==== built-in array-shaped memories ==============================================================


class GenericTorchMemory(TorchMemory):
    """Array-shaped replay memory for any observation structure.

    Every sample gets a slot in preallocated ring buffers: one NumPy array per observation leaf
    (nested tuples, lists and dicts are flattened; arrays are allocated from the first sample),
    plus actions, rewards, flags, a ``prev`` pointer (absolute counter of the previous sample of
    the same worker and episode, -1 at an episode's first sample) and the absolute counter each
    slot was written with. The transition at slot ``j`` is ``(obs[prev[j]], act[j], rew[j],
    obs[j], terminated[j], truncated[j])``; it is valid when ``prev[j]`` is still in the memory, so
    no transition spans a reset or an overwritten sample. Buffers whose ``sources`` are set are
    split into one stream per worker, so interleaved workers never mix.

    Items (``get_transition(item)``, ``sample(indices)``) are slot numbers of valid transitions;
    ``len(memory)`` is the number of valid transitions.

    float64 arrays are stored as float32. ``None`` actions (the first sample of an episode in a
    non-real-time environment) are stored as zeros; they never appear in a transition.

    Fast path: :meth:`sample` gathers a whole batch with vectorised indexing and converts it to
    tensors in one go (pinned memory and non-blocking copies on CUDA). With a
    ``sample_preprocessor`` or ``crc_debug``, it falls back to the per-item slow path.

    Args:
        device, nb_steps, sample_preprocessor, memory_size, batch_size, dataset_path, crc_debug:
            as in :class:`Memory`.
        store_info: keep each sample's ``info`` dict (Python objects, not checkpointed) so that
            ``get_transition`` returns it; implied by ``crc_debug``. Otherwise ``info`` is ``{}``.

    Subclassing (history-based memories): override :meth:`build_obs` and set
    :attr:`history_depth`; use :meth:`history_slots`, :meth:`obs_leaf` and :attr:`actions`.
    """

    #: How many ``prev`` links a transition's observations reach back (1: only ``prev[j]``).
    #: Transitions whose chain is cut by an overwritten sample within this depth are not sampled.
    history_depth: int = 1

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
        cap = self.memory_size
        self.uid = uuid.uuid4().hex
        self.total = 0  # absolute counter of the next sample
        self._obs_spec: list | None = None
        self._obs: list[np.ndarray] = []
        self._act: np.ndarray | None = None
        self._rew = np.zeros(cap, dtype=np.float32)
        self._terminated = np.zeros(cap, dtype=bool)
        self._truncated = np.zeros(cap, dtype=bool)
        self._prev = np.full(cap, -1, dtype=np.int64)
        self._count = np.full(cap, -1, dtype=np.int64)
        self._infos: list[Any] | None = [None] * cap if (store_info or crc_debug) else None
        # per source id: (absolute counter of its last sample, whether that sample ended an episode)
        self._streams: dict[int, tuple[int, bool]] = {}
        self._valid: np.ndarray | None = None
        # Counters below this were never stored here (a restore into a bigger memory).
        self._floor = 0
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
        return min(self.total, self.memory_size)

    @property
    def actions(self) -> np.ndarray | None:
        """The ring array of actions, shape ``(capacity, *action_shape)`` (``None`` before the
        first non-``None`` action)."""
        return self._act

    def obs_leaf(self, index: int) -> np.ndarray:
        """The ring array of the ``index``-th observation leaf (depth-first order), shape
        ``(capacity, *leaf_shape)``."""
        return self._obs[index]

    @property
    def obs_spec(self) -> list | None:
        """The JSON-able description of the stored observation structure (``None`` when empty)."""
        return self._obs_spec

    def _ring_write(self, buf: Any, counter: int, rows: Any) -> None:
        cap = self.memory_size
        m = len(rows)
        pos = counter % cap
        first = min(m, cap - pos)
        buf[pos : pos + first] = rows[:first]
        if first < m:
            buf[: m - first] = rows[first:]

    def append_buffer(self, buffer: Any) -> None:
        """Store the samples of ``buffer`` (see the class docstring for the layout).

        Raises:
            UserError: a sample is not a 6-tuple, or observations/actions change structure, shape
                or become non-numeric.
        """
        # A buffer received from the network can hand its columns over as arrays (no tuple per
        # sample); infos are kept only in CRC debug mode, which therefore reads the samples.
        as_columns = getattr(buffer, "as_columns", None)
        columns = as_columns() if self._infos is None and callable(as_columns) else None
        if columns is not None:
            acts, obs, rew, terminated, truncated = columns
            n = len(rew)
            rew = np.asarray(rew, dtype=np.float32)
            terminated = np.asarray(terminated, dtype=bool)
            truncated = np.asarray(truncated, dtype=bool)
            samples = None
        else:
            samples = buffer.memory
            n = len(samples)
            if n == 0:
                return
            if not isinstance(samples[0], (tuple, list)) or len(samples[0]) != 6:
                raise UserError(
                    "a sample must be (act, new_obs, rew, terminated, truncated, info): check that the "
                    "sample_compressor returns these six values"
                )
            acts = [s[0] for s in samples]
            obs = [s[1] for s in samples]
            rew = np.asarray([s[2] for s in samples], dtype=np.float32)
            terminated = np.asarray([bool(s[3]) for s in samples], dtype=bool)
            truncated = np.asarray([bool(s[4]) for s in samples], dtype=bool)
        sources = getattr(buffer, "sources", None)

        # Stream bookkeeping: the prev pointer of each sample, per worker.
        counters = self.total + np.arange(n, dtype=np.int64)
        done = terminated | truncated
        prev = np.empty(n, dtype=np.int64)
        if sources is None:
            src = np.zeros(n, dtype=np.int64)
        else:
            src = np.asarray(sources, dtype=np.int64)
            if src.shape != (n,):
                raise UserError(
                    f"buffer.sources has {src.size} entries for {n} samples: it must be None or one "
                    "source id per sample"
                )
        for s in np.unique(src):
            idx = np.flatnonzero(src == s)
            last, last_done = self._streams.get(int(s), (-1, True))
            p = np.empty(len(idx), dtype=np.int64)
            p[0] = last
            p[1:] = counters[idx[:-1]]
            pdone = np.empty(len(idx), dtype=bool)
            pdone[0] = last_done
            pdone[1:] = done[idx[:-1]]
            p[pdone] = -1
            prev[idx] = p
            self._streams[int(s)] = (int(counters[idx[-1]]), bool(done[idx[-1]]))

        # Only the newest `capacity` samples of an oversized buffer can be kept.
        keep = slice(max(0, n - self.memory_size), n)
        start = self.total + keep.start
        if samples is None:
            obs_leaves = self._obs_arrays(obs, keep)
            act_rows = self._action_array(acts, keep)
        else:
            obs_leaves = self._prepare_obs(obs[keep])
            act_rows = self._prepare_actions(acts[keep])
        for buf, rows in zip(self._obs, obs_leaves):
            self._ring_write(buf, start, rows)
        if act_rows is not None:
            self._ring_write(self._act, start, act_rows)
        self._ring_write(self._rew, start, rew[keep])
        self._ring_write(self._terminated, start, terminated[keep])
        self._ring_write(self._truncated, start, truncated[keep])
        self._ring_write(self._prev, start, prev[keep])
        self._ring_write(self._count, start, counters[keep])
        if self._infos is not None:
            self._ring_write(self._infos, start, [s[5] for s in samples[keep]])
        self.total += n
        self._valid = None

    def _prepare_obs(self, obs: list[Any]) -> list[np.ndarray]:
        if self._obs_spec is None:
            spec = _make_spec(obs[0], [0])
        else:
            spec = self._obs_spec
        columns: list[list[Any]] = []
        _columns(spec, obs, columns, "obs")
        paths = _leaf_paths(spec)
        return self._check_obs([_stack(col, path) for col, path in zip(columns, paths)], spec, paths)

    def _check_obs(self, arrays: list[np.ndarray], spec: list, paths: list[str]) -> list[np.ndarray]:
        if self._obs_spec is None:
            # Lazy allocation: shapes and dtypes come from the first sample.
            self._obs = [
                np.zeros((self.memory_size, *a.shape[1:]), dtype=_storage_dtype(a)) for a in arrays
            ]
            self._obs_spec = spec
        for arr, buf, path in zip(arrays, self._obs, paths):
            if arr.shape[1:] != buf.shape[1:]:
                raise UserError(
                    f"{path} has shape {arr.shape[1:]} but earlier samples had {buf.shape[1:]}: "
                    "observations must keep one shape"
                )
            if arr.dtype == object:
                _storage_dtype(arr)
        return arrays

    def _obs_arrays(self, tree: Any, keep: slice) -> list[np.ndarray]:
        """:meth:`_prepare_obs` for observations already stacked leaf by leaf (``tree`` has the
        structure of one observation, an array of all samples at each leaf)."""
        spec = _make_spec(tree, [0]) if self._obs_spec is None else self._obs_spec
        leaves: list[Any] = []
        _tree_leaves(spec, tree, leaves, "obs")
        return self._check_obs([leaf[keep] for leaf in leaves], spec, _leaf_paths(spec))

    def _action_array(self, act: np.ndarray | None, keep: slice) -> np.ndarray | None:
        """:meth:`_prepare_actions` for actions already stacked (zeros where they were ``None``)."""
        if act is None:
            return None
        act = act[keep]
        if self._act is None:
            self._act = np.zeros((self.memory_size, *act.shape[1:]), dtype=_storage_dtype(act))
        if act.shape[1:] != self._act.shape[1:]:
            raise UserError(
                f"an action has shape {act.shape[1:]} but earlier actions had {self._act.shape[1:]}: "
                "actions must keep one shape"
            )
        return act

    def _prepare_actions(self, acts: list[Any]) -> np.ndarray | None:
        first = next((a for a in acts if a is not None), None)
        if first is None:
            return None  # only None actions: the zeros already in the ring stand for them
        if any(a is None for a in acts):
            ref = np.asarray(first) if self._act is None else self._act[0]
            zeros = np.zeros(ref.shape, dtype=_storage_dtype(ref))
            acts = [zeros if a is None else a for a in acts]
        arr = _stack(acts, "the action")
        _storage_dtype(arr)  # refuses non-numeric actions with the one-line error
        return self._action_array(arr, slice(None))

    # --- validity and histories ----------------------------------------------------------------

    def _oldest(self) -> int:
        """Absolute counter of the oldest sample held."""
        return max(self.total - self.size, self._floor)

    def valid_slots(self) -> np.ndarray:
        """Slots ``j`` whose transition is valid (``prev[j]`` is set and still in the memory), in
        increasing slot order. Cached until the next append."""
        if self._valid is None:
            size = self.size
            # prev >= oldest also excludes prev == -1 (oldest >= 0).
            self._valid = np.flatnonzero(self._prev[:size] >= self._oldest())
        return self._valid

    def __len__(self) -> int:
        """Number of valid transitions."""
        return len(self.valid_slots())

    def _chain_ok(self, slots: np.ndarray, depth: int) -> np.ndarray:
        """For slots whose ``prev`` is valid: whether following ``depth`` links stays inside the
        memory (or stops at an episode's first sample)."""
        cap, oldest = self.memory_size, self._oldest()
        ok = np.ones(len(slots), dtype=bool)
        ptr = self._prev[slots]
        for _ in range(depth - 1):
            live = ptr >= 0
            nxt = np.where(live, self._prev[ptr % cap], -1)
            ok &= ~(live & (nxt >= 0) & (nxt < oldest))
            ptr = np.where(live & (nxt >= oldest), nxt, -1)
        return ok

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
        cap, oldest = self.memory_size, self._oldest()
        cur = np.asarray(slots, dtype=np.int64)
        out = np.empty((len(cur), length), dtype=np.int64)
        out[:, -1] = cur
        for k in range(2, length + 1):
            ptr = self._prev[cur]
            # Stop at the episode's start (ptr == -1) and, defensively, at overwritten samples
            # (the sampler never draws transitions whose needed history was overwritten).
            cur = np.where(ptr >= oldest, ptr % cap, cur)
            out[:, -k] = cur
        return out

    def build_obs(self, slots: np.ndarray) -> Any:
        """The observations stored at ``slots``, batched: the stored structure with each leaf of
        shape ``(len(slots), *leaf_shape)``. Subclasses override this to add histories."""
        assert self._obs_spec is not None
        return _unflatten(self._obs_spec, [leaf[slots] for leaf in self._obs])

    # --- sampling ------------------------------------------------------------------------------

    def sample_indices(self) -> np.ndarray:
        """Draw ``batch_size`` valid slots uniformly (with replacement).

        Raises:
            ValueError: no valid transition yet.
            UserError: the memory is too small to hold the history its transitions need.
        """
        valid = self.valid_slots()
        if len(valid) == 0:
            raise ValueError("cannot sample from a memory that holds no transition yet")
        slots = valid[self.rng.integers(0, len(valid), size=self.batch_size)]
        if self.history_depth > 1:
            for _ in range(64):
                bad = ~self._chain_ok(slots, self.history_depth)
                if not bad.any():
                    break
                slots[bad] = valid[self.rng.integers(0, len(valid), size=int(bad.sum()))]
            else:
                raise UserError(
                    f"memory_size={self.memory_size} is too small for histories of "
                    f"{self.history_depth} samples: increase memory_size"
                )
        return slots

    def _check_slots(self, indices: Any) -> np.ndarray:
        slots = np.asarray(indices, dtype=np.int64).reshape(-1)
        size = self.size
        if slots.size and (slots.min() < 0 or slots.max() >= size):
            raise IndexError(f"slot out of range: the memory holds {size} samples")
        bad = self._prev[slots] < self._oldest()
        if bad.any():
            raise IndexError(
                f"slot {int(slots[bad][0])} holds no transition (first sample of an episode, or its "
                "previous sample was overwritten): use valid_slots()"
            )
        return slots

    def gather(self, slots: np.ndarray) -> tuple:
        """Rebuild the transitions at ``slots`` as batched NumPy arrays.

        Returns:
            ``(prev_obs, act, rew, new_obs, terminated, truncated)``; observation leaves and
            ``act`` have a leading batch dimension, ``rew`` is float32, the flags are bool.
        """
        if self._act is None:
            raise UserError("the memory holds no action yet: every stored action is None")
        n = len(slots)
        prev_slots = self._prev[slots] % self.memory_size
        # One gather for both observations halves the per-leaf overhead; the halves are views.
        both = self.build_obs(np.concatenate([prev_slots, slots]))
        return (
            _tree_map(lambda a: a[:n], both),
            self._act[slots],
            self._rew[slots],
            _tree_map(lambda a: a[n:], both),
            self._terminated[slots],
            self._truncated[slots],
        )

    def sample(self, indices: Sequence[int] | np.ndarray | None = None) -> tuple:
        """Build one batch of tensors on the memory's device.

        Args:
            indices: slots of valid transitions; ``None`` draws ``batch_size`` of them.

        Returns:
            ``(prev_obs, act, rew, new_obs, terminated, truncated)``: observations keep their
            structure with batched tensor leaves, ``act`` has shape ``(B, *action_shape)``,
            ``rew``/``terminated``/``truncated`` are float32 of shape ``(B,)``.

        Raises:
            IndexError: an index is not the slot of a valid transition.
        """
        if self.sample_preprocessor is not None or self.crc_debug:
            return super().sample(indices)
        slots = self.sample_indices() if indices is None else self._check_slots(indices)
        prev_obs, act, rew, new_obs, terminated, truncated = self.gather(slots)
        dev = self.device
        return (
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
        slots = self._check_slots([item])
        prev_obs, act, rew, new_obs, terminated, truncated = self.gather(slots)
        first = lambda a: a[0]
        info = self._infos[int(slots[0])] if self._infos is not None else {}
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
        arrays: dict[str, np.ndarray] = {
            "rew": self._rew,
            "terminated": self._terminated,
            "truncated": self._truncated,
            "prev": self._prev,
            "count": self._count,
        }
        if self._act is not None:
            arrays["act"] = self._act
        for i, leaf in enumerate(self._obs):
            arrays[f"obs.{i}"] = leaf
        return arrays

    def ring_meta(self) -> dict[str, Any]:
        """JSON-able description of everything that is not per-slot rows."""
        return {
            "class": type(self).__qualname__,
            "capacity": self.memory_size,
            "total": self.total,
            "uid": self.uid,
            "obs_spec": self._obs_spec,
            "leaves": [[str(a.dtype), list(a.shape[1:])] for a in self._obs],
            "act": None if self._act is None else [str(self._act.dtype), list(self._act.shape[1:])],
            "streams": [[k, v[0], v[1]] for k, v in self._streams.items()],
            "oldest": self._oldest(),
            "rng": self.rng.bit_generator.state,
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
        self._obs_spec = meta["obs_spec"]
        self._obs = [np.zeros((self.memory_size, *shape), dtype=np.dtype(dt)) for dt, shape in meta["leaves"]]
        act = meta["act"]
        self._act = None if act is None else np.zeros((self.memory_size, *act[1]), dtype=np.dtype(act[0]))
        self._rew[:] = 0
        self._terminated[:] = False
        self._truncated[:] = False
        self._prev[:] = -1
        self._count[:] = -1
        if self._infos is not None:
            self._infos = [None] * self.memory_size
        total = int(meta["total"])
        saved_oldest = int(meta.get("oldest", total - min(total, int(meta["capacity"]))))
        floor = max(saved_oldest, total - min(total, self.memory_size))
        for name, buf in self.ring_arrays().items():
            first, arr = rows(name)
            if first + len(arr) != total:
                raise ValueError(f"memory array {name} ends at sample {first + len(arr)}, expected {total}")
            if first > saved_oldest:
                raise ValueError(f"memory array {name} starts at sample {first}, expected {saved_oldest} or earlier")
            if arr.shape[1:] != buf.shape[1:]:
                raise ValueError(f"memory array {name} has rows of shape {arr.shape[1:]}, expected {buf.shape[1:]}")
            skip = floor - first
            self._ring_write(buf, floor, arr[skip:])
        self.total = total
        self._floor = floor
        self.uid = meta["uid"]
        self._streams = {int(k): (int(last), bool(done)) for k, last, done in meta["streams"]}
        if meta.get("rng") is not None:
            self.rng.bit_generator.state = meta["rng"]
        if meta.get("stats") is not None:
            (self.stat_train_return, self.stat_test_return, self.stat_train_steps, self.stat_test_steps) = meta["stats"]
        self._valid = None


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

    Args:
        act_buf_len: length of the action buffer (rtgym's ``act_buf_len``).
        other arguments: as in :class:`GenericTorchMemory`.
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
        """Stored observation elements followed by the rebuilt action buffer."""
        base = super().build_obs(slots)
        assert self._act is not None
        acts = self._act[self.history_slots(slots, self.act_buf_len)]  # (B, L, *act_shape)
        elements = tuple(base) if isinstance(base, (tuple, list)) else (base,)
        return elements + tuple(acts[:, i] for i in range(self.act_buf_len))
