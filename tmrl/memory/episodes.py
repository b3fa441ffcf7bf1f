"""Which slot precedes which: :class:`EpisodeLinks`, the per-worker episode chains over a
:class:`~tmrl.memory.storage.RingStorage` that make a transition valid or not and rebuild
histories.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from typing import Any

import numpy as np

from tmrl.errors import UserError
from tmrl.memory.storage import RestoreWindow, RingStorage, _ring_write

__all__ = ["EpisodeLinks"]


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
