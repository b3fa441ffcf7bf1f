"""Weights on the wire and into a worker's actor.

The trainer broadcasts an envelope (:func:`pack_weights`): a magic, a small data-only header (the
actor's spaces, the broadcast counter, the run identity, pacing fields) signed with the trainer
key, then the weights file's bytes as they are. A worker opens it with :func:`unpack_weights` and
installs it through its :class:`WeightsInstaller`, which checks every tensor before the actor
sees it and keeps the previous actor on any problem.
"""

from __future__ import annotations

import datetime
import hashlib
import logging
import os
import struct
import threading
from pathlib import Path
from typing import Any

import numpy as np

from tmrl import platform
from tmrl.distributed._common import LOGGER_NAME, _one_line
from tmrl.errors import UserError
from tmrl.spaces import check_spaces
from tmrl.util import RateLimitedLog, atomic_write_bytes
from tmrl.wire_buffers import PAYLOAD_VERSION, PayloadError

__all__ = ["WeightsInstaller", "WeightsRejected", "move_over", "pack_weights", "replace_file", "unpack_weights"]

logger = logging.getLogger(LOGGER_NAME)

_WEIGHTS_MAGIC = b"TMRLWGT2"
_U32 = struct.Struct("<I")
_RESERVED_HEADER_KEYS = frozenset(("v", "kind", "version", "spaces", "size", "run", "sha256"))


def replace_file(path: str | os.PathLike[str], data: bytes | memoryview) -> None:
    """Write ``data`` to ``path`` through a temporary file moved there (:func:`move_over`): a
    reader never sees half of a file.

    Nothing is synced to disk, unlike :func:`tmrl.util.atomic_write_bytes`: the trainer's and a
    worker's copy of the weights are rewritten at every broadcast (a sync of the file and of its
    folder cost the trainer about 3 ms each time, more than an update on the tutorial's settings),
    a crash loses nothing that the next broadcast does not bring back, and a file left empty by
    one is reported and ignored when the worker starts (:meth:`WeightsInstaller.load_file`)."""
    path = Path(path)
    tmp = path.with_name(f".{path.name}.{os.getpid()}-{threading.get_ident()}.tmp")
    try:
        with open(tmp, "wb") as f:
            f.write(data)
        move_over(tmp, path)
    except BaseException:
        platform.remove(tmp)
        raise


def remove_stale_temporaries(path: str | os.PathLike[str]) -> int:
    """Remove the temporary copies of ``path`` that a killed process left in its folder: the
    ``.<name>.<pid>-<id>.tmp`` of :func:`replace_file` and the ``.<name>.<pid>-<id>.incoming`` of
    :meth:`WeightsInstaller.install` whose process ``<pid>`` no longer runs. Only processes of
    one machine share a ``model_path`` (workers of one machine may), so the pid tells. Says how
    many went in one log line; returns that number."""
    path = Path(path)
    prefix = f".{path.name}."
    removed = 0
    try:
        entries = list(os.scandir(path.parent))
    except OSError:
        return 0
    for entry in entries:
        name = entry.name
        if not name.startswith(prefix) or not name.endswith((".tmp", ".incoming")):
            continue
        pid_text = name[len(prefix):].split("-", 1)[0]
        if not pid_text.isdigit() or _pid_alive(int(pid_text)):
            continue
        if platform.remove(entry.path):
            removed += 1
    if removed:
        logger.info("removed %d temporary weights files left by stopped processes beside %s", removed, path)
    return removed


def _pid_alive(pid: int) -> bool:
    """Whether process ``pid`` runs on this machine (True when that cannot be told: on Windows,
    ``os.kill(pid, 0)`` would end the process instead of probing it)."""
    if pid <= 0 or os.name != "posix":
        return True
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except OSError:  # PermissionError: someone else's process, alive
        return True
    return True


def move_over(src: str | os.PathLike[str], dst: str | os.PathLike[str]) -> None:
    """Move ``src`` over ``dst`` atomically (``os.replace``): a reader finds the old file or the new
    one, on every system. Retried while another process holds ``dst`` (Windows refuses to replace
    an open file); :class:`tmrl.platform.FileBusy` when it stays held.

    (A removal then a rename to the free name cost less on ext4, whose ``auto_da_alloc`` writes a
    file renamed over another out at once, about a millisecond per broadcast on a busy disk; but
    on Windows the rename fails whenever the removal did, and a reader could find no file.)"""
    platform.replace(src, dst)


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


class WeightsInstaller:
    """Where a worker installs weights: every envelope the trainer broadcasts goes through
    :meth:`install`, and the file kept from the last run through :meth:`load_file`.

    Nothing reaches the actor before every check has passed: the signature when the trainer's key
    is pinned, the spaces, the tensors (finite, the names and shapes of the actor's), and the
    actor's own ``load`` into a new actor. ``model_path`` is replaced only once the new actor has
    loaded; every ``model_history``-th accepted file is also kept in the history.

    Args:
        spaces: :func:`~tmrl.spaces.describe_spaces` of the worker's environment.
        device: where the actor lives (``actor.load(..., device=)``).
        model_path: the worker's copy of the latest weights.
        model_path_history: prefix of the history files.
        model_history: keep every ``model_history``-th accepted file (``0`` or negative: none).
        keys_dir: the credentials folder where the trainer's public key may be pinned.
    """

    def __init__(
        self,
        spaces: dict[str, Any],
        device: str,
        model_path: str | os.PathLike[str],
        model_path_history: str | os.PathLike[str],
        model_history: int,
        keys_dir: str | os.PathLike[str] | None,
    ) -> None:
        self.spaces = spaces
        self.device = device
        self.model_path = Path(model_path)
        self.model_path_history = str(model_path_history)
        self.model_history = int(model_history)
        self.keys_dir = keys_dir
        self.rejected = 0
        """Envelopes refused so far."""
        self._history_count = 0
        self._log = RateLimitedLog(logger, logging.ERROR, 10.0)
        self._unsigned_warned = False
        self._key: bytes | None = None
        self._key_stamp: tuple[int, int, int] | None = None
        remove_stale_temporaries(self.model_path)

    def load_file(self, actor: Any) -> Any:
        """``actor`` with the weights of ``model_path`` (at start), or ``actor`` itself when the
        file does not exist or does not load: that is reported in one line and the worker goes on
        (the trainer's next weights replace the file)."""
        if not self.model_path.is_file():
            return actor
        logger.debug("loading weights from %s", self.model_path)
        try:
            problem = _weights_problem(actor, platform.read_bytes(self.model_path))
            if problem is not None:
                raise UserError(problem)
            # retried while another process holds the file (Windows: the trainer replacing it)
            return platform.when_free(lambda: actor.load(str(self.model_path), device=self.device),
                                      what=str(self.model_path))
        except Exception as err:  # noqa: BLE001 (any failure of a replaceable file: one line, go on)
            logger.error(
                "ignored the weights file %s (%s); starting with a fresh actor until the trainer's weights arrive",
                self.model_path,
                _one_line(err),
            )
            return actor

    def pinned_key(self) -> bytes | None:
        """The trainer's public key pinned in the credentials folder (``None``: none, warned once).
        Read again only when the file changed (pinned, replaced or removed while the worker runs)."""
        from tmrl.transport.credentials import TRAINER_PUBLIC_KEY_FILE, load_trainer_public_key

        try:
            st = os.stat(Path(self.keys_dir) / TRAINER_PUBLIC_KEY_FILE) if self.keys_dir is not None else None
            stamp = None if st is None else (st.st_ino, st.st_size, st.st_mtime_ns)
        except OSError:
            stamp = None
        if stamp is not None and stamp == self._key_stamp:
            return self._key
        key = load_trainer_public_key(self.keys_dir)
        self._key_stamp, self._key = (stamp, key) if key is not None else (None, None)
        if key is None and not self._unsigned_warned:
            self._unsigned_warned = True
            logger.warning(
                "weights from the server are not authenticated: copy trainer_public_key.pem from the "
                "trainer's credentials folder into %s so that only the trainer's weights are loaded",
                self.keys_dir or "this worker's credentials folder",
            )
        return key

    def install(self, actor: Any, envelope: bytes, version: int, verbose: bool) -> tuple[Any, dict[str, Any]] | None:
        """Check ``envelope`` and load its weights into a new actor.

        Args:
            actor: the worker's current actor (loads the new weights; kept on any problem).
            envelope: the bytes received (:func:`pack_weights`).
            version: the worker's current weights version (names the history file).
            verbose: log the history file at INFO level.

        Returns:
            ``(new actor, envelope header)``, or ``None``: refused (counted in :attr:`rejected`,
            one rate-limited line says why, nothing written).
        """
        # one name per worker: several workers of one machine may share a data folder and model_path
        candidate = self.model_path.with_name(f".{self.model_path.name}.{os.getpid()}-{id(self):x}.incoming")
        try:
            header, data = unpack_weights(envelope, self.pinned_key())
            check_spaces(self.spaces, header.get("spaces"))
            problem = _weights_problem(actor, data)
            if problem is not None:
                raise WeightsRejected(problem)
            replace_file(candidate, data)
            new_actor = actor.load(str(candidate), device=self.device)
        except Exception as err:  # noqa: BLE001 (a peer's bytes, or user load code: never fatal)
            self.rejected += 1
            self._log(
                "ignored weights from the server (%s); keeping the current actor (%d ignored so far)",
                _one_line(err),
                self.rejected,
            )
            platform.remove(candidate)
            return None
        try:
            move_over(candidate, self.model_path)
        except OSError as err:  # the actor has them: only the copy on disk waits for the next weights
            self._log("kept the new weights without their copy in %s (%s)", self.model_path, _one_line(err))
            platform.remove(candidate)
        if self.model_history > 0:
            self._history_count += 1
            if self._history_count >= self.model_history:
                self._history_count = 0
                stamp = datetime.datetime.now().strftime("%d_%m_%Y_%H_%M_%S")
                atomic_write_bytes(f"{self.model_path_history}{stamp}_{version + 1}.tmod", data)
                if verbose:
                    logger.info("weights saved in the history")
        return new_actor, header
