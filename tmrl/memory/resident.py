"""A replay memory's rings on the training device: :class:`DeviceRing`, the copy of a
:class:`~tmrl.memory.storage.RingStorage`'s arrays in torch tensors that a built-in memory on a GPU
builds its batches from (``MEMORY_ON_DEVICE``, the memories' ``on_device`` argument).

Why. On a CUDA trainer the host path gathers a batch with NumPy (for images: ``2 * B * hist_len``
frames), converts it and copies it to the GPU at every update. With the rings on the GPU, an
update's batch is a few gathers there: the host draws the slots and follows the episode links
(``2 * B * depth`` integers of index arithmetic, :class:`~tmrl.memory.episodes.EpisodeLinks`),
copies that one index matrix over (pinned memory, non-blocking), and the device gathers the
observations, actions, rewards and flags from it. Nothing waits for the device: no value comes
back to the host.

What lives where. The host :class:`RingStorage` stays the record: links, validity, checkpoints
and ``get_transition`` read it, so a checkpoint does not depend on the device (a GPU run resumes on
a CPU and back). The device holds one row per slot of each array, each frame once (histories are
gathered by index): observation leaves in their stored dtype (uint8 images stay uint8), actions,
rewards, and the two flags as float32 (the batch's dtype). Every append copies its new rows over,
one copy per array (two where the ring wraps), from pinned memory. So the host keeps its copy and
the device memory holds ``capacity`` rows of each array: 1,000,000 samples of 64x64 uint8 frames
are 4.1 GB there.

A memory whose rings do not fit on the device (``torch.OutOfMemoryError`` while allocating):
with ``"auto"`` the memory logs one warning and builds its batches on the host as before; with
``"on"`` it stops with a one-line error giving the size.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np
import torch

from tmrl.batch import to_torch
from tmrl.config.schema import ON_DEVICE_MODES
from tmrl.errors import UserError
from tmrl.memory.storage import RingStorage

__all__ = ["ON_DEVICE_MODES", "DeviceRing", "RingDoesNotFit", "as_float32", "take", "wants_device_ring"]


class RingDoesNotFit(Exception):
    """The device could not allocate the rings (the message gives the size)."""


def wants_device_ring(mode: str, device: Any) -> bool:
    """Whether a memory on ``device`` with ``on_device=mode`` keeps its rings there.

    Raises:
        UserError: ``mode`` is not one of :data:`ON_DEVICE_MODES`.
    """
    if mode not in ON_DEVICE_MODES:
        raise UserError(f"MEMORY_ON_DEVICE={mode!r} is not known: use one of "
                        f"{', '.join(map(repr, ON_DEVICE_MODES))}")
    if mode == "off":
        return False
    return mode == "on" or torch.device(device).type == "cuda"


def take(rows: Any, index: Any) -> Any:
    """``rows[index]`` along the first axis, for a NumPy array (fancy indexing) or a tensor (one
    ``index_select``, then a view: on a CPU 13 times faster than ``tensor[index]`` for a batch of
    64x64 frames, and one gather kernel on a GPU).

    Args:
        rows: the ring, ``(capacity, *row_shape)``.
        index: integer array of slots, any shape.

    Returns:
        Shape ``(*index.shape, *row_shape)``.
    """
    if isinstance(rows, torch.Tensor):
        return torch.index_select(rows, 0, index.reshape(-1)).view(*index.shape, *rows.shape[1:])
    return rows[index]


def as_float32(array: Any, scale: float | None = None) -> Any:
    """``array`` (a NumPy array or a tensor) as float32, times ``scale`` when given: the one
    conversion a memory's :meth:`~tmrl.memory.GenericTorchMemory.build_from` needs that NumPy and
    torch spell differently. The product is computed in float32 on both (the same values), in place
    on the converted copy: a batch of image histories is 33 MB of float32, and a second array of
    that size costs more than the product (page faults on the host)."""
    if isinstance(array, torch.Tensor):
        out = array.to(torch.float32)
        if scale is None:
            return out
        # a Python scalar: no copy to the device; in place unless .to() returned the input itself
        return out * float(scale) if out is array else out.mul_(float(scale))
    out = array.astype(np.float32)
    if scale is not None:
        out *= np.float32(scale)
    return out


# torch.OutOfMemoryError (PyTorch 2.5 on), or the CUDA one it names (older versions)
_OUT_OF_MEMORY = getattr(torch, "OutOfMemoryError", None) or torch.cuda.OutOfMemoryError


def _device_zeros(shape: tuple[int, ...], dtype: torch.dtype, device: torch.device) -> torch.Tensor:
    """The one allocation on the device (the seam tests use to make the device run out of memory)."""
    return torch.zeros(shape, dtype=dtype, device=device)


def _gib(n: int) -> str:
    return f"{n / 2**30:.2f} GiB"


class DeviceRing:
    """The rings of ``storage`` as tensors on ``device``, kept equal to the host rows by
    :meth:`write` (after each append) and :meth:`reload` (after a restore).

    It offers what a memory's batch-building code reads from a :class:`RingStorage` (``obs``,
    ``act``, ``rew``, ``terminated``, ``truncated``, ``obs_spec``), so the same code gathers on
    either; ``terminated`` and ``truncated`` are float32 here.

    Args:
        storage: the host rings to copy.
        device: the torch device.

    Attributes:
        storage: those rings.
        device: the device.
        nbytes: bytes allocated on the device.
    """

    def __init__(self, storage: RingStorage, device: Any) -> None:
        self.storage = storage
        self.device = torch.device(device)
        self._pin = self.device.type == "cuda"
        self._fresh()

    def _fresh(self) -> None:
        """No rings but the per-slot scalars (observations and actions follow the host's arrays,
        :meth:`_allocate`)."""
        self.obs: list[torch.Tensor] = []
        self.act: torch.Tensor | None = None
        self.nbytes = 0
        cap = self.storage.capacity
        self.rew = self._zeros(cap, torch.float32)
        self.terminated = self._zeros(cap, torch.float32)
        self.truncated = self._zeros(cap, torch.float32)

    @property
    def obs_spec(self) -> list | None:
        """The host storage's observation structure."""
        return self.storage.obs_spec

    # --- allocation ----------------------------------------------------------------------------

    def _zeros(self, shape: Any, dtype: torch.dtype) -> torch.Tensor:
        """A zero tensor on the device (zeros, as the host's ``np.zeros`` rings: rows never
        written hold the same values on both)."""
        shape = (shape,) if isinstance(shape, int) else tuple(shape)
        size = int(np.prod(shape, dtype=np.int64)) * torch.empty((), dtype=dtype).element_size()
        try:
            t = _device_zeros(shape, dtype, self.device)
        except _OUT_OF_MEMORY:
            raise RingDoesNotFit(
                f"the replay memory's rings need {_gib(self.nbytes + size)} on {self.device} "
                f"(at least; {_gib(self.nbytes)} allocated before this array of {_gib(size)}) and do not fit"
            ) from None
        self.nbytes += size
        return t

    def _allocate(self) -> None:
        """Allocate the arrays the host has and the device not yet (observation leaves come with
        the first sample, actions with the first non-``None`` action)."""
        st = self.storage
        if len(self.obs) != len(st.obs):
            self.obs = [self._zeros((st.capacity, *a.shape[1:]), torch.from_numpy(a[:0]).dtype) for a in st.obs]
        if self.act is None and st.act is not None:
            self.act = self._zeros((st.capacity, *st.act.shape[1:]), torch.from_numpy(st.act[:0]).dtype)

    # --- copies --------------------------------------------------------------------------------

    chunk_bytes = 64 << 20
    """The largest copy to the device at once: a restore of a million frames (4 GB) goes over in
    pieces, so that no more than this is pinned on the host at a time."""

    def _put(self, dst: torch.Tensor, lo: int, hi: int, rows: np.ndarray) -> None:
        """Copy host ``rows`` into ``dst[lo:hi]`` (through pinned memory, without waiting, on
        CUDA), :attr:`chunk_bytes` at a time."""
        step = max(1, self.chunk_bytes // max(1, rows[:1].nbytes))
        for a in range(0, hi - lo, step):
            b = min(a + step, hi - lo)
            src = torch.from_numpy(np.ascontiguousarray(rows[a:b]))
            if src.dtype != dst.dtype:
                src = src.to(dst.dtype)
            if self._pin:
                src = src.pin_memory()
            dst[lo + a : lo + b].copy_(src, non_blocking=self._pin)

    def _pairs(self) -> list[tuple[torch.Tensor, np.ndarray]]:
        st = self.storage
        pairs = list(zip(self.obs, st.obs))
        if self.act is not None and st.act is not None:
            pairs.append((self.act, st.act))
        pairs += [(self.rew, st.rew), (self.terminated, st.terminated), (self.truncated, st.truncated)]
        return pairs

    def write(self, start: int, n: int) -> None:
        """Copy the host rows of the ``n`` counters from ``start`` on (already written there).

        Raises:
            RingDoesNotFit: an array the host just allocated does not fit on the device.
        """
        if n <= 0:
            return
        self._allocate()
        cap = self.storage.capacity
        pos = start % cap
        first = min(n, cap - pos)
        spans = [(pos, pos + first)] + ([(0, n - first)] if first < n else [])
        for dst, host in self._pairs():
            for lo, hi in spans:
                self._put(dst, lo, hi, host[lo:hi])

    def reload(self) -> None:
        """Drop the device arrays and copy every host row again (after a restore, which may
        change the arrays' shapes).

        Raises:
            RingDoesNotFit: the rings do not fit on the device.
        """
        self._fresh()  # the old arrays are released before the new ones are allocated
        self._allocate()
        cap = self.storage.capacity
        for dst, host in self._pairs():
            self._put(dst, 0, cap, host)

    def index(self, slots: np.ndarray | Sequence[int]) -> torch.Tensor:
        """An int64 index array (host) as a tensor on the device (pinned, non-blocking on CUDA).

        Args:
            slots: the host indices.
        """
        return to_torch(np.ascontiguousarray(slots, dtype=np.int64), self.device)
