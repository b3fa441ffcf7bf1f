"""The :class:`Buffer` of samples a worker sends, and its wire form: :func:`pack_buffer` and
:func:`unpack_buffer` (the column encoding itself is :mod:`tmrl.wire_buffers`, pure functions on
columns that know nothing of the buffer)."""

from __future__ import annotations

import logging
from collections.abc import Callable
from typing import Any

import numpy as np

from tmrl.config.settings import NetSettings
from tmrl.distributed._common import LOGGER_NAME
from tmrl.errors import UserError
from tmrl.spaces import SampleSchema
from tmrl.wire_buffers import (
    PAYLOAD_VERSION,
    PayloadError,
    _chunk_arrays,
    _skeleton,
    _tree_concat,
    _unpack_column,
    clean_stats,
    pack_samples,
    unpack_samples,
)

__all__ = ["Buffer", "pack_buffer", "unpack_buffer"]

logger = logging.getLogger(LOGGER_NAME)

def _stat_property(name: str, cast: Callable[[Any], Any], what: str) -> property:
    """A ``Buffer`` statistic: set for the buffer's own worker, read as the mean over workers."""
    return property(
        lambda self: self._get_stat(name),
        lambda self, v: self._set_stat(name, cast(v)),
        doc=f"{what} (mean over sources).",
    )


class Buffer:
    """Samples on their way from a worker to the trainer, with episode statistics.

    A sample is ``(act, new_obs, rew, terminated, truncated, info)`` (see docs/internals.md).

    Attributes:
        memory: the list of samples, oldest first.
        sources: ``None`` or a list as long as ``memory``: the integer source id of the worker that
            produced each sample. The trainer fills it when it merges buffers from several workers.
        maxlen: the most samples kept; beyond it the oldest are dropped and counted in ``dropped``.
        stats: per source id (``None`` for the local worker), the latest ``stat_*`` values it
            reported. ``stat_train_return``, ``stat_test_return``, ``stat_train_steps`` and
            ``stat_test_steps`` read the mean over sources of their latest value (0 when none
            reported), so that merging a buffer from one worker does not overwrite another's.
            Setting one of them records it for this buffer's ``source_id``.
        source_id: the id under which values set on this buffer are recorded (``None`` locally).

    Args:
        maxlen: capacity in samples; ``None`` reads ``BUFFERS_MAXLEN`` from the config.
    """

    def __init__(self, maxlen: int | None = None):
        self.maxlen = int(maxlen if maxlen is not None else NetSettings.load().buffers_maxlen)
        if self.maxlen <= 0:
            raise UserError(f"Buffer maxlen must be positive, got {self.maxlen}: set BUFFERS_MAXLEN > 0")
        self._memory: list[Any] = []
        # Received payloads not yet turned into sample tuples, in order after `_memory`: each is
        # (n, the six validated columns of unpack_buffer). See `memory` and `as_columns`.
        self._chunks: list[tuple[int, list[Any]]] = []
        self.sources: list[int] | None = None
        self.stats: dict[int | None, dict[str, float]] = {}
        self.source_id: int | None = None
        self.dropped = 0

    @property
    def memory(self) -> list[Any]:
        """The list of samples, oldest first (samples received from the network become tuples on
        first access: a trainer whose memory reads :meth:`as_columns` never builds them)."""
        if self._chunks:
            self._materialize()
        return self._memory

    @memory.setter
    def memory(self, value: list[Any]) -> None:
        self._memory = value
        self._chunks = []

    def _materialize(self) -> None:
        rows = self._memory
        for n, cols in self._chunks:
            rows += zip(*[_unpack_column(c, n) for c in cols])
        self._chunks = []

    def as_columns(self) -> tuple[Any, Any, np.ndarray, np.ndarray, np.ndarray] | None:
        """The samples as stacked arrays ``(act, obs, rew, terminated, truncated)``, without
        building one tuple per sample, or ``None`` when they are not all in that form (then read
        :attr:`memory`).

        ``act`` is an array of shape ``(n, *action_shape)`` with zeros where a sample's action is
        ``None``, or ``None`` when every action is ``None``; ``obs`` has the structure of one
        observation (nested tuples, lists and dicts) with an array of shape ``(n, *leaf_shape)``
        at each leaf; the three others are 1-D arrays. Infos are not part of it.
        """
        if self._memory or not self._chunks:
            return None
        parts = []
        for n, cols in self._chunks:
            part = _chunk_arrays(n, cols)
            if part is None:
                return None
            parts.append(part)
        if len(parts) == 1:
            return parts[0]
        act_parts = [p[0] for p in parts]
        known = [a for a in act_parts if a is not None]
        if not known:
            act = None
        else:
            shape, dtype = known[0].shape[1:], known[0].dtype
            if any(a.shape[1:] != shape or a.dtype != dtype for a in known):
                return None
            act = np.concatenate(
                [np.zeros((len(p[2]), *shape), dtype) if a is None else a for a, p in zip(act_parts, parts)]
            )
        skeleton = _skeleton(parts[0][1])
        if any(_skeleton(p[1]) != skeleton for p in parts[1:]):
            return None
        try:
            obs = _tree_concat([p[1] for p in parts])
        except ValueError:  # leaves of different shapes: let the memory report it
            return None
        rew, term, trunc = (np.concatenate([p[i] for p in parts]) for i in (2, 3, 4))
        return act, obs, rew, term, trunc

    # --- statistics, kept per source -------------------------------------------------------------

    def _get_stat(self, name: str) -> float:
        values = [d[name] for d in self.stats.values() if name in d]
        if not values:
            return 0 if name.endswith("steps") else 0.0
        mean = sum(values) / len(values)
        return round(mean) if name.endswith("steps") else float(mean)

    def _set_stat(self, name: str, value: float) -> None:
        self.stats.setdefault(self.source_id, {})[name] = value

    stat_train_return = _stat_property("stat_train_return", float, "Return of the latest train episode")
    stat_test_return = _stat_property("stat_test_return", float, "Return of the latest test episode")
    stat_train_steps = _stat_property("stat_train_steps", int, "Length of the latest train episode")
    stat_test_steps = _stat_property("stat_test_steps", int, "Length of the latest test episode")

    # --- samples ---------------------------------------------------------------------------------

    def clip_to_maxlen(self) -> None:
        """Drop the oldest samples beyond ``maxlen`` (counted in ``dropped``, logged)."""
        excess = len(self.memory) - self.maxlen
        if excess > 0:
            del self.memory[:excess]
            if self.sources is not None:
                del self.sources[:excess]
            self.dropped += excess
            logger.warning(
                "buffer full (%d samples): dropped the %d oldest, %d so far",
                self.maxlen,
                excess,
                self.dropped,
            )

    def append_sample(self, sample: Any) -> None:
        """Append one sample ``(act, new_obs, rew, terminated, truncated, info)``."""
        if self._chunks:
            self._materialize()
        self._memory.append(sample)
        if self.sources is not None:
            self.sources.append(-1 if self.source_id is None else self.source_id)
        if len(self._memory) > self.maxlen:
            self.clip_to_maxlen()

    def clear(self) -> None:
        """Remove every sample; the statistics are kept."""
        self.memory = []
        self.sources = None

    def __len__(self) -> int:
        return len(self._memory) + sum(n for n, _ in self._chunks)

    def _sources_or_default(self) -> list[int] | None:
        if self.sources is not None:
            return self.sources
        if self.source_id is not None:
            return [self.source_id] * len(self)
        return None

    def __iadd__(self, other: Buffer) -> Buffer:
        mine = self._sources_or_default()
        theirs = other._sources_or_default()
        if mine is not None or theirs is not None:
            mine = list(mine) if mine is not None else [-1] * len(self)
            theirs = theirs if theirs is not None else [-1] * len(other)
            self.sources = mine + list(theirs)
        if other._chunks and not other._memory:
            self._chunks += other._chunks  # still columns: stays so until someone reads `memory`
        elif len(other):
            self.memory += other.memory
        for key, values in other.stats.items():
            self.stats.setdefault(key, {}).update(values)
        self.dropped += other.dropped
        if len(self) > self.maxlen:
            self.clip_to_maxlen()
        return self

    def __repr__(self) -> str:
        return f"Buffer({len(self)} samples, maxlen={self.maxlen}, sources={len(self.stats)})"



def pack_buffer(buffer: Buffer, source_id: int, seq: int, run: str | None = None) -> dict[str, Any]:
    """Describe ``buffer`` as a data-only dict for :mod:`tmrl.wire`, column by column.

    Args:
        buffer: the samples and statistics to send.
        source_id: the sending worker's id.
        seq: the sending worker's payload counter (lets the trainer count lost payloads).
        run: the run identity of the weights the worker acts with (``None``: none received yet);
            a trainer drops samples stamped for another run.

    Raises:
        UserError: a sample holds something the wire cannot carry (named in the message).
    """
    memory = buffer.memory
    payload = {
        "v": PAYLOAD_VERSION,
        "kind": "samples",
        "src": int(source_id),
        "seq": int(seq),
        "n": len(memory),
        "cols": pack_samples(memory),
        "stats": dict(buffer.stats.get(buffer.source_id, {})),
    }
    if run is not None:
        payload["run"] = str(run)
    return payload


def unpack_buffer(payload: Any, maxlen: int | None = None, schema: SampleSchema | None = None) -> Buffer:
    """Rebuild the :class:`Buffer` sent by :func:`pack_buffer`; ``sources`` is filled with the
    sender's id and its statistics are recorded under that id (non-finite ones are dropped).

    Args:
        payload: the decoded payload.
        maxlen: the buffer's capacity (at least the payload's size).
        schema: when given, the samples are checked against it (shapes, dtypes, finite values,
            action bounds) and cast to its dtypes; the buffer then holds them as columns.

    Raises:
        PayloadError: the payload does not have the structure :func:`pack_buffer` produces.
        SampleRejected: the samples do not fit ``schema``.
    """
    if not isinstance(payload, dict) or payload.get("kind") != "samples":
        raise PayloadError("received an object that is not a tmrl sample payload")
    if payload.get("v") != PAYLOAD_VERSION:
        raise PayloadError(
            f"sample payload version {payload.get('v')!r} is not {PAYLOAD_VERSION}: "
            "run the same tmrl version on workers and trainer"
        )
    n, src = payload.get("n"), payload.get("src")
    if type(n) is not int or n < 0 or type(src) is not int:
        raise PayloadError("malformed sample payload header")
    cols, rows = unpack_samples(payload.get("cols"), n, schema)
    buf = Buffer(maxlen=max(maxlen or 0, n, 1))
    if rows is not None:
        buf.memory = rows
    elif n:  # kept as columns: tuples are built only if someone reads `memory`
        buf._chunks = [(n, cols)]
    buf.sources = [src] * n
    stats = clean_stats(payload.get("stats"))
    if stats:
        buf.stats[src] = stats
    return buf
