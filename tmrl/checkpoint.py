"""Checkpoints of the full training state, data-only and incremental.

A checkpoint is a folder::

    <path>/checkpoint.json          the header, written last: the commit point
    <path>/state-<gen>.pt           agent state (models, optimizers...) and torch RNG states,
                                    read back with torch.load(weights_only=True)
    <path>/memory-<gen>.safetensors samples of a built-in memory, in segments
    <path>/data-<gen>.wire          or the ``data`` of a user memory (tmrl.wire format)

Built-in (array-shaped) memories are saved in *segments*: each checkpoint writes only the samples
received since the previous one (one safetensors file holding, for each ring array, the rows of
those samples in arrival order) and the header lists the segments still needed. Segments whose
samples have all been overwritten are deleted; when more than half of the stored rows are dead,
the memory is written again in one segment. So a 1M-sample memory costs one full write, then
writes proportional to what is new.

Every file is written to a temporary name, flushed, synced and renamed; the header is replaced
last, and files it no longer names are removed afterwards. A crash leaves the previous
checkpoint intact. Nothing is pickled: the header is JSON, arrays are safetensors, the torch file
is loaded with ``weights_only=True``, user memories go through :mod:`tmrl.wire`.

Size and CRC32 of every file are recorded in the header; a corrupt, truncated or foreign
checkpoint raises :class:`CheckpointError` with one line.
"""

from __future__ import annotations

import io
import json
import logging
import os
import random
import re
import struct
import tempfile
import zlib
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import torch

from tmrl import platform
from tmrl.errors import UserError
from tmrl.util import atomic_write_bytes, atomic_write_text

__all__ = [
    "FORMAT",
    "checkpoint_complete",
    "VERSION",
    "CheckpointError",
    "dump_run_instance",
    "load_checkpoint",
    "load_memory",
    "load_run_instance",
    "make_load_run_instance_fn",
    "save_checkpoint",
    "update_run_instance",
]

logger = logging.getLogger(__name__)

FORMAT = "tmrl-checkpoint"
VERSION = 1
HEADER = "checkpoint.json"
_OWN_FILE = re.compile(r"^(state-\d+\.pt|memory-\d+\.safetensors|data-\d+\.wire)$")
_TMP_FILE = re.compile(r"^\.((state|memory|data)-\d+\..*|checkpoint\.json\.[^.]+)\.tmp$")
"""Temporaries of an interrupted write (a process killed while saving): the segments' and the
header's (``atomic_write_text`` names it ``.checkpoint.json.<random>.tmp``)."""

_ST_DTYPES = {
    np.dtype(np.float64): "F64",
    np.dtype(np.float32): "F32",
    np.dtype(np.float16): "F16",
    np.dtype(np.int64): "I64",
    np.dtype(np.int32): "I32",
    np.dtype(np.int16): "I16",
    np.dtype(np.int8): "I8",
    np.dtype(np.uint64): "U64",
    np.dtype(np.uint32): "U32",
    np.dtype(np.uint16): "U16",
    np.dtype(np.uint8): "U8",
    np.dtype(np.bool_): "BOOL",
}


class CheckpointError(UserError):
    """A checkpoint cannot be read or written; the message names the file and what to do."""


def _one_line(err: BaseException) -> str:
    text = str(err).strip().splitlines()
    return (text[0] if text else type(err).__name__)[:200]


# ==== files =======================================================================================


def _crc_of_file(path: Path) -> tuple[int, int]:
    crc, size = 0, 0
    with open(path, "rb") as f:
        while True:
            chunk = f.read(1 << 22)
            if not chunk:
                return crc, size
            crc = zlib.crc32(chunk, crc)
            size += len(chunk)


def _write_file(folder: Path, name: str, data: bytes) -> dict[str, Any]:
    atomic_write_bytes(folder / name, data)
    return {"file": name, "size": len(data), "crc32": zlib.crc32(data)}


def _write_segment(folder: Path, name: str, arrays: dict[str, list[np.ndarray]], meta: dict[str, str]) -> dict[str, Any]:
    """Stream a safetensors file (each array given as consecutive row blocks, so ring-buffer
    slices are written without concatenating them first), atomically. Returns the file record."""
    header: dict[str, Any] = {}
    offset = 0
    for key, parts in arrays.items():
        dtype = parts[0].dtype
        if dtype not in _ST_DTYPES:
            raise CheckpointError(f"cannot save memory array {key} of dtype {dtype}: store numbers or bools")
        rows = sum(len(p) for p in parts)
        nbytes = sum(p.nbytes for p in parts)
        header[key] = {"dtype": _ST_DTYPES[dtype], "shape": [rows, *parts[0].shape[1:]], "data_offsets": [offset, offset + nbytes]}
        offset += nbytes
    header["__metadata__"] = meta
    head = json.dumps(header, separators=(",", ":")).encode()
    head += b" " * (-len(head) % 8)  # safetensors aligns the data on 8 bytes
    fd, tmp = tempfile.mkstemp(prefix=f".{name}.", suffix=".tmp", dir=folder)
    crc = 0
    size = 0
    try:
        with os.fdopen(fd, "wb") as f:
            for chunk in (struct.pack("<Q", len(head)), head):
                f.write(chunk)
                crc = zlib.crc32(chunk, crc)
                size += len(chunk)
            for parts in arrays.values():
                for part in parts:
                    view = np.ascontiguousarray(part).reshape(-1).view(np.uint8).data
                    f.write(view)
                    crc = zlib.crc32(view, crc)
                    size += view.nbytes
            f.flush()
            os.fsync(f.fileno())
        platform.replace(tmp, folder / name)  # retried while a reader holds the old one (Windows)
    except BaseException:
        platform.remove(tmp)
        raise
    return {"file": name, "size": size, "crc32": crc}


def _check_file(folder: Path, record: dict[str, Any]) -> Path:
    path = folder / str(record["file"])
    if not path.is_file():
        raise CheckpointError(
            f"checkpoint {folder} is incomplete: {path.name} is missing; restore the folder from a "
            "backup or delete it to start over"
        )
    try:  # retried while another process (an antivirus, a backup tool) holds it: Windows
        crc, size = platform.when_free(_crc_of_file, path, what=str(path))
    except platform.FileBusy as err:
        raise CheckpointError(f"checkpoint file {path} cannot be read: {err}; close what holds it and start "
                              "again") from None
    if size != record["size"]:
        raise CheckpointError(
            f"checkpoint file {path} is truncated ({size} bytes, expected {record['size']}); restore "
            "the folder from a backup or delete it to start over"
        )
    if crc != record["crc32"]:
        raise CheckpointError(
            f"checkpoint file {path} is corrupt (checksum mismatch); restore the folder from a "
            "backup or delete it to start over"
        )
    return path


def _read_header(folder: Path) -> dict[str, Any]:
    if not folder.exists():
        raise CheckpointError(f"no checkpoint at {folder}: check the checkpoint path")
    if not folder.is_dir():
        raise CheckpointError(
            f"{folder} is a file, not a tmrl checkpoint folder (pickled checkpoints of tmrl 0.7 are "
            "never loaded, pickle can run code): move it away or choose another checkpoint path"
        )
    path = folder / HEADER
    if not path.is_file():
        raise CheckpointError(
            f"{folder} holds no {HEADER}: not a tmrl checkpoint (or its first save was interrupted); "
            "move it away or choose another checkpoint path"
        )
    try:
        header = json.loads(platform.read_bytes(path).decode("utf-8"))  # retried while held (Windows)
    except (UnicodeDecodeError, json.JSONDecodeError) as err:
        raise CheckpointError(
            f"{path} is corrupt ({_one_line(err)}); restore the folder from a backup or delete it"
        ) from None
    if not isinstance(header, dict) or header.get("format") != FORMAT:
        raise CheckpointError(
            f"{path} is not a tmrl checkpoint header: move the folder away or choose another checkpoint path"
        )
    if not isinstance(header.get("version"), int) or header["version"] > VERSION:
        raise CheckpointError(
            f"{path} was written by a newer tmrl (format version {header.get('version')}, this one "
            f"reads {VERSION}): upgrade tmrl"
        )
    for key in ("generation", "epoch", "total_updates", "total_samples", "state", "memory", "rng"):
        if key not in header:
            raise CheckpointError(f"{path} is corrupt (no {key!r}); restore the folder from a backup or delete it")
    problem = _header_problem(header)
    if problem is not None:
        raise CheckpointError(f"{path} is corrupt ({problem}); restore the folder from a backup or delete it")
    return header


def _is_count(value: Any, low: int = 0) -> bool:
    return type(value) is int and low <= value < 2**62


def _file_record_problem(record: Any, what: str) -> str | None:
    if not isinstance(record, dict):
        return f"{what} is not a file record"
    name = record.get("file")
    if not isinstance(name, str) or not _OWN_FILE.match(name):
        return f"{what} names no file of this checkpoint"
    if not _is_count(record.get("size")) or not _is_count(record.get("crc32")):
        return f"{what} has a bad size or checksum"
    return None


def _header_problem(header: dict[str, Any]) -> str | None:
    """The first value of ``header`` that cannot be right, or ``None`` (a hand-edited or
    damaged header is refused in one line instead of failing deep inside the restore)."""
    if not _is_count(header["generation"], 1):
        return "bad 'generation'"
    for key in ("epoch", "total_updates", "total_samples"):
        if not _is_count(header[key]):
            return f"bad {key!r}: {str(header[key])[:40]}"
    run_id = header.get("run_id")
    if run_id is not None and (not isinstance(run_id, str) or not 0 < len(run_id) <= 64):
        return "bad 'run_id'"
    problem = _file_record_problem(header["state"], "'state'")
    if problem is not None:
        return problem
    memory = header["memory"]
    if not isinstance(memory, dict) or memory.get("kind") not in ("ring", "data"):
        return "bad 'memory'"
    stats = memory.get("stats")
    if not isinstance(stats, list) or len(stats) != 4 or not all(type(v) in (int, float) for v in stats):
        return "bad memory statistics"
    if memory["kind"] == "data":
        return _file_record_problem(memory.get("file"), "the memory data")
    meta, segments = memory.get("meta"), memory.get("segments")
    if not isinstance(meta, dict) or not isinstance(segments, list):
        return "bad memory layout"
    for key in ("total", "capacity", "oldest"):
        if key in meta and not _is_count(meta[key]):
            return f"bad memory {key!r}"
    for seg in segments:
        problem = _file_record_problem(seg, "a memory segment")
        if problem is not None:
            return problem
        if not (_is_count(seg.get("start")) and _is_count(seg.get("stop")) and seg["start"] <= seg["stop"]):
            return "a memory segment has bad bounds"
    rng = header["rng"]
    if not isinstance(rng, dict) or not isinstance(rng.get("python"), list) or not isinstance(rng.get("numpy"), list):
        return "bad 'rng'"
    return None


def checkpoint_complete(path: str | os.PathLike[str]) -> bool:
    """Whether the folder ``path`` holds a checkpoint to resume from.

    Returns:
        ``True`` when it has a header; ``False`` when it is missing, empty or holds only the
        files of an interrupted *first* save (generation 1: nothing to lose).

    Raises:
        CheckpointError: the folder holds saved state of a later generation but no header (a
            deleted or lost ``checkpoint.json``): starting afresh would overwrite that state.
    """
    folder = Path(path)
    if not folder.is_dir():
        return False
    if (folder / HEADER).exists():
        return True
    later = sorted(e.name for e in folder.iterdir() if _OWN_FILE.match(e.name) and _generation(e.name) > 1)
    if later:
        raise CheckpointError(
            f"checkpoint {folder} holds saved state ({later[0]}...) but no {HEADER}: it is refused rather "
            "than overwritten; restore checkpoint.json from a backup, or move the folder away to start a new run"
        )
    return False


def _generation(name: str) -> int:
    digits = re.search(r"-(\d+)\.", name)
    return int(digits.group(1)) if digits else 0


# ==== agent and RNG ================================================================================


def _agent_state(agent: Any) -> Any:
    state_dict = getattr(agent, "state_dict", None)
    if not callable(state_dict):
        raise CheckpointError(
            f"the training agent ({type(agent).__qualname__}) has no state_dict(): subclass "
            "tmrl.training.TrainingAgent or implement state_dict()/load_state_dict()"
        )
    return state_dict()


def _python_rng() -> list[Any]:
    version, state, gauss = random.getstate()
    return [version, list(state), gauss]


def _numpy_rng() -> list[Any]:
    name, keys, pos, has_gauss, cached = np.random.get_state()
    return [name, [int(k) for k in keys], int(pos), int(has_gauss), float(cached)]


def _restore_rng(header_rng: dict[str, Any], state: dict[str, Any]) -> None:
    version, keys, gauss = header_rng["python"]
    random.setstate((version, tuple(keys), gauss))
    name, keys, pos, has_gauss, cached = header_rng["numpy"]
    np.random.set_state((name, np.asarray(keys, dtype=np.uint32), pos, has_gauss, cached))
    torch.set_rng_state(state["torch_rng"])
    cuda = state.get("cuda_rng")
    if cuda and torch.cuda.is_available() and len(cuda) == torch.cuda.device_count():
        torch.cuda.set_rng_state_all(cuda)


# ==== memory ======================================================================================


def _is_ring(memory: Any) -> bool:
    return all(hasattr(memory, a) for a in ("ring_arrays", "ring_meta", "restore_ring"))


def _ring_rows(memory: Any, start: int, stop: int) -> dict[str, list[np.ndarray]]:
    """Row blocks of every ring array for absolute counters [start, stop), in arrival order."""
    cap = memory.capacity
    out: dict[str, list[np.ndarray]] = {}
    pos = start % cap
    n = stop - start
    first = min(n, cap - pos)
    for name, arr in memory.ring_arrays().items():
        parts = [arr[pos : pos + first]]
        if first < n:
            parts.append(arr[: n - first])
        out[name] = parts
    return out


def _save_memory(memory: Any, folder: Path, gen: int, old: dict[str, Any] | None, old_gen: int | None) -> dict[str, Any]:
    stats = [float(memory.stat_train_return), float(memory.stat_test_return),
             int(memory.stat_train_steps), int(memory.stat_test_steps)]
    if _is_ring(memory):
        meta = memory.ring_meta()
        total, cap = int(meta["total"]), int(meta["capacity"])
        oldest = int(meta["oldest"])
        segments: list[dict[str, Any]] = []
        start = oldest
        # Segments on disk are reused only if they were written from (or loaded into) this very
        # memory object at the generation now on disk: a memory resumed from a backup or another
        # folder has a different history and is written in full.
        linked = getattr(memory, "_checkpoint_link", None) == (str(folder.resolve()), old_gen)
        if linked and old is not None and old.get("kind") == "ring":
            m = old["meta"]
            same_run = m["uid"] == meta["uid"] and m["capacity"] == cap and int(m["total"]) <= total
            same_layout = m["leaves"] == meta["leaves"] and m["act"] == meta["act"]
            if same_run and same_layout:
                kept = [s for s in old["segments"] if s["stop"] > oldest]
                stored = sum(s["stop"] - s["start"] for s in kept)
                if stored <= 2 * max(1, total - oldest):  # else: compact into one segment
                    segments, start = kept, max(oldest, int(m["total"]))
        if total > start:
            record = _write_segment(
                folder, f"memory-{gen:06d}.safetensors", _ring_rows(memory, start, total),
                {"start": str(start), "stop": str(total)},
            )
            record.update(start=start, stop=total)
            segments.append(record)
        return {"kind": "ring", "meta": meta, "segments": segments, "stats": stats}
    from tmrl import wire

    try:
        data = wire.encode(memory.data)
    except (TypeError, ValueError) as err:
        raise CheckpointError(
            f"cannot save the memory's data ({_one_line(err)}): keep arrays, numbers, strings and "
            "containers in memory.data"
        ) from None
    record = _write_file(folder, f"data-{gen:06d}.wire", data)
    rng = memory.rng.bit_generator.state if hasattr(memory, "rng") else None
    return {"kind": "data", "file": record, "stats": stats, "rng": rng}


def _restore_memory(memory: Any, folder: Path, saved: dict[str, Any]) -> None:
    kind = saved.get("kind")
    if kind == "ring":
        if not _is_ring(memory):
            raise CheckpointError(
                f"checkpoint {folder} holds a built-in memory but {type(memory).__qualname__} is not "
                "one: use the memory class the checkpoint was written with"
            )
        meta = saved["meta"]
        if meta.get("class") != type(memory).__qualname__:
            logger.warning("checkpoint memory was a %s, loading it into a %s", meta.get("class"), type(memory).__qualname__)
        total = int(meta["total"])
        oldest = int(meta.get("oldest", total - min(total, int(meta["capacity"]))))
        loaded: dict[str, list[np.ndarray]] = {}
        from safetensors import safe_open

        first = None
        expected_start = 0
        for seg in saved["segments"]:
            path = _check_file(folder, seg)
            start, stop = int(seg["start"]), int(seg["stop"])
            skip = max(0, oldest - start)
            if first is None:
                first = start + skip
            elif start != expected_start:
                raise CheckpointError(
                    f"checkpoint {folder} is corrupt (memory segments are not contiguous); restore the "
                    "folder from a backup or delete it"
                )
            expected_start = stop
            try:
                with safe_open(str(path), framework="numpy") as f:
                    for name in f.keys():  # noqa: SIM118 (safe_open is not a dict)
                        arr = f.get_tensor(name)
                        if len(arr) != stop - start:
                            raise ValueError(f"{name} has {len(arr)} rows for samples {start}..{stop}")
                        loaded.setdefault(name, []).append(arr[skip:])
            except Exception as err:  # noqa: BLE001 (safetensors raises its own error types)
                raise CheckpointError(
                    f"checkpoint file {path} is corrupt ({_one_line(err)}); restore the folder from a "
                    "backup or delete it"
                ) from None
        first = total if first is None else first
        arrays = {name: np.concatenate(parts) if len(parts) > 1 else parts[0] for name, parts in loaded.items()}

        def rows(name: str) -> tuple[int, np.ndarray]:
            if name not in arrays:
                if total == first:
                    return first, np.zeros((0,), dtype=np.float32)
                raise ValueError(f"no saved rows for memory array {name}")
            return first, arrays[name]

        try:
            memory.restore_ring(meta, rows)
        except (ValueError, KeyError, TypeError) as err:
            raise CheckpointError(
                f"the memory in checkpoint {folder} does not fit this memory ({_one_line(err)}); use "
                "the memory settings the checkpoint was written with"
            ) from None
    elif kind == "data":
        from tmrl import wire

        path = _check_file(folder, saved["file"])
        try:
            memory.data = wire.decode(path.read_bytes(), copy=True)
        except wire.DecodeError as err:
            raise CheckpointError(f"checkpoint file {path} is corrupt ({_one_line(err)})") from None
        if saved.get("rng") is not None and hasattr(memory, "rng"):
            memory.rng.bit_generator.state = saved["rng"]
    else:
        raise CheckpointError(f"checkpoint {folder} has an unknown memory kind {kind!r}: upgrade tmrl")
    (memory.stat_train_return, memory.stat_test_return, memory.stat_train_steps, memory.stat_test_steps) = saved["stats"]


# ==== public API ==================================================================================


def save_checkpoint(training: Any, path: str | os.PathLike[str]) -> Path:
    """Save the full training state into the checkpoint folder ``path``.

    Saved: the agent's ``state_dict()`` (models, optimizers, entropy coefficient...), the memory
    (incrementally for built-in memories), ``epoch``, ``total_updates``, ``total_samples``, and
    the Python, NumPy, torch (and CUDA) RNG states.

    Args:
        training: a :class:`tmrl.training_offline.TrainingOffline` (anything with ``agent``,
            ``memory``, ``epoch``, ``total_updates`` and ``total_samples``).
        path: the checkpoint folder (created when missing).

    Returns:
        The folder.

    Raises:
        CheckpointError: ``path`` is a file or a folder of saved state without its header, the
            agent's state holds non-finite values, or the agent or memory cannot be saved.
    """
    folder = Path(path)
    if folder.exists() and not folder.is_dir():
        raise CheckpointError(
            f"{folder} is a file, not a tmrl checkpoint folder: move it away or choose another checkpoint path"
        )
    old: dict[str, Any] | None = None
    if (folder / HEADER).exists():
        try:
            old = _read_header(folder)
        except CheckpointError as err:
            logger.warning("replacing an unreadable checkpoint at %s (%s)", folder, err)
    else:
        checkpoint_complete(folder)  # refuses a folder of saved state without its header
    folder.mkdir(parents=True, exist_ok=True)
    gen = int(old["generation"]) + 1 if old else 1

    state: dict[str, Any] = {"agent": _agent_state(training.agent), "torch_rng": torch.get_rng_state()}
    from tmrl.algorithms.guard import all_finite

    if not all_finite(state["agent"]):
        # A NaN checkpoint would poison every restart: keep the previous one instead.
        raise CheckpointError(
            f"not saving {folder}: the agent's state holds NaN or infinite values (the previous "
            "checkpoint is kept); see the trainer's log for skipped updates"
        )
    if torch.cuda.is_available() and torch.cuda.is_initialized():
        state["cuda_rng"] = torch.cuda.get_rng_state_all()
    buf = io.BytesIO()
    torch.save(state, buf)
    state_record = _write_file(folder, f"state-{gen:06d}.pt", buf.getvalue())

    memory_record = _save_memory(
        training.memory, folder, gen, old["memory"] if old else None, int(old["generation"]) if old else None
    )
    header = {
        "format": FORMAT,
        "version": VERSION,
        "generation": gen,
        "epoch": int(training.epoch),
        "total_updates": int(training.total_updates),
        "total_samples": int(training.total_samples),
        "training_class": type(training).__qualname__,
        "run_id": run_id if isinstance(run_id := getattr(training, "run_id", None), str) else None,
        "state": state_record,
        "memory": memory_record,
        "rng": {"python": _python_rng(), "numpy": _numpy_rng()},
    }
    atomic_write_text(folder / HEADER, json.dumps(header))
    _link(training.memory, folder, gen)
    _remove_unreferenced(folder, header)
    return folder


def _link(memory: Any, folder: Path, generation: int) -> None:
    """Remember which checkpoint generation this memory matches (enables incremental saves)."""
    try:
        memory._checkpoint_link = (str(folder.resolve()), generation)
    except AttributeError:  # memories with __slots__: always saved in full
        pass


def _referenced(header: dict[str, Any]) -> set[str]:
    names = {header["state"]["file"]}
    memory = header["memory"]
    if memory.get("kind") == "ring":
        names.update(s["file"] for s in memory["segments"])
    elif memory.get("kind") == "data":
        names.add(memory["file"]["file"])
    return names


def _remove_unreferenced(folder: Path, header: dict[str, Any]) -> None:
    keep = _referenced(header)
    for entry in folder.iterdir():
        name = entry.name
        # Only files this module writes (or the temporaries of an interrupted write) are removed.
        if name not in keep and (_OWN_FILE.match(name) or _TMP_FILE.match(name)):
            # A file an antivirus or a backup tool holds stays until the next checkpoint removes it.
            platform.remove(entry)


def _build(training: Any) -> Any:
    if hasattr(training, "run_epoch") and hasattr(training, "memory"):
        return training
    if callable(training):
        return training()
    raise TypeError("load_checkpoint needs a TrainingOffline instance or a callable that builds one")


def load_checkpoint(path: str | os.PathLike[str], training: Any) -> Any:
    """Restore the training state saved in the checkpoint folder ``path``.

    Args:
        path: the checkpoint folder.
        training: the :class:`~tmrl.training_offline.TrainingOffline` to restore into, or a
            zero-argument callable (class or partial) that builds it. Nothing in the checkpoint
            names code to run: the classes always come from the caller.

    Returns:
        The restored training object.

    Raises:
        CheckpointError: the checkpoint is missing, foreign, truncated, corrupt or does not fit
            ``training`` (one line naming the file and what to do).
    """
    folder = Path(path)
    header = _read_header(folder)
    instance = _build(training)
    state_path = _check_file(folder, header["state"])
    try:
        data = platform.read_bytes(state_path)  # retried while another process holds it (Windows)
    except OSError as err:
        raise CheckpointError(f"checkpoint file {state_path} cannot be read ({_one_line(err)})") from None
    try:
        state = torch.load(io.BytesIO(data), map_location="cpu", weights_only=True)
    except Exception as err:  # noqa: BLE001 (torch raises several types for bad files)
        raise CheckpointError(f"checkpoint file {state_path} is corrupt ({_one_line(err)})") from None
    try:
        instance.agent.load_state_dict(state["agent"])
    except (KeyError, RuntimeError, ValueError, TypeError) as err:
        raise CheckpointError(
            f"the agent saved in {folder} does not fit this agent ({_one_line(err)}); use the model "
            "settings the checkpoint was written with"
        ) from None
    try:
        _restore_memory(instance.memory, folder, header["memory"])
        _restore_rng(header["rng"], state)
    except CheckpointError:
        raise
    except (KeyError, TypeError, ValueError, IndexError, OverflowError, RuntimeError) as err:
        raise CheckpointError(
            f"{folder / HEADER} is corrupt ({type(err).__name__}: {_one_line(err)}); restore the folder "
            "from a backup or delete it"
        ) from None
    _link(instance.memory, folder, int(header["generation"]))
    instance.epoch = int(header["epoch"])
    instance.total_updates = int(header["total_updates"])
    instance.total_samples = int(header["total_samples"])
    if header.get("run_id") is not None:
        instance.run_id = header["run_id"]
    logger.info(
        "resumed from checkpoint %s: epoch %d, %d samples in memory (%d received), %d updates",
        folder, instance.epoch, len(instance.memory), instance.total_samples, instance.total_updates,
    )
    return instance


def load_memory(memory: Any, path: str | os.PathLike[str]) -> Any:
    """Fill ``memory`` with the memory saved in the checkpoint folder ``path`` (used by built-in
    memories for ``dataset_path``); the agent and counters in the checkpoint are ignored.

    Returns:
        ``memory``.

    Raises:
        CheckpointError: as :func:`load_checkpoint`.
    """
    folder = Path(path)
    header = _read_header(folder)
    try:
        _restore_memory(memory, folder, header["memory"])
    except CheckpointError:
        raise
    except (KeyError, TypeError, ValueError, IndexError, OverflowError) as err:
        raise CheckpointError(
            f"{folder / HEADER} is corrupt ({type(err).__name__}: {_one_line(err)}); restore the folder "
            "from a backup or delete it"
        ) from None
    logger.info("loaded %d transitions from %s", len(memory), folder)
    return memory


def dump_run_instance(run_instance: Any, checkpoint_path: str | os.PathLike[str]) -> None:
    """Default ``dump_run_instance_fn`` of the networking ``Trainer``: :func:`save_checkpoint`.

    Args:
        run_instance: the training instance (a :class:`~tmrl.training_offline.TrainingOffline`).
        checkpoint_path: the checkpoint folder.
    """
    save_checkpoint(run_instance, checkpoint_path)


def load_run_instance(checkpoint_path: str | os.PathLike[str], run_cls: Callable[[], Any]) -> Any:
    """Default ``load_run_instance_fn`` of the networking ``Trainer``: builds ``run_cls()`` and
    restores the checkpoint into it (:func:`load_checkpoint`).

    Args:
        checkpoint_path: the checkpoint folder.
        run_cls: builds a fresh training instance to restore into.
    """
    return load_checkpoint(checkpoint_path, run_cls)


def make_load_run_instance_fn(run_cls: Callable[[], Any]) -> Callable[[str | os.PathLike[str]], Any]:
    """A one-argument ``load_run_instance_fn(checkpoint_path)`` bound to ``run_cls``, for code
    written against tmrl 0.7's signature."""

    def load_run_instance_fn(checkpoint_path: str | os.PathLike[str]) -> Any:
        return load_checkpoint(checkpoint_path, run_cls)

    return load_run_instance_fn


_LOOP_SETTINGS = ("epochs", "rounds", "steps", "update_model_interval", "update_buffer_interval",
                  "max_training_steps_per_env_step", "start_training", "sleep_between_buffer_retrieval_attempts")
"""Settings of a training loop that :func:`update_run_instance` takes from the new one."""
_AGENT_SETTINGS = {"lr_actor": "pi_optimizer", "lr_critic": "q_optimizer", "lr_entropy": "alpha_optimizer",
                   "gamma": None, "polyak": None}
"""Agent settings it takes, and the optimizer whose learning rate follows each."""


def update_run_instance(run_instance: Any, training_cls: Any) -> Any:
    """An ``updater_fn`` for :class:`~tmrl.networking.Trainer`: a resumed run takes the settings
    that ``training_cls`` (a ``partial``) gives now, so that editing ``config.json`` between two
    runs changes a resumed run as tmrl 0.7's ``update_run_instance`` did.

    Taken over: the loop's epochs, rounds, steps, intervals and ratios; the agent's learning rates
    (set in its optimizers, whose state is kept), ``gamma`` and ``polyak``; the memory's batch
    size. The memory's contents, the networks and the counters are kept.

    Returns:
        ``run_instance``, updated in place.
    """
    loop = dict(getattr(training_cls, "keywords", {}) or {})
    for name in _LOOP_SETTINGS:
        if name in loop and getattr(run_instance, name, None) != loop[name]:
            logger.info("resumed run: %s %s -> %s", name, getattr(run_instance, name, None), loop[name])
            setattr(run_instance, name, loop[name])
    memory = getattr(run_instance, "memory", None)
    if memory is not None and hasattr(memory, "nb_steps"):
        memory.nb_steps = run_instance.steps
    memory_kwargs = dict(getattr(loop.get("memory_cls"), "keywords", {}) or {})
    if memory is not None and "batch_size" in memory_kwargs:
        memory.batch_size = int(memory_kwargs["batch_size"])
    agent = getattr(run_instance, "agent", None)
    agent_kwargs = dict(getattr(loop.get("training_agent_cls"), "keywords", {}) or {})
    for name, optimizer_name in _AGENT_SETTINGS.items():
        if agent is None or name not in agent_kwargs or getattr(agent, name, None) == agent_kwargs[name]:
            continue
        logger.info("resumed run: %s %s -> %s", name, getattr(agent, name, None), agent_kwargs[name])
        setattr(agent, name, agent_kwargs[name])
        optimizer = getattr(agent, optimizer_name, None) if optimizer_name else None
        for group in getattr(optimizer, "param_groups", []):
            group["lr"] = float(agent_kwargs[name])
    return run_instance
