"""The distributed pipeline: :class:`Server`, :class:`RolloutWorker`, :class:`Trainer` and their
:class:`Buffer` of samples.

Workers collect samples and send them to the trainer through the server; the trainer trains and
broadcasts its actor's weights back to every worker. Everything crosses the network through
:mod:`tmrl.transport` (tlspyo underneath) as data only (:mod:`tmrl.wire`): never pickle.

Two payloads travel:

- **Samples** (worker -> trainer): a :class:`Buffer` packed column by column
  (:func:`pack_buffer`): samples that share a structure become a few stacked NumPy arrays, which is
  both smaller on the wire and much faster to encode than one small object per sample. Each
  payload carries the worker's random source id, a sequence number and the worker's episode
  statistics.
- **Weights** (trainer -> workers): the bytes of the file written by ``actor.save``, with a short
  description of the actor's observation and action spaces, so that a worker built for another
  environment fails with a clear error instead of loading nonsense.

Nothing here reads the configuration at import: defaults that come from ``config.json`` are
resolved when an object is built.
"""

from __future__ import annotations

import collections
import contextlib
import datetime
import hashlib
import itertools
import logging
import math
import os
import secrets
import struct
import tempfile
import threading
import time
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import Any, ClassVar

import numpy as np

from tmrl.config.settings import NetSettings
from tmrl.errors import UserError
from tmrl.spaces import (  # noqa: F401 (re-exported: their home was this module)
    PinnedSampleSchema,
    Rows,
    SampleRejected,
    SampleSchema,
    SpacesMismatchError,
    _space_str,
    check_spaces,
    describe_spaces,
    finite_stat,
)
from tmrl.util import RateLimitedLog, show_progress_on_console
from tmrl.wire_buffers import (  # the column packing of sample buffers: its home was this module
    PAYLOAD_VERSION,
    PayloadError,
    _chunk_arrays,
    _skeleton,
    _tree_concat,
    _unpack_column,
    pack_buffer,
    unpack_buffer,
)

__all__ = [
    "Buffer",
    "PayloadOrder",
    "RolloutWorker",
    "Server",
    "SpacesMismatchError",
    "Trainer",
    "TrainerInterface",
    "describe_spaces",
    "pack_buffer",
    "unpack_buffer",
]

logger = logging.getLogger(__name__)

STOP_TIMEOUT = 2.0
"""Seconds a role interrupted by a signal gives its network process to flush before killing it
(a role must be gone within 5 s of SIGTERM or Ctrl-C)."""


def _one_line(err: BaseException) -> str:
    """An exception as one short line (its message's first line, or its type)."""
    text = str(err).strip().splitlines()
    return (text[0] if text else type(err).__name__)[:300]


class _FromConfig:
    """Default of an argument whose ``None`` has a meaning of its own (for example
    ``checkpoint_path=None``: no checkpoint); the real default is read from the config."""

    def __repr__(self) -> str:
        return "<from config>"


FROM_CONFIG: Any = _FromConfig()


class _NotGiven:
    """Default of an argument whose ``None`` has a meaning of its own and whose absence too."""

    def __repr__(self) -> str:
        return "<not given>"


NOT_GIVEN: Any = _NotGiven()


def _given(value: Any, default: Any) -> Any:
    """``value`` unless it is ``None`` or ``FROM_CONFIG`` (then ``default``, from the settings)."""
    return default if value is None or value is FROM_CONFIG else value


def _given_keep_none(value: Any, default: Any) -> Any:
    """``value`` unless it is ``FROM_CONFIG``: an explicit ``None`` means something of its own."""
    return default if value is FROM_CONFIG else value


def _settings(settings: NetSettings | None) -> NetSettings:
    """``settings``, or those of ``config.json`` (loaded now: a role reads the config when it is
    built, never at import)."""
    return settings if settings is not None else NetSettings.load()


# ================================================================================================
# Buffer


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


# ================================================================================================
# Weights envelope


_WEIGHTS_MAGIC = b"TMRLWGT2"
_U32 = struct.Struct("<I")
_RESERVED_HEADER_KEYS = frozenset(("v", "kind", "version", "spaces", "size", "run", "sha256"))


def pack_weights(
    data: bytes,
    spaces: dict[str, Any] | None,
    version: int,
    run: str | None = None,
    meta: dict[str, Any] | None = None,
    key: Any = None,
) -> bytes:
    """The bytes broadcast to workers: a magic, a small :mod:`tmrl.wire` header, a signature and
    the weights file's bytes as they are (no re-encoding of the big part: one copy for a model of
    any size).

    Args:
        data: the weights file's bytes.
        spaces: :func:`describe_spaces` of the actor (``None``: unknown).
        version: the trainer's broadcast counter.
        run: the run identity (workers stamp their samples with it).
        meta: extra data-only header fields (names other than the reserved ones).
        key: a :class:`~tmrl.transport.credentials.TrainerKey`: the header (which holds the
            SHA-256 of ``data``) is signed with it. ``None``: unsigned.

    Raises:
        ValueError: ``meta`` uses a reserved name.
    """
    from tmrl import wire

    fields: dict[str, Any] = {
        "v": PAYLOAD_VERSION,
        "kind": "weights",
        "version": int(version),
        "spaces": spaces,
        "size": len(data),
        "run": run,
    }
    if meta:
        clash = _RESERVED_HEADER_KEYS.intersection(meta)
        if clash:
            raise ValueError(f"weights header fields {sorted(clash)} are reserved")
        fields.update(meta)
    signature = b""
    if key is not None:
        fields["sha256"] = hashlib.sha256(data).digest()
    header = wire.encode(fields)
    if key is not None:
        signature = key.sign(header)
    return b"".join((_WEIGHTS_MAGIC, _U32.pack(len(header)), header, _U32.pack(len(signature)), signature, data))


class WeightsRejected(PayloadError):
    """Received weights that this worker must not load (the message says why)."""


def unpack_weights(
    envelope: bytes | bytearray | memoryview, public_key: bytes | None = None
) -> tuple[dict[str, Any], memoryview]:
    """Inverse of :func:`pack_weights`: ``(header, weights bytes as a view, not a copy)``.

    Args:
        envelope: the received bytes.
        public_key: the pinned trainer public key (PEM): the envelope must then be signed by it
            and its data must match the signed SHA-256. ``None``: no signature is required.

    Raises:
        PayloadError: not a weights envelope of this tmrl version, or truncated.
        WeightsRejected: unsigned, or not signed by ``public_key``.
    """
    from tmrl import wire

    view = memoryview(envelope)
    start = len(_WEIGHTS_MAGIC) + _U32.size
    if len(view) < start or bytes(view[: len(_WEIGHTS_MAGIC)]) != _WEIGHTS_MAGIC:
        raise PayloadError("received weights in an unknown format: run the same tmrl version everywhere")
    (hlen,) = _U32.unpack(view[len(_WEIGHTS_MAGIC) : start])
    header_bytes = bytes(view[start : start + hlen])
    sig_at = start + hlen
    if len(view) < sig_at + _U32.size:
        raise PayloadError("received weights that are truncated")
    (slen,) = _U32.unpack(view[sig_at : sig_at + _U32.size])
    signature = bytes(view[sig_at + _U32.size : sig_at + _U32.size + slen])
    data = view[sig_at + _U32.size + slen :]
    try:
        header = wire.decode(header_bytes)
    except wire.DecodeError as err:
        raise PayloadError(f"received weights with a corrupt header ({err})") from None
    if (
        not isinstance(header, dict)
        or header.get("kind") != "weights"
        or header.get("v") != PAYLOAD_VERSION
        or header.get("size") != len(data)
        or len(signature) != slen
    ):
        raise PayloadError("received weights that are truncated or from another tmrl version")
    if public_key is not None:
        from tmrl.transport.credentials import verify_signature

        if not signature:
            raise WeightsRejected("the weights are not signed, but this worker pins the trainer's key")
        if not verify_signature(public_key, signature, header_bytes):
            raise WeightsRejected("the weights are not signed by the trainer whose key this worker pins")
        if header.get("sha256") != hashlib.sha256(data).digest():
            raise WeightsRejected("the weights do not match their signed checksum (corrupt or altered)")
    return header, data


# ================================================================================================
# Server


class Server:
    """The central relay: one :class:`Trainer` and up to ``max_workers`` :class:`RolloutWorker`
    connect to it. It forwards samples to the trainer and the trainer's weights to every worker
    (the latest weights also to workers that connect later).

    The relay runs in a child process from construction until :meth:`stop` or the end of this
    process: a ``Server`` that is not kept in a variable keeps running.

    Args:
        port: public port (``PORT`` in the config when ``None``).
        password: shared password (``PASSWORD``).
        local_port: accepted for compatibility with tmrl 0.7, unused.
        header_size: tlspyo header size in bytes (``HEADER_SIZE``); the same on every process.
        security: ``"TLS"`` or ``None`` for plain TCP (``SECURITY`` by default).
        keys_dir: folder holding ``key.pem`` and ``certificate.pem`` (``CREDENTIALS_DIRECTORY``).
        max_workers: most workers at once; ``None`` or negative for no limit (``NB_WORKERS``).
        settings: the :class:`~tmrl.config.settings.NetSettings` the ``None`` arguments are read
            from (default: derived from ``config.json`` when the server is built).

    Raises:
        UserError: the port cannot be bound, TLS credentials are missing, or plain TCP is refused.
    """

    # why: keeps every Server reachable until stop(), so that a Server() not kept in a variable runs on
    _alive: ClassVar[list[Server]] = []

    def __init__(
        self,
        port: int | None = None,
        password: str | None = None,
        local_port: int | None = None,
        header_size: int | None = None,
        security: str | None = FROM_CONFIG,
        keys_dir: str | os.PathLike[str] | None = None,
        max_workers: int | None = FROM_CONFIG,
        *,
        settings: NetSettings | None = None,
    ):
        from tmrl.transport import BACKENDS

        show_progress_on_console()
        cfg = _settings(settings)
        port = int(_given(port, cfg.port))
        password = _given(password, cfg.password)
        header_size = int(_given(header_size, cfg.header_size))
        security = _given_keep_none(security, cfg.security)
        keys_dir = _given(keys_dir, cfg.credentials_directory)
        max_workers = _given_keep_none(max_workers, cfg.max_workers)
        if max_workers is not None and int(max_workers) < 0:
            max_workers = None
        self.port = port
        from tmrl.transport.credentials import TRAINER_PUBLIC_KEY_FILE

        self._relay = BACKENDS[cfg.transport].relay(
            port=port,
            password=password,
            local_port=local_port,
            header_size=header_size,
            security=security,
            keys_dir=str(keys_dir) if keys_dir is not None else None,
            max_workers=max_workers,
            trainer_key_file=Path(keys_dir) / TRAINER_PUBLIC_KEY_FILE if keys_dir is not None else None,
            **cfg.link_options(),
            **cfg.relay_options(),
            **cfg.transport_options("relay"),
        )
        Server._alive.append(self)
        logger.info("server listening on port %d (%s)", port, "TLS" if security else "plain TCP")

    @property
    def running(self) -> bool:
        """Whether the relay process is running."""
        return bool(self._relay.running)

    def stop(self, timeout: float = 15.0) -> None:
        """Stop the relay (idempotent): it may flush for up to ``timeout`` seconds, then it is
        killed."""
        self._relay.stop(timeout)
        if self in Server._alive:
            Server._alive.remove(self)

    def __enter__(self) -> Server:
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()


# ================================================================================================
# Trainer side


def _make_link(
    link_cls: Any,
    server_ip: str,
    server_port: int | None,
    password: str | None,
    local_port: int | None,
    header_size: int | None,
    security: str | None,
    keys_dir: str | os.PathLike[str] | None,
    hostname: str | None,
    settings: NetSettings | None = None,
    **extra: Any,
) -> Any:
    """A transport link (``WorkerLink`` or ``TrainerLink``) with every unset argument taken from
    the settings, as the worker and the trainer both need; ``extra`` goes to the link as is."""
    cfg = _settings(settings)
    keys_dir = _given(keys_dir, cfg.credentials_directory)
    return link_cls(
        server_ip,
        int(_given(server_port, cfg.port)),
        _given(password, cfg.password),
        local_port=local_port,
        header_size=int(_given(header_size, cfg.header_size)),
        security=_given_keep_none(security, cfg.security),
        keys_dir=str(keys_dir) if keys_dir is not None else None,
        hostname=_given(hostname, cfg.hostname),
        **cfg.link_options(),
        **extra,
    )


class PayloadOrder:
    """Per-worker bookkeeping of payload sequence numbers on the trainer side.

    The transport delivers sample payloads at least once: after a dropped connection the relay
    re-sends what the trainer did not acknowledge, possibly after newer payloads. A payload is
    taken when its number is new for its worker, including a late one that fills a gap; a
    second copy is refused. Gaps still open are counted as lost and logged.

    Memory is bounded whatever the peers send: at most ``max_sources`` workers are followed (the
    least recently heard of is forgotten) and at most ``max_gaps`` open gaps per worker.

    Args:
        max_gaps: how many open gaps are remembered per worker (the oldest are forgotten).
        max_sources: how many workers are followed.
    """

    def __init__(self, max_gaps: int = 10_000, max_sources: int = 4096):
        self.max_gaps = max_gaps
        self.max_sources = max_sources
        self._last: collections.OrderedDict[Any, int] = collections.OrderedDict()
        self._gaps: dict[Any, dict[int, None]] = {}
        self.lost = 0
        self.duplicates = 0
        self._lost_log = RateLimitedLog(logger, logging.WARNING, 1.0)

    def accept(self, src: Any, seq: Any) -> bool:
        """Whether payload ``seq`` of worker ``src`` should be used (``False``: a duplicate)."""
        if type(seq) is not int:
            return True  # a peer that does not number its payloads: nothing to check
        last = self._last.get(src)
        if last is not None:
            self._last.move_to_end(src)
        elif len(self._last) >= self.max_sources:
            old, _ = self._last.popitem(last=False)
            self._gaps.pop(old, None)
        gaps = self._gaps.setdefault(src, {})
        if last is None or seq == last + 1:
            self._last[src] = seq
            return True
        if seq > last + 1:
            missing = seq - last - 1
            for k in range(max(last + 1, seq - self.max_gaps), seq):
                gaps[k] = None
            while len(gaps) > self.max_gaps:
                del gaps[next(iter(gaps))]
            self.lost += missing
            self._lost_log("worker %s: %d sample payloads missing (%d in total)", src, missing, self.lost)
            self._last[src] = seq
            return True
        if seq in gaps:  # late, but new
            del gaps[seq]
            self.lost -= 1
            return True
        self.duplicates += 1
        logger.debug("worker %s: dropped a second copy of payload %d", src, seq)
        return False


def _weights_problem(actor: Any, data: bytes | memoryview) -> str | None:
    """What is wrong with the weights file ``data`` for ``actor``, or ``None``.

    Safetensors files (the built-in actors' format) are read with NumPy: every floating-point
    tensor must be finite and, for a module, names and shapes must be the module's (so that
    loading cannot fail half-way). Other formats (a user actor's own) are left to ``actor.load``.
    """
    try:
        from safetensors.numpy import load

        arrays = load(bytes(data))
    except Exception:  # noqa: BLE001 (not safetensors, or a dtype NumPy lacks: the actor decides)
        return None
    for name, arr in arrays.items():
        if arr.dtype.kind in "fc" and not np.isfinite(arr).all():
            return f"tensor {name} holds non-finite values"
    state_dict = getattr(actor, "state_dict", None)
    if callable(state_dict):
        try:
            mine = {k: tuple(v.shape) for k, v in state_dict().items()}
        except Exception:  # noqa: BLE001 (not a torch module after all: nothing to compare)
            return None
        theirs = {k: tuple(a.shape) for k, a in arrays.items()}
        if mine != theirs:
            diff = sorted(set(mine) ^ set(theirs)) or [k for k in mine if mine[k] != theirs[k]]
            return f"the tensors do not fit this actor (first difference: {diff[0]!r})"
    return None


class TrainerInterface:
    """The trainer's side of the network, as ``TrainingOffline.run_epoch`` sees it:
    :meth:`retrieve_buffer` and :meth:`broadcast_model`.

    Statistics are kept per worker across calls: the buffer returned by :meth:`retrieve_buffer`
    reports, for each worker, the latest episode statistics it ever sent. When the connection to
    the server comes back (a restarted server), the latest weights are broadcast again.

    Received sample batches are checked before anyone sees them: their structure always, and
    when :attr:`schema` is set, their shapes, dtypes and values (see :class:`~tmrl.spaces.SampleSchema`).
    A batch that fails is dropped whole, counted in :attr:`rejected_batches` and reported in a
    rate-limited log line naming the worker and the first problem. Batches stamped with another
    :attr:`run_id` are dropped and counted in :attr:`foreign_batches`.

    Args: as :class:`Trainer` (``server_ip``, ``server_port``, ``password``, ``header_size``,
    ``security``, ``keys_dir``, ``hostname``, ``model_path``); ``local_com_port`` and
    ``max_buf_len`` are accepted for compatibility with tmrl 0.7 and unused.
    ``schema``: the run's :class:`~tmrl.spaces.SampleSchema` (``None``: structure only).
    ``run_id``: the run identity stamped on the weights (``None``: none).
    ``sign_weights``: sign every broadcast with the trainer key of the credentials folder
    (created there when missing; see :mod:`tmrl.transport.credentials`).

    Raises:
        UserError: bad connection settings (see :mod:`tmrl.transport`).
    """

    def __init__(
        self,
        server_ip: str | None = None,
        server_port: int | None = None,
        password: str | None = None,
        local_com_port: int | None = None,
        header_size: int | None = None,
        max_buf_len: int | None = None,
        security: str | None = FROM_CONFIG,
        keys_dir: str | os.PathLike[str] | None = None,
        hostname: str | None = None,
        model_path: str | os.PathLike[str] | None = None,
        schema: SampleSchema | None = None,
        run_id: str | None = None,
        sign_weights: bool = True,
        *,
        settings: NetSettings | None = None,
    ):
        from tmrl.transport import BACKENDS

        cfg = _settings(settings)
        self.model_path = Path(_given(model_path, cfg.model_path_trainer))
        self.server_ip = _given(server_ip, cfg.server_ip_for_trainer)
        self.maxlen = cfg.buffers_maxlen
        self.schema = schema
        self.run_id = run_id
        keys = _given(keys_dir, cfg.credentials_directory)
        self._key: Any = None
        if sign_weights and keys is not None:
            from tmrl.transport.credentials import ensure_trainer_key

            self._key = ensure_trainer_key(keys)
        self._link = _make_link(
            BACKENDS[cfg.transport].trainer,
            self.server_ip,
            server_port,
            password,
            local_com_port,
            header_size,
            security,
            keys_dir,
            hostname,
            cfg,
            trainer_key=self._key,
            **cfg.transport_options("trainer"),
        )
        self._stats: collections.OrderedDict[int | None, dict[str, float]] = collections.OrderedDict()
        self._order = PayloadOrder()
        self.rejected_batches = 0
        self.foreign_batches = 0
        self.received_samples = 0
        self.skipped_broadcasts = 0
        self.weights_version = 0
        self.pace_source: Callable[[], dict[str, Any] | None] | None = None
        """Gives the pacing fields broadcast with the weights (``TrainingOffline.pace``)."""
        self._reject_log = RateLimitedLog(logger, logging.WARNING, 1.0)
        self._foreign_log = RateLimitedLog(logger, logging.INFO, 1.0)
        self._last_weights: bytes | None = None
        self._weights_lock = threading.Lock()
        self.connections = 0
        """Connections to the server seen so far (the latest weights are broadcast again on each
        after the first)."""
        self._closed = threading.Event()
        self._watcher = threading.Thread(
            target=self._rebroadcast_on_reconnect, daemon=True, name="tmrl-trainer-reconnect"
        )
        self._watcher.start()
        logger.info("trainer connecting to the server at %s", self.server_ip)

    @property
    def rejected_payloads(self) -> int:
        """Alias of :attr:`rejected_batches` (its earlier name)."""
        return self.rejected_batches

    @property
    def lost_payloads(self) -> int:
        """Sample payloads that some worker sent and that never arrived (so far)."""
        return self._order.lost

    @property
    def duplicate_payloads(self) -> int:
        """Second copies of payloads, dropped (the transport delivers at least once)."""
        return self._order.duplicates

    def counters(self) -> dict[str, int]:
        """Counters for the trainer's metrics row: ``rejected_batches`` (malformed or off-schema
        batches dropped), ``foreign_batches`` (stamped for another run), ``skipped_broadcasts``
        (weights with non-finite values not sent)."""
        return {
            "rejected_batches": self.rejected_batches,
            "foreign_batches": self.foreign_batches,
            "skipped_broadcasts": self.skipped_broadcasts,
        }

    @property
    def connected(self) -> bool:
        """Whether the trainer is connected to the server right now."""
        return bool(self._link.connected)

    def wait_connected(self, timeout: float | None = None) -> bool:
        """Wait until connected to the server; ``False`` after ``timeout`` seconds."""
        return bool(self._link.wait_connected(timeout))

    def _rebroadcast_on_reconnect(self) -> None:
        # why: a restarted server has lost the latest weights; workers that (re)connect to it
        # would otherwise wait for the next training step, which may itself wait for their samples.
        # Only a reconnection: both links deliver what was broadcast before their first connection,
        # and weights broadcast just after it, before this thread looked, were sent once already
        # (sent again, a worker could take them for the next ones).
        was_connected = False
        while not self._closed.wait(0.1):
            connected = self._link.connected
            if connected and not was_connected:
                with self._weights_lock:
                    if self.connections and self._last_weights is not None:
                        try:
                            self._link.broadcast_weights(self._last_weights)
                        except (ConnectionError, RuntimeError):  # closing: nothing to do
                            return
                self.connections += 1
            was_connected = connected

    def _unpack(self, payload: Any) -> Buffer | None:
        """The payload as a checked buffer, or ``None`` (dropped, counted and logged)."""
        src = payload.get("src") if isinstance(payload, dict) else None
        who = f"worker {src}" if type(src) is int else "a peer"
        run = payload.get("run") if isinstance(payload, dict) else None
        if run is not None and self.run_id is not None and run != self.run_id:
            self.foreign_batches += 1
            self._foreign_log(
                "dropped a sample batch from %s made for another run (%d so far): it acted with weights "
                "of an earlier run",
                who,
                self.foreign_batches,
            )
            return None
        try:
            buf = unpack_buffer(payload, maxlen=self.maxlen, schema=self.schema)
        except (PayloadError, SampleRejected) as err:
            self.rejected_batches += 1
            self._reject_log(
                "dropped a sample batch from %s: %s (%d dropped so far)", who, err, self.rejected_batches
            )
            return None
        if not self._order.accept(payload["src"], payload.get("seq")):
            return None  # a second copy of a payload already taken (at-least-once delivery)
        return buf

    def retrieve_buffer(self) -> Buffer:
        """Every sample received since the last call (possibly none), never blocking.

        ``sources`` gives each sample's worker id; batches that are malformed, do not fit
        :attr:`schema` or were made for another run are dropped (see the class docstring).
        """
        res = Buffer(maxlen=self.maxlen)
        res.sources = []
        for payload in self._link.receive_samples():
            buf = self._unpack(payload)
            if buf is None:
                continue
            for key, values in buf.stats.items():
                self._stats.setdefault(key, {}).update(values)
                self._stats.move_to_end(key)
                while len(self._stats) > 1024:  # bounded whatever source ids peers make up
                    self._stats.popitem(last=False)
            res += buf
        self._reject_log.flush()
        self._foreign_log.flush()
        self.received_samples += len(res)
        res.stats = {k: dict(v) for k, v in self._stats.items()}
        return res

    def broadcast_model(self, model: Any) -> None:
        """Send ``model``'s weights (an ``ActorModule``) to every worker.

        The actor saves itself to a temporary file next to ``model_path``, which then replaces
        ``model_path`` (the trainer keeps a local copy) and whose bytes are broadcast, stamped
        with :attr:`run_id` and signed with the trainer key. Weights that hold a non-finite
        value are neither kept nor sent (logged, counted in ``skipped_broadcasts``).
        """
        self.model_path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(
            prefix=f".{self.model_path.name}.", suffix=".tmp", dir=self.model_path.parent
        )
        os.close(fd)
        try:
            model.save(tmp)
            data = Path(tmp).read_bytes()
            problem = _weights_problem(None, data)
            if problem is not None:
                self.skipped_broadcasts += 1
                logger.error(
                    "did not broadcast the actor's weights: %s (%d broadcasts skipped)", problem, self.skipped_broadcasts
                )
                return
            os.replace(tmp, self.model_path)
        finally:
            if os.path.exists(tmp):
                os.unlink(tmp)
        obs_space = getattr(model, "observation_space", None)
        act_space = getattr(model, "action_space", None)
        spaces = (
            describe_spaces(obs_space, act_space) if obs_space is not None and act_space is not None else None
        )
        self.weights_version += 1
        pace = self.pace_source() if self.pace_source is not None else None
        envelope = pack_weights(data, spaces, self.weights_version, run=self.run_id, meta=pace, key=self._key)
        with self._weights_lock:
            self._last_weights = envelope
            self._link.broadcast_weights(envelope)

    def close(self, timeout: float = 15.0) -> None:
        """Disconnect (idempotent); the link's process is killed after ``timeout`` seconds."""
        self._closed.set()
        self._link.close(timeout)


class Trainer:
    """Where training happens: runs ``training_cls`` epoch after epoch, feeding it the samples of
    every worker and broadcasting its actor's weights, with a checkpoint after each epoch.

    Args:
        training_cls: a callable (usually a ``partial`` of ``TorchTrainingOffline``) building the
            training instance; ``None`` uses ``config_objects.TRAINER``.
        server_ip: the server's address (``SERVER_IP_FOR_TRAINER``).
        server_port: the server's port (``PORT``).
        password: the server's password (``PASSWORD``).
        local_com_port: accepted for compatibility with tmrl 0.7, unused.
        header_size: tlspyo header size (``HEADER_SIZE``).
        max_buf_len: accepted for compatibility with tmrl 0.7, unused (the transport bounds memory).
        security: ``"TLS"`` or ``None`` (``SECURITY``).
        keys_dir: credentials folder (``CREDENTIALS_DIRECTORY``).
        hostname: TLS hostname of the server certificate (``HOSTNAME``).
        model_path: where the trainer keeps a copy of the latest weights (``MODEL_PATH_TRAINER``).
        checkpoint_path: checkpoint file, written after every epoch and resumed from at start;
            ``None`` for no checkpoint (by default ``CHECKPOINT_PATH``).
        dump_run_instance_fn: ``fn(run_instance, path)`` writing a checkpoint
            (default: :func:`tmrl.checkpoint.dump_run_instance`: a checkpoint folder with the
            agent, the replay memory, counters and RNG states, written atomically).
        load_run_instance_fn: ``fn(path) -> run_instance`` (default: restores the checkpoint
            folder into a fresh ``training_cls()``; see :func:`tmrl.checkpoint.load_checkpoint`).
        updater_fn: ``fn(run_instance, training_cls) -> run_instance`` applied after loading a
            checkpoint, for example to change hyperparameters of a resumed run.
        obs_preprocessor: the workers' observation preprocessor (``OBS_PREPROCESSOR`` of the
            built-in pipelines; ``None``: the workers use none).
        sample_compressor: the workers' sample compressor (``SAMPLE_COMPRESSOR``; ``None``: none).
            With ``obs_preprocessor`` and the spaces of the training instance (``run_instance.agent.observation_space`` and
            ``action_space``) they give the run's :class:`~tmrl.spaces.SampleSchema`: sample
            batches that do not fit it are dropped before the memory sees them. When neither is
            given (tmrl 0.7's scripts), batches are still checked (numbers, finite values, actions
            in bounds) but their shapes are fixed by the first batch received
            (:class:`~tmrl.spaces.PinnedSampleSchema`); ``python -m tmrl --trainer`` always gives
            them.

    A run has an identity (:attr:`run_id`): created for a new run, kept in the default
    checkpoint, stamped on every broadcast; workers stamp their samples with the identity of the
    weights they act with, and samples made for another run are dropped.

    Raises:
        UserError: bad connection settings; at :meth:`run`, a checkpoint that cannot be resumed
            (for example a checkpoint folder whose header is missing), or a schema that cannot be
            derived.
    """

    def __init__(
        self,
        training_cls: Callable[[], Any] | None = None,
        server_ip: str | None = None,
        server_port: int | None = None,
        password: str | None = None,
        local_com_port: int | None = None,
        header_size: int | None = None,
        max_buf_len: int | None = None,
        security: str | None = FROM_CONFIG,
        keys_dir: str | os.PathLike[str] | None = None,
        hostname: str | None = None,
        model_path: str | os.PathLike[str] | None = None,
        checkpoint_path: str | os.PathLike[str] | None = FROM_CONFIG,
        dump_run_instance_fn: Callable[[Any, str], None] | None = None,
        load_run_instance_fn: Callable[[str], Any] | None = None,
        updater_fn: Callable[[Any, Any], Any] | None = None,
        obs_preprocessor: Callable[[Any], Any] | None = NOT_GIVEN,
        sample_compressor: Callable[..., tuple] | None = NOT_GIVEN,
        *,
        settings: NetSettings | None = None,
    ):
        show_progress_on_console()
        cfg = self.settings = _settings(settings)
        if training_cls is None:
            from tmrl.config import config_objects

            training_cls = config_objects.TRAINER
        self.training_cls = training_cls
        cp = _given_keep_none(checkpoint_path, cfg.checkpoint_path)
        self.checkpoint_path = str(cp) if cp is not None else None
        self._default_checkpoint = dump_run_instance_fn is None and load_run_instance_fn is None
        if dump_run_instance_fn is None or load_run_instance_fn is None:
            from tmrl import checkpoint

            dump_run_instance_fn = dump_run_instance_fn or checkpoint.dump_run_instance
            load_run_instance_fn = load_run_instance_fn or checkpoint.make_load_run_instance_fn(training_cls)
        self.dump_run_instance_fn = dump_run_instance_fn
        self.load_run_instance_fn = load_run_instance_fn
        self.updater_fn = updater_fn
        self.obs_preprocessor = obs_preprocessor
        self.sample_compressor = sample_compressor
        self.run_instance: Any = None
        self.run_id: str | None = None
        self.callbacks: list[Any] = []
        self.metrics_logger: Any = None
        """where the training loop reports each round (a :class:`tmrl.metrics.MetricsLogger`); ``None``:
        the training instance's own (console only unless it was given one). ``python -m tmrl
        --trainer`` sets one that also writes ``<data folder>/logs/<RUN_NAME>/metrics.csv``."""
        self.interface = TrainerInterface(
            server_ip=server_ip,
            server_port=server_port,
            password=password,
            local_com_port=local_com_port,
            header_size=header_size,
            max_buf_len=max_buf_len,
            security=security,
            keys_dir=keys_dir,
            hostname=hostname,
            model_path=model_path,
            settings=cfg,
        )

    def checkpoint_exists(self) -> bool:
        """Whether there is a checkpoint to resume from at ``checkpoint_path``.

        Raises:
            CheckpointError: a checkpoint folder holds saved state but no header (it would be
                overwritten by a new run): it is refused, never overwritten.
        """
        path = self.checkpoint_path
        if path is None or not os.path.exists(path):
            return False
        if self._default_checkpoint and os.path.isdir(path):
            from tmrl.checkpoint import checkpoint_complete

            return checkpoint_complete(path)
        return True

    def _load_or_create(self) -> Any:
        path = self.checkpoint_path
        if path is not None and self.checkpoint_exists():
            t0 = time.perf_counter()
            run_instance = self.load_run_instance_fn(path)
            logger.info(
                "resumed from checkpoint %s (epoch %s) in %.1f s",
                path,
                getattr(run_instance, "epoch", "?"),
                time.perf_counter() - t0,
            )
            if self.updater_fn is not None:
                run_instance = self.updater_fn(run_instance, self.training_cls)
            run_id = getattr(run_instance, "run_id", None)
            self.run_id = run_id if isinstance(run_id, str) and run_id else None
        else:
            run_instance = self.training_cls()
            self.run_id = secrets.token_hex(8)
            try:
                run_instance.run_id = self.run_id  # kept by the default checkpoint
            except AttributeError:  # a training class with __slots__: the identity lives here only
                pass
            if path is not None:
                self.dump_run_instance_fn(run_instance, path)
        if self.metrics_logger is not None and hasattr(run_instance, "metrics_logger"):
            run_instance.metrics_logger = self.metrics_logger
        add = getattr(run_instance, "add_callback", None)
        for callback in self.callbacks:
            if add is None:
                raise UserError(f"{type(run_instance).__name__} takes no callbacks: build it from tmrl.training_offline")
            add(callback)
        self._announce(run_instance)
        return run_instance

    def add_callback(self, callback: Any) -> None:
        """Observe training: ``callback`` goes to the training loop when :meth:`run` builds or
        resumes it (:meth:`tmrl.training_offline.TrainingOffline.add_callback`: a
        ``TrainingCallback``, or a function called with each round's ``RoundMetrics``)."""
        self.callbacks.append(callback)

    def _announce(self, run_instance: Any) -> None:
        """Give the interface the run's schema and identity, and broadcast the actor at once:
        workers that (re)connect get this run's weights (and identity) without waiting for the
        next training step, which may itself wait for their samples."""
        self.interface.run_id = self.run_id
        pace = getattr(run_instance, "pace", None)
        self.interface.pace_source = pace if callable(pace) else None
        agent = getattr(run_instance, "agent", None)
        spaces = None
        for holder in (agent, run_instance):
            obs, act = getattr(holder, "observation_space", None), getattr(holder, "action_space", None)
            if obs is not None and act is not None:
                spaces = (obs, act)
                break
        if spaces is not None and self.obs_preprocessor is NOT_GIVEN and self.sample_compressor is NOT_GIVEN:
            self.interface.schema = PinnedSampleSchema(spaces[1])
            logger.info(
                "sample batches are checked for numbers, finite values and actions in bounds, their shapes are "
                "fixed by the first batch: give Trainer the workers' obs_preprocessor and sample_compressor "
                "(None if they have none) to check shapes against the spaces"
            )
        elif spaces is not None:
            given = [None if f is NOT_GIVEN else f for f in (self.obs_preprocessor, self.sample_compressor)]
            self.interface.schema = SampleSchema(*spaces, *given)
            logger.info("sample batches are checked against %r", self.interface.schema)
        else:
            logger.info("the training instance names no spaces: sample batches are checked for structure only")
        ensure_finite = getattr(run_instance, "ensure_finite", None)  # also keeps a good copy
        if agent is not None and hasattr(agent, "get_actor") and (not callable(ensure_finite) or ensure_finite()):
            try:
                self.interface.broadcast_model(agent.get_actor())
            except Exception:
                logger.exception("could not broadcast the actor")

    def _iterate_epochs(self) -> Iterable[Any]:
        run_instance = self._load_or_create()
        self.run_instance = run_instance
        while run_instance.epoch < run_instance.epochs:
            stats = run_instance.run_epoch(interface=self.interface)
            ensure_finite = getattr(run_instance, "ensure_finite", None)
            if callable(ensure_finite) and not ensure_finite():
                logger.error("checkpoint not saved: the agent's parameters are not finite")
            elif self.checkpoint_path is not None:
                t0 = time.perf_counter()
                self.dump_run_instance_fn(run_instance, self.checkpoint_path)
                logger.info("checkpoint saved in %.2f s", time.perf_counter() - t0)
            yield stats

    def run(self) -> None:
        """Train until ``training_cls``'s number of epochs is reached; the network link is
        closed at the end (also on Ctrl-C, which propagates as ``KeyboardInterrupt``: then within
        a few seconds, without waiting for the server)."""
        try:
            for _ in self._iterate_epochs():
                pass
        except KeyboardInterrupt:
            self.interface.close(STOP_TIMEOUT)
            raise
        finally:
            self.interface.close()

    def run_with_wandb(
        self,
        entity: str | None = None,
        project: str | None = None,
        run_id: str | None = None,
        key: str | None = None,
    ) -> None:
        """Like :meth:`run`, logging every epoch's statistics to Weights & Biases.

        Args:
            entity: wandb entity, a user or team (``WANDB_ENTITY`` from the config when ``None``).
            project: wandb project (``WANDB_PROJECT``).
            run_id: wandb run id, to resume the same wandb run (``WANDB_RUN_ID``).
            key: wandb API key (``WANDB_KEY``); set as ``WANDB_API_KEY`` for this process.

        Raises:
            UserError: wandb is not installed.
        """
        try:
            import wandb  # type: ignore[import-not-found]
        except ImportError as err:
            raise UserError('wandb is not installed: pip install "tmrl[wandb]"') from err
        from tmrl.util import partial_to_dict

        cfg = self.settings
        entity = _given(entity, cfg.wandb_entity)
        project = _given(project, cfg.wandb_project)
        run_id = _given(run_id, cfg.wandb_run_id)
        key = _given(key, cfg.wandb_key)
        if key:
            os.environ["WANDB_API_KEY"] = key
        try:
            config = partial_to_dict(self.training_cls)  # type: ignore[arg-type]
        except (ValueError, TypeError, AttributeError):
            config = {}
        resume = self.checkpoint_exists()
        wandb_dir = tempfile.mkdtemp(prefix="tmrl-wandb-")
        wandb.init(
            dir=wandb_dir,
            entity=entity,
            project=project,
            id=run_id,
            resume="allow" if resume else None,
            config=config,
        )
        try:
            for stats in self._iterate_epochs():
                for entry in stats if isinstance(stats, list) else [stats]:
                    if entry is None:
                        continue
                    wandb.log({k: v for k, v in dict(entry).items() if isinstance(v, (int, float))})
        except KeyboardInterrupt:
            self.interface.close(STOP_TIMEOUT)
            raise
        finally:
            self.interface.close()
            wandb.finish()


# ================================================================================================
# Rollout worker


class EpisodeLog:
    """The worker's episode reports: every episode at DEBUG level; at ``level`` (INFO by
    default) the first one, then one summary line every ``interval`` seconds, so that a fast
    environment does not print a wall of lines (thousands an hour).

    Args:
        kind: ``"train"`` or ``"expert"``.
        level: level of the first line and the summaries.
        interval: seconds between two summaries.
    """

    def __init__(self, kind: str, level: int = logging.INFO, interval: float = 30.0) -> None:
        self.kind = kind
        self.level = level
        self.interval = interval
        self._last = -math.inf
        self._returns: list[float] = []
        self._first = 0
        self._sent = 0
        self._test: tuple[float, int] | None = None

    def test(self, ret: float, steps: int) -> None:
        """A test episode's return and length (reported with the next summary)."""
        logger.debug("test episode: return %.1f in %d steps", ret, steps)
        self._test = (ret, steps)

    def train(self, episode: int, ret: float, steps: int, sent: int, version: int) -> None:
        """A finished episode: its index, return, length, samples sent, weights version."""
        logger.debug("%s episode %d: return %.1f in %d steps; %d samples sent; weights version %d",
                     self.kind, episode, ret, steps, sent, version)
        if not self._returns:
            self._first = episode
        self._returns.append(float(ret))
        self._sent += sent
        now = time.monotonic()
        if now - self._last < self.interval:
            return
        self._last = now
        returns = self._returns
        span = f"episode {episode}" if len(returns) == 1 else f"episodes {self._first}-{episode}"
        test = "" if self._test is None else f"; test return {self._test[0]:.1f}"
        logger.log(self.level, "%s %s: return last %.1f, mean %.1f, best %.1f%s; %d samples sent; weights version %d",
                   self.kind, span, returns[-1], sum(returns) / len(returns), max(returns), test, self._sent, version)
        self._returns, self._sent, self._test = [], 0, None


class Pace:
    """The worker's side of the trainer's sample budget (Reverb's rate limiter, simplified).

    With ``MAX_ENVIRONMENT_STEPS_PER_TRAINING_STEP`` set, the trainer sends with its weights how
    many samples it accepts to have received by now (``pace_budget``) and how many it has
    (``pace_received``). The worker counts the samples it collects after those weights and
    pauses once the budget is used up, until new weights raise it. With several workers each may
    use the whole budget of one broadcast, so they overshoot by at most one budget each; the
    trainer's own ratio (``MAX_TRAINING_STEPS_PER_ENVIRONMENT_STEP``) bounds the rest.
    """

    def __init__(self) -> None:
        self.limit = 0.0
        self.allowance = 0
        self.collected = 0

    @property
    def active(self) -> bool:
        """Whether the trainer asked for pacing."""
        return self.limit > 0

    def update(self, header: dict[str, Any]) -> None:
        """Take the pacing fields of a weights header (a header without them turns pacing off)."""
        fields = [header.get(k) for k in ("pace_limit", "pace_budget", "pace_received")]
        if not all(finite_stat(v) is not None and v >= 0 for v in fields):
            self.limit = 0.0
            return
        limit, budget, received = fields
        self.limit = float(limit)
        self.allowance = int(budget) - int(received)
        self.collected = 0

    def count(self, n: int) -> None:
        """``n`` more samples collected."""
        self.collected += n

    def exhausted(self) -> bool:
        """Whether the samples collected since the last weights used up the budget."""
        return self.active and self.collected >= self.allowance


def _is_real_time(env: Any) -> bool:
    """Whether ``env`` runs on the wall clock (an rtgym-style environment with ``benchmarks()``)."""
    return callable(getattr(getattr(env, "unwrapped", env), "benchmarks", None))


class RolloutWorker:
    """Runs the current policy in an environment; sends the samples to the server and loads the
    weights the trainer broadcasts. In standalone mode (``standalone=True``) it connects to
    nothing, for deployment and tests.

    Args:
        env_cls: callable building the Gymnasium environment (e.g. ``partial(GenericGymEnv, id=...)``).
        actor_module_cls: callable ``(observation_space=, action_space=)`` building the
            ``ActorModule``.
        sample_compressor: ``fn(prev_act, obs, rew, terminated, truncated, info)`` returning the
            same 6 values, smaller (the memory decompresses); ``None`` sends samples as they are.
        device: device of the policy (``"cpu"``, ``"cuda"``).
        max_samples_per_episode: episodes are cut (``truncated=True``) after this many steps.
        model_path: where the worker keeps its copy of the latest weights (``MODEL_PATH_WORKER``);
            loaded at start when it exists.
        obs_preprocessor: ``fn(obs) -> obs`` applied to every observation from the environment.
        crc_debug: store the full transition ``(prev_obs, act, new_obs, rew, terminated,
            truncated)`` in ``info["crc_sample"]`` before compression, for the memory to check its
            rebuilt transitions against (debugging custom pipelines only).
        model_path_history: prefix of the files of the saved history of weights
            (``MODEL_PATH_SAVE_HISTORY``).
        model_history: save every ``model_history``-th received model (``0`` or negative: never;
            ``MODEL_HISTORY``).
        standalone: do not connect to a server.
        server_ip: the server's address (``SERVER_IP_FOR_WORKER``).
        server_port: the server's port (``PORT``).
        password: the shared password (``PASSWORD``).
        local_port: accepted for compatibility with tmrl 0.7, unused.
        max_buf_len: accepted for compatibility with tmrl 0.7, unused.
        header_size: tlspyo header size (``HEADER_SIZE``).
        security: ``"TLS"`` or ``None`` for plain TCP (``SECURITY``).
        keys_dir: folder holding the TLS certificate (``CREDENTIALS_DIRECTORY``).
        hostname: the name the server's certificate is checked against (``HOSTNAME``).

    Raises:
        UserError: bad connection settings (see :mod:`tmrl.transport`).
    """

    def __init__(
        self,
        env_cls: Callable[[], Any],
        actor_module_cls: Callable[..., Any],
        sample_compressor: Callable[..., tuple] | None = None,
        device: str = "cpu",
        max_samples_per_episode: float = math.inf,
        model_path: str | os.PathLike[str] | None = None,
        obs_preprocessor: Callable[[Any], Any] | None = None,
        crc_debug: bool = False,
        model_path_history: str | os.PathLike[str] | None = None,
        model_history: int | None = None,
        standalone: bool = False,
        server_ip: str | None = None,
        server_port: int | None = None,
        password: str | None = None,
        local_port: int | None = None,
        header_size: int | None = None,
        max_buf_len: int | None = None,
        security: str | None = FROM_CONFIG,
        keys_dir: str | os.PathLike[str] | None = None,
        hostname: str | None = None,
        *,
        settings: NetSettings | None = None,
    ):
        show_progress_on_console()
        cfg = _settings(settings)
        self.obs_preprocessor = obs_preprocessor
        self.sample_compressor = sample_compressor
        self.env = env_cls()
        obs_space = self.env.observation_space
        act_space = self.env.action_space
        self.spaces = describe_spaces(obs_space, act_space)
        self.model_path = Path(_given(model_path, cfg.model_path_worker))
        self.model_path_history = str(_given(model_path_history, cfg.model_path_save_history))
        self.model_history = int(_given(model_history, cfg.model_history))
        self.device = device
        self.actor = actor_module_cls(observation_space=obs_space, action_space=act_space).to_device(device)
        if self.model_path.is_file():
            self._load_model_file()
        self.standalone = standalone
        self.max_samples_per_episode = max_samples_per_episode
        self.crc_debug = crc_debug
        self.source_id = secrets.randbelow(2**31 - 1) + 1
        self.buffer = Buffer(cfg.buffers_maxlen)
        self.buffer.source_id = self.source_id
        self._seq = 0
        self._cur_hist_cpt = 0
        self.weights_version = 0
        self.run_id: str | None = None
        """The run identity of the weights this worker acts with (stamped on its samples)."""
        self.pace = Pace()
        self._paused_mid_episode = not _is_real_time(self.env)
        self.rejected_weights = 0
        self._weights_log = RateLimitedLog(logger, logging.ERROR, 10.0)
        self._keys_dir = _given(keys_dir, cfg.credentials_directory)
        self._unsigned_warned = False
        self.debug_ts_cpt = 0
        self.debug_ts_res_cpt = 0
        self.server_ip = _given(server_ip, cfg.server_ip_for_worker)
        self._link: Any = None
        self._closed = False
        if not standalone:
            from tmrl.transport import BACKENDS

            self._link = _make_link(
                BACKENDS[cfg.transport].worker,
                self.server_ip,
                server_port,
                password,
                local_port,
                header_size,
                security,
                keys_dir,
                hostname,
                cfg,
                **cfg.transport_options("worker"),
            )
            logger.info("worker %d connecting to the server at %s", self.source_id, self.server_ip)

    # --- connection ------------------------------------------------------------------------------

    @property
    def connected(self) -> bool:
        """Whether the worker is connected to the server (``False`` in standalone mode)."""
        return self._link is not None and bool(self._link.connected)

    def wait_connected(self, timeout: float | None = None) -> bool:
        """Wait until connected to the server; ``False`` on timeout or in standalone mode."""
        return self._link is not None and bool(self._link.wait_connected(timeout))

    def close(self, timeout: float = 15.0) -> None:
        """Send what was handed to the network, then disconnect (idempotent). The link's process
        flushes for at most ``timeout - 1`` seconds and is killed after ``timeout``."""
        self._closed = True
        if self._link is not None:
            self._link.close(timeout)

    def __enter__(self) -> RolloutWorker:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # --- stepping --------------------------------------------------------------------------------

    @property
    def get_local_buffer_sample(self) -> Callable[..., tuple] | None:
        """tmrl 0.7's name of :attr:`sample_compressor` (reads and writes it)."""
        return self.sample_compressor

    @get_local_buffer_sample.setter
    def get_local_buffer_sample(self, fn: Callable[..., tuple] | None) -> None:
        self.sample_compressor = fn

    def act(self, obs: Any, test: bool = False) -> Any:
        """The actor's action for ``obs`` (``test=True``: deterministic)."""
        return self.actor.act_(obs, test=test)

    def _record(
        self, act: Any, new_obs: Any, rew: float, terminated: bool, truncated: bool, info: dict
    ) -> None:
        if self.sample_compressor is not None:
            sample = self.sample_compressor(act, new_obs, rew, terminated, truncated, info)
        else:
            sample = (act, new_obs, rew, terminated, truncated, info)
        self.buffer.append_sample(sample)

    def reset(self, collect_samples: bool) -> tuple[Any, dict]:
        """Start an episode; when ``collect_samples``, record its first sample, whose action is
        the environment's ``default_action`` (real-time environments) or ``None``.

        Returns:
            ``(obs, info)`` after the ``obs_preprocessor``.
        """
        act = getattr(self.env.unwrapped, "default_action", None)
        new_obs, info = self.env.reset()
        if self.obs_preprocessor is not None:
            new_obs = self.obs_preprocessor(new_obs)
        if collect_samples:
            if self.crc_debug:
                self.debug_ts_cpt += 1
                self.debug_ts_res_cpt = 0
                info["crc_sample"] = (None, act, new_obs, 0.0, False, False)
                info["crc_sample_ts"] = (self.debug_ts_cpt, self.debug_ts_res_cpt)
            self._record(act, new_obs, 0.0, False, False, info)
            self.pace.count(1)
        return new_obs, info

    def step(self, obs: Any, test: bool, collect_samples: bool, last_step: bool = False) -> tuple:
        """One transition: act on ``obs``, step the environment, record the sample.

        Args:
            obs: the previous observation.
            test: passed to the actor (deterministic action).
            collect_samples: record the sample for the trainer.
            last_step: the episode is cut after this step: ``truncated`` is set unless ``terminated``.

        Returns:
            ``(new_obs, rew, terminated, truncated, info)``.
        """
        act = self.act(obs, test=test)
        new_obs, rew, terminated, truncated, info = self.env.step(act)
        if self.obs_preprocessor is not None:
            new_obs = self.obs_preprocessor(new_obs)
        if last_step and not terminated:
            truncated = True
        if collect_samples:
            if self.crc_debug:
                self.debug_ts_cpt += 1
                self.debug_ts_res_cpt += 1
                info["crc_sample"] = (obs, act, new_obs, rew, terminated, truncated)
                info["crc_sample_ts"] = (self.debug_ts_cpt, self.debug_ts_res_cpt)
            self._record(act, new_obs, rew, terminated, truncated, info)
            if self.pace.active:
                self._keep_pace(end_of_episode=terminated or truncated)
        return new_obs, rew, terminated, truncated, info

    def _wait_first_weights(self) -> None:
        """After its first episode, a training worker waits for the trainer's first weights: they
        say which run the samples are for and how fast the trainer wants them (its pace); a
        fast environment would otherwise fill the memory with thousands of samples of the
        initial policy before the trainer has even started."""
        if self._link is None:
            return
        logger.info("waiting for the trainer's first weights")
        while self.weights_version == 0 and not self._closed:
            self.update_actor_weights(verbose=False, blocking=True)

    def _keep_pace(self, end_of_episode: bool) -> None:
        """Pause while this worker is ahead of the trainer's budget of samples (see :class:`Pace`):
        send what it has, then wait for weights that raise the budget. A real-time environment is
        only paused between episodes (its clock must not stop mid-episode)."""
        self.pace.count(1)
        if not self.pace.exhausted() or not (self._paused_mid_episode or end_of_episode):
            return
        while self.pace.exhausted() and self._link is not None and not self._closed:
            if len(self.buffer):
                self.send_and_clear_buffer()
            self.update_actor_weights(verbose=False, blocking=True)

    @staticmethod
    def _steps(max_samples: float) -> Iterable[int]:
        return itertools.count() if max_samples == math.inf else range(int(max_samples))

    def collect_train_episode(self, max_samples: float | None = None) -> None:
        """Run one train episode of at most ``max_samples`` steps into the buffer (cut episodes
        end with ``truncated=True``) and record its return and length."""
        max_samples = self.max_samples_per_episode if max_samples is None else max_samples
        ret, steps = 0.0, 0
        obs, _ = self.reset(collect_samples=True)
        for i in self._steps(max_samples):
            obs, rew, terminated, truncated, _ = self.step(
                obs, test=False, collect_samples=True, last_step=i == max_samples - 1
            )
            ret += rew
            steps += 1
            if terminated or truncated or self._closed:
                break
        self.buffer.stat_train_return = ret
        self.buffer.stat_train_steps = steps

    def run_episode(self, max_samples: float | None = None, train: bool = False) -> float:
        """Run one episode without recording samples (a test episode unless ``train``); record
        its return and length as test statistics. Returns the episode's return.

        Args:
            max_samples: most steps of the episode (default: ``max_samples_per_episode``).
            train: act with the training (stochastic) policy instead of the test one.
        """
        max_samples = self.max_samples_per_episode if max_samples is None else max_samples
        ret, steps = 0.0, 0
        obs, _ = self.reset(collect_samples=False)
        for _ in self._steps(max_samples):
            obs, rew, terminated, truncated, _ = self.step(obs, test=not train, collect_samples=False)
            ret += rew
            steps += 1
            if terminated or truncated:
                break
        self.buffer.stat_test_return = ret
        self.buffer.stat_test_steps = steps
        return ret

    def run_episodes(
        self, max_samples_per_episode: float | None = None, nb_episodes: float = math.inf, train: bool = False
    ) -> None:
        """Run ``nb_episodes`` episodes with :meth:`run_episode` (deployment).

        Args:
            max_samples_per_episode: most steps per episode (default: the worker's).
            nb_episodes: how many episodes (default: until stopped).
            train: act with the training (stochastic) policy instead of the test one.
        """
        for _ in self._steps(nb_episodes):
            self.run_episode(max_samples_per_episode, train=train)

    def run(
        self,
        test_episode_interval: int = 0,
        nb_episodes: float = math.inf,
        verbose: bool = True,
        expert: bool = False,
    ) -> None:
        """Collect train episodes, sending each to the server and loading new weights between
        episodes.

        Args:
            test_episode_interval: run a test episode before every ``test_episode_interval``-th
                train episode (0: never; never in CRC debug mode).
            nb_episodes: number of train episodes.
            verbose: log one line per episode at INFO level (DEBUG otherwise).
            expert: send samples but never load weights nor run test episodes.
        """
        summary = EpisodeLog("expert" if expert else "train", level=logging.INFO if verbose else logging.DEBUG)
        for episode in self._steps(nb_episodes):
            if self._closed:  # close() from another thread: stop between episodes
                break
            if (
                not expert
                and test_episode_interval
                and episode % test_episode_interval == 0
                and not self.crc_debug
            ):
                ret = self.run_episode(self.max_samples_per_episode, train=False)
                summary.test(ret, self.buffer.stat_test_steps)
            self.collect_train_episode(self.max_samples_per_episode)
            n = len(self.buffer) if self._link is not None else 0  # standalone: nothing is sent
            self.send_and_clear_buffer()
            if expert:
                self.ignore_actor_weights()
            elif episode == 0 and self.weights_version == 0:
                self._wait_first_weights()
            else:
                self.update_actor_weights(verbose=False)
            summary.train(episode, self.buffer.stat_train_return, self.buffer.stat_train_steps, n, self.weights_version)

    def run_synchronous(
        self,
        test_episode_interval: int = 0,
        nb_steps: float = math.inf,
        initial_steps: int = 1,
        max_steps_per_update: float = math.inf,
        end_episodes: bool = True,
        verbose: bool = False,
    ) -> None:
        """Collect ``nb_steps`` steps while keeping pace with the trainer: at most
        ``max_steps_per_update`` environment steps per model received (for environments that can
        be stepped as fast as wanted).

        Args:
            test_episode_interval: a test episode every ``test_episode_interval`` train episodes
                (0: never; needs ``end_episodes``).
            nb_steps: steps to collect after the initial ones.
            initial_steps: steps collected before waiting for the first model.
            max_steps_per_update: most environment steps per received model (may be fractional).
            end_episodes: only pause (send and wait for a model) between episodes.
            verbose: log at INFO level.
        """
        log = logger.info if verbose else logger.debug
        iteration, obs, done = self._collect_initial_samples(initial_steps, end_episodes, log)
        models = self._wait_for_models(iteration, 1, max_steps_per_update, send=True, verbose=verbose)
        iteration, episode, steps, ret = 0, 0, 0, 0.0
        while iteration < nb_steps:
            if done:
                if test_episode_interval > 0 and episode % test_episode_interval == 0 and end_episodes:
                    log("running a test episode")
                    self.run_episode(self.max_samples_per_episode, train=False)
                obs, _ = self.reset(collect_samples=True)
                done, steps, ret = False, 0, 0.0
                iteration += 1
                episode += 1
            while not done:  # _wait_for_models holds the ratio: an episode always runs to its end
                obs, rew, terminated, truncated, _ = self._training_step(obs, steps)
                iteration += 1
                steps += 1
                ret += rew
                done = terminated or truncated
                if not end_episodes:
                    models = self._wait_for_models(iteration, models, max_steps_per_update, send=not done, verbose=verbose)
            if end_episodes:
                models = self._wait_for_models(iteration, models, max_steps_per_update, send=not done, verbose=verbose)
            if done:
                self.buffer.stat_train_return = ret
                self.buffer.stat_train_steps = steps
            self.send_and_clear_buffer()

    def _training_step(self, obs: Any, steps: int) -> tuple:
        """One collecting step of a training episode that has run ``steps`` steps so far."""
        return self.step(obs, test=False, collect_samples=True, last_step=steps == self.max_samples_per_episode - 1)

    def _collect_initial_samples(self, initial_steps: int, end_episodes: bool, log: Callable[..., None]) -> tuple:
        """:meth:`run_synchronous`'s first ``initial_steps`` steps (whole episodes unless
        ``end_episodes`` is False), sent as they end. Returns ``(steps, obs, done)``."""
        iteration, done = 0, False
        obs: Any = None
        while iteration < initial_steps:
            obs, _ = self.reset(collect_samples=True)
            done, steps, ret = False, 0, 0.0
            iteration += 1
            while not done and (end_episodes or iteration < initial_steps):
                obs, rew, terminated, truncated, _ = self._training_step(obs, steps)
                iteration += 1
                steps += 1
                ret += rew
                done = terminated or truncated
            self.buffer.stat_train_return = ret
            self.buffer.stat_train_steps = steps
            log("sending %d initial samples", len(self.buffer))
            self.send_and_clear_buffer()
        return iteration, obs, done

    def _wait_for_models(self, steps_done: int, models: int, limit: float, send: bool, verbose: bool) -> int:
        """While more than ``limit`` environment steps were taken per model received, send the
        buffer (when ``send``) and wait for the next model. Returns the models received so far."""
        while (steps_done + 1) / models > limit:
            if send:
                self.send_and_clear_buffer()
            before = self.weights_version
            if self.update_actor_weights(verbose=verbose, blocking=True):
                # only the newest broadcast is kept: the versions skipped in between were models
                # too (counting receptions alone waited forever for broadcasts already made)
                models += max(1, self.weights_version - before)
        return models

    def run_env_benchmark(self, nb_steps: int, test: bool = False, verbose: bool = True) -> Any:
        """Step the environment ``nb_steps`` times (one episode at most) and return its
        ``benchmarks()`` (rtgym-style environments created with ``"benchmark": True``).

        Args:
            nb_steps: how many steps (a positive integer).
            test: act with the test (deterministic) policy.
            verbose: accepted for compatibility with tmrl 0.7 (the caller prints the result).

        Raises:
            UserError: ``nb_steps`` is not a positive finite number, or the environment has no
                ``benchmarks()`` method.
        """
        if not isinstance(nb_steps, int) or nb_steps <= 0:
            raise UserError(f"run_env_benchmark needs a positive integer number of steps, got {nb_steps!r}")
        obs, _ = self.reset(collect_samples=False)
        for _ in range(nb_steps):
            obs, _, terminated, truncated, _ = self.step(obs, test=test, collect_samples=False)
            if terminated or truncated:
                break
        bench = getattr(self.env.unwrapped, "benchmarks", None)
        if bench is None:
            raise UserError(
                "this environment has no benchmarks(): benchmarks need a real-time "
                'environment created with "benchmark": true in its config'
            )
        res = bench()
        if verbose:
            logger.info("benchmark results: %s", res)
        return res

    # --- network ---------------------------------------------------------------------------------

    def send_and_clear_buffer(self) -> None:
        """Hand the buffered samples to the network and clear the buffer.

        While the server is unreachable the transport keeps them (bounded) and sends them on
        reconnection. In standalone mode, or once the worker is closed (from another thread while
        it runs), the samples are simply dropped.
        """
        if self._link is None or self._closed:
            self.buffer.clear()
            return
        try:
            payload = pack_buffer(self.buffer, self.source_id, self._seq, run=self.run_id)
            try:
                self._link.send_samples(payload)
            except RuntimeError:
                if not self._closed:
                    raise
                self.buffer.clear()  # closed while sending: the run is over for this worker
                return
        except TypeError as err:
            raise UserError(
                f"a sample holds something that cannot be sent ({err}): keep observations, actions "
                "and info values to numbers, strings, bytes, NumPy arrays and containers of those "
                "(drop the rest in a sample_compressor)"
            ) from err
        self._seq += 1
        self.buffer.clear()

    def _load_model_file(self) -> None:
        """Load ``model_path`` at start; a file that does not load is reported and left alone (the
        trainer's next weights replace it): a worker never refuses to start over a file it can
        replace."""
        logger.debug("loading weights from %s", self.model_path)
        try:
            problem = _weights_problem(self.actor, self.model_path.read_bytes())
            if problem is not None:
                raise UserError(problem)
            self.actor = self.actor.load(str(self.model_path), device=self.device)
        except Exception as err:  # noqa: BLE001 (any failure of a replaceable file: one line, go on)
            logger.error(
                "ignored the weights file %s (%s); starting with a fresh actor until the trainer's weights arrive",
                self.model_path,
                _one_line(err),
            )

    def _pinned_key(self) -> bytes | None:
        from tmrl.transport.credentials import load_trainer_public_key

        key = load_trainer_public_key(self._keys_dir)
        if key is None and not self._unsigned_warned:
            self._unsigned_warned = True
            logger.warning(
                "weights from the server are not authenticated: copy trainer_public_key.pem from the "
                "trainer's credentials folder into %s so that only the trainer's weights are loaded",
                self._keys_dir or "this worker's credentials folder",
            )
        return key

    def _load_weights(self, envelope: bytes, verbose: bool) -> bool:
        """Check and load received weights; on any problem keep the current actor, log one line
        (rate-limited) and return ``False``. Nothing is written before the checks pass, and
        ``model_path`` is replaced only once the new weights have loaded."""
        from tmrl.util import atomic_write_bytes

        # one name per worker: several workers of one machine may share a data folder and model_path
        candidate = self.model_path.with_name(f".{self.model_path.name}.{os.getpid()}-{id(self):x}.incoming")
        try:
            msg, data = unpack_weights(envelope, self._pinned_key())
            check_spaces(self.spaces, msg.get("spaces"))
            problem = _weights_problem(self.actor, data)
            if problem is not None:
                raise WeightsRejected(problem)
            atomic_write_bytes(candidate, data)
            actor = self.actor.load(str(candidate), device=self.device)
        except Exception as err:  # noqa: BLE001 (a peer's bytes, or user load code: never fatal)
            self.rejected_weights += 1
            self._weights_log(
                "ignored weights from the server (%s); keeping the current actor (%d ignored so far)",
                _one_line(err),
                self.rejected_weights,
            )
            with contextlib.suppress(OSError):
                candidate.unlink()
            return False
        os.replace(candidate, self.model_path)
        self.actor = actor
        if self.model_history > 0:
            self._cur_hist_cpt += 1
            if self._cur_hist_cpt >= self.model_history:
                self._cur_hist_cpt = 0
                stamp = datetime.datetime.now().strftime("%d_%m_%Y_%H_%M_%S")
                atomic_write_bytes(f"{self.model_path_history}{stamp}_{self.weights_version + 1}.tmod", data)
                if verbose:
                    logger.info("weights saved in the history")
        version = msg.get("version")
        self.weights_version = version if type(version) is int else self.weights_version + 1
        run = msg.get("run")
        self.run_id = run if isinstance(run, str) and 0 < len(run) <= 64 else None
        self.pace.update(msg)
        if verbose:
            logger.info("weights updated (version %d)", self.weights_version)
        return True

    def update_actor_weights(self, verbose: bool = True, blocking: bool = False) -> int:
        """Load the newest weights broadcast by the trainer, if any arrived.

        Args:
            verbose: log at INFO level.
            blocking: wait until weights arrive.

        Returns:
            The number of models loaded (0 or 1: only the newest broadcast matters). Weights that
            fail a check (signature, spaces, non-finite values, a file the actor cannot load) are
            not loaded: the worker keeps its actor and logs why (rate-limited); 0 is returned.
        """
        if self._link is None:
            return 0
        while True:
            t0 = time.monotonic()
            envelope = self._link.latest_weights(block=blocking, timeout=1.0 if blocking else None)
            if envelope is not None or not blocking or self._closed:
                break
            if time.monotonic() - t0 < 0.5:  # the link's process is gone: do not spin
                time.sleep(0.5)
        if envelope is None:
            return 0
        return 1 if self._load_weights(envelope, verbose) else 0

    def ignore_actor_weights(self) -> int:
        """Discard weights received from the trainer (expert workers). Returns how many were discarded."""
        if self._link is None:
            return 0
        return 0 if self._link.latest_weights(block=False) is None else 1
