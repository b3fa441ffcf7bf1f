"""The built-in array-shaped memories: :class:`GenericTorchMemory` (any observation structure) and
:class:`RealTimeTorchMemory` (rebuilds the action buffer of real-time environments). Each is
composed of a :class:`~tmrl.memory.storage.RingStorage`, :class:`~tmrl.memory.episodes.EpisodeLinks`
and a :class:`~tmrl.memory.sampler.SlotSampler`, and builds a whole batch with a few vectorised
gathers (the *fast path*). Pre-filling from ``dataset_path`` is :mod:`tmrl.memory.persist`'s job.
"""

from __future__ import annotations

import logging
import uuid
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np
import torch

from tmrl.batch import Batch, to_torch
from tmrl.errors import UserError
from tmrl.memory.api import TorchMemory
from tmrl.memory.episodes import EpisodeLinks
from tmrl.memory.persist import load_dataset
from tmrl.memory.resident import DeviceRing, RingDoesNotFit, take, wants_device_ring
from tmrl.memory.sampler import SlotSampler
from tmrl.memory.storage import ColumnBuffer, RestoreWindow, RingStorage, SampleBuffer, SampleColumns
from tmrl.memory.tree import _tree_map, _unflatten

__all__ = ["GenericTorchMemory", "RealTimeTorchMemory"]

logger = logging.getLogger(__name__)


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

    On the device (``on_device``, :mod:`tmrl.memory.resident`): on a GPU the rings also live there,
    copied row by row as samples arrive, and :meth:`sample` gathers the batch on the device from
    one index matrix the host computes (no NumPy gather, no batch copy, no wait for the device).
    The batches are the same as the host path's, value for value. A subclass that overrides
    :meth:`build_obs` keeps the host path (its code is NumPy); the built-in ones override
    :meth:`build_from`, which both paths run.

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
        on_device: ``MEMORY_ON_DEVICE``: ``"auto"`` (the rings also on ``device`` when it is a
            GPU), ``"on"`` (also on ``device``, whatever it is) or ``"off"`` (host only).

    Attributes:
        uid: identity of this memory's history (a checkpoint appends to its own segments only).
        device_ring: the rings on the device (:class:`~tmrl.memory.resident.DeviceRing`), or
            ``None`` when batches are built on the host.

    Subclassing (history-based memories): override :meth:`build_obs` and set
    :attr:`history_depth`; use :meth:`history_slots`, :meth:`obs_leaf` and :attr:`actions`. Or,
    to keep the device path, override :meth:`build_from` (code that runs on NumPy arrays and on
    tensors alike).
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
        on_device: str = "auto",
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
        self.on_device = on_device
        self.device_ring: DeviceRing | None = None
        if wants_device_ring(on_device, device) and sample_preprocessor is None and not crc_debug:
            # (those two sample item by item on the host: rings on the device would go unused)
            if type(self).build_obs is not GenericTorchMemory.build_obs:
                logger.info("%s overrides build_obs: its batches are built on the host and copied to %s",
                            type(self).__name__, device)
            else:
                self.device_ring = self._to_device(lambda: DeviceRing(self._storage, device))
        load_dataset(self, dataset_path)

    def _to_device(self, step: Callable[[], Any]) -> Any:
        """Run ``step`` (an allocation or copy of the device rings) and return what it returns;
        when the rings do not fit, go on without them (``"auto"``: one warning, None returned) or
        stop (``"on"``: one line)."""
        try:
            return step()
        except RingDoesNotFit as e:
            self.device_ring = None
            if self.on_device == "on":
                raise UserError(f"{e}: lower MEMORY_SIZE or set MEMORY_ON_DEVICE to \"off\"") from None
            logger.warning("%s; batches are built on the host instead (MEMORY_ON_DEVICE \"off\" says so "
                           "without trying)", e)
            if torch.device(self.device).type == "cuda":
                torch.cuda.empty_cache()
            return None

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
        ring = self.device_ring
        if ring is not None:
            self._to_device(lambda: ring.write(first, n - keep.start))

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
        shape ``(len(slots), *leaf_shape)``, histories rebuilt (:meth:`build_from` on the host
        rings). A subclass may override this (NumPy code; its batches are then built on the host).

        Args:
            slots: the slots whose observations to build.
        """
        return self.build_from(self._storage, self.history_slots(slots, self.history_depth))

    def build_from(self, rings: Any, hist: Any) -> Any:
        """The observations whose history slots are ``hist``, gathered from ``rings``: the code
        both paths run, on NumPy arrays (the host :class:`RingStorage`) or on tensors (the
        :class:`~tmrl.memory.resident.DeviceRing`). It must gather with :func:`~tmrl.memory.resident.take`
        and convert with :func:`~tmrl.memory.resident.as_float32`, and otherwise use only slicing
        and ``reshape``, which both kinds of arrays share.

        Args:
            rings: what holds the rings: ``obs`` (one ring per observation leaf), ``act``,
                ``obs_spec``.
            hist: integer array ``(n, history_depth)``: the slots of each observation's history,
                oldest first, as :meth:`history_slots` gives them (column ``-1``: the slots).

        Returns:
            The stored structure with batched leaves.
        """
        idx = hist[:, -1]
        return _unflatten(rings.obs_spec, [take(leaf, idx) for leaf in rings.obs])

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
        if self.device_ring is not None:
            return self._gather_on_device(self.device_ring, slots)
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

    def _gather_on_device(self, ring: DeviceRing, slots: np.ndarray) -> Batch:
        """:meth:`gather` on the device: the host follows the links of both observations' slots
        into one index matrix, copies it over, and the device gathers everything from it."""
        if ring.act is None:
            raise UserError("the memory holds no action yet: every stored action is None")
        n = len(slots)
        both = np.concatenate([self._links.prev_slots(slots), slots])
        hist = ring.index(self.history_slots(both, self.history_depth))
        obs = self.build_from(ring, hist)
        last = hist[n:, -1]
        return Batch(
            _tree_map(lambda a: a[:n], obs),
            take(ring.act, last),
            take(ring.rew, last),
            _tree_map(lambda a: a[n:], obs),
            take(ring.terminated, last),
            take(ring.truncated, last),
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
        ring = self.device_ring
        if ring is not None:
            self._to_device(ring.reload)
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
        on_device: str = "auto",
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
            on_device=on_device,
        )

    def build_from(self, rings: Any, hist: Any) -> tuple:
        """Stored observation elements followed by the rebuilt action buffer (the actions at the
        last ``act_buf_len`` columns of ``hist``, oldest first).

        Args:
            rings: as in :meth:`GenericTorchMemory.build_from`.
            hist: as in :meth:`GenericTorchMemory.build_from`.
        """
        base = super().build_from(rings, hist)
        assert rings.act is not None
        elements = tuple(base) if isinstance(base, (tuple, list)) else (base,)
        return elements + tuple(take(rings.act, hist[:, j]) for j in range(-self.act_buf_len, 0))
