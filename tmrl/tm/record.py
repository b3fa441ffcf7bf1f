"""Reward trajectories: record the car's path, resample it, refuse degenerate recordings, save
and load it safely.

A reward trajectory is a float64 array of shape ``(N, 3)``: positions ``(x, y, z)`` from the start
line to the finish, one every 0.1 m along the driven path (the original tmrl resamples at 0.1 m,
so 100 points are 10 m of progress). It is saved as a ``.npy`` file (data only, read with
``allow_pickle=False``) under ``<data folder>/reward/``.

Legacy ``reward.pkl`` files of the original tmrl are pickled NumPy arrays. They are read by
:func:`read_legacy_reward_pickle`, a restricted reader that interprets only the pickle opcodes a
NumPy array needs and builds the array itself: it never calls ``pickle.load`` and nothing in the
file can run code. Anything else is refused with a clear message.
"""

from __future__ import annotations

import io
import logging
import math
import os
import struct
import time
from pathlib import Path
from typing import Any, Callable

import numpy as np

from tmrl.errors import UserError
from tmrl.util import atomic_write_bytes

__all__ = [
    "DegenerateRecording",
    "RewardFileError",
    "RESAMPLE_STEP",
    "default_reward_path",
    "load_reward",
    "read_legacy_reward_bytes",
    "read_legacy_reward_pickle",
    "record_reward",
    "resample_path",
    "save_reward",
    "trajectory_problem",
    "trim_stationary_start",
    "validate_recording",
]

logger = logging.getLogger(__name__)

RESAMPLE_STEP = 0.1  # metres between two points of a reward trajectory (original tmrl value)
RECORD_HINT = "record one with `python -m tmrl --record-reward` (drive from the start line to the finish)"


class DegenerateRecording(UserError):
    """A recording that cannot serve as a reward trajectory; the message says what went wrong."""


class RewardFileError(UserError):
    """The reward file is missing or unreadable; the message says how to record one."""


# ---------------------------------------------------------------------------------------- paths
def default_reward_path(data_folder: str | os.PathLike[str] | None = None) -> Path:
    """Where the reward trajectory is read and written: ``<data folder>/reward/reward.npy``.

    Args:
        data_folder: the data folder; None for :func:`tmrl.config.loader.data_folder`
            (``$TMRL_DATA``, else ``~/TmrlData``).
    """
    if data_folder is None:
        try:
            from tmrl.config.loader import data_folder as _data_folder  # type: ignore[import-not-found]

            data_folder = _data_folder()
        except ImportError:
            data_folder = os.environ.get("TMRL_DATA") or Path.home() / "TmrlData"
    return Path(data_folder) / "reward" / "reward.npy"


# ---------------------------------------------------------------------------------------- geometry
def trim_stationary_start(positions: np.ndarray, tolerance: float = 1e-3) -> np.ndarray:
    """Drop the leading points where the car has not yet left its first position (the countdown),
    keeping the last of them as the path's start.

    Args:
        positions: ``(N, 3)`` positions in driving order.
        tolerance: a point closer than this to the first one (metres) counts as not moved.
    """
    positions = np.asarray(positions, dtype=np.float64)
    if len(positions) == 0:
        return positions
    moved = np.linalg.norm(positions - positions[0], axis=1) > tolerance
    first = int(np.argmax(moved)) if moved.any() else len(positions) - 1
    return positions[max(first - 1, 0) :]


def resample_path(positions: np.ndarray, step: float = RESAMPLE_STEP) -> np.ndarray:
    """Points every ``step`` metres along the polyline ``positions`` (arc length), starting with
    its first point; the tail shorter than ``step`` is dropped (as in the original recorder).

    A thin wrapper of the shared :func:`tmrl.driving.reward.resample_polyline`, with the checks
    of a recording (a single point is returned as is).

    Args:
        positions: ``(N, 3)`` positions in driving order.
        step: distance between two output points, > 0.

    Returns:
        float64 array ``(M, 3)`` with ``M = floor(length / step) + 1``.
    """
    from tmrl.driving.reward import resample_polyline

    p = np.asarray(positions, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 3 or len(p) == 0:
        raise ValueError(f"positions must have shape (N, 3) with N >= 1, got {p.shape}")
    if step <= 0:
        raise ValueError("step must be > 0")
    if len(p) == 1 or not np.any(np.diff(p, axis=0)):
        return p[:1].copy()
    return resample_polyline(p, spacing=step)


def validate_recording(
    positions: np.ndarray,
    finished: bool,
    min_points: int = 10,
    min_length: float = 10.0,
    allow_unfinished: bool = False,
) -> None:
    """Refuse a recording that would make a useless reward.

    Args:
        positions: the ``(N, 3)`` positions recorded.
        finished: whether the plugin reported the race finished.
        min_points: fewest positions accepted.
        min_length: shortest path accepted, in metres.
        allow_unfinished: accept a recording that never reached the finish line.

    Raises:
        DegenerateRecording: too few positions, no movement, a path shorter than ``min_length``
            metres, or the finish line never reached (unless ``allow_unfinished``).
    """
    p = np.asarray(positions, dtype=np.float64)
    if p.ndim != 2 or p.shape[-1] != 3 or len(p) < min_points:
        n = len(p) if p.ndim >= 1 else 0
        raise DegenerateRecording(
            f"only {n} positions were recorded (need at least {min_points}): keep the game in focus, "
            f"check the OpenPlanet plugin sends data (python -m tmrl --doctor), then drive the whole track"
        )
    if not np.isfinite(p).all():
        raise DegenerateRecording("the recording holds NaN or infinite positions: record again")
    length = float(np.linalg.norm(np.diff(p, axis=0), axis=1).sum())
    if length < 1e-3:
        raise DegenerateRecording(
            "the car never moved during the recording: drive from the start line to the finish"
        )
    if length < min_length:
        raise DegenerateRecording(
            f"the recorded path is only {length:.1f} m long (need {min_length:g} m): drive the whole track"
        )
    if not finished and not allow_unfinished:
        raise DegenerateRecording(
            "the finish line was never reached: drive until the finish (the recording stops there by itself)"
        )


# ---------------------------------------------------------------------------------------- files
def save_reward(trajectory: np.ndarray, path: str | os.PathLike[str] | None = None) -> Path:
    """Write ``trajectory`` ``(N, 3)`` atomically as a ``.npy`` file (no pickle). Returns the path."""
    traj = np.ascontiguousarray(trajectory, dtype=np.float64)
    if traj.ndim != 2 or traj.shape[1] != 3 or len(traj) < 2:
        raise ValueError(f"a reward trajectory has shape (N >= 2, 3), got {traj.shape}")
    path = default_reward_path() if path is None else Path(path)
    buf = io.BytesIO()
    np.save(buf, traj, allow_pickle=False)
    return atomic_write_bytes(path, buf.getvalue())


def load_reward(path: str | os.PathLike[str] | None = None) -> np.ndarray:
    """Read a reward trajectory: ``.npy`` (ours) or a legacy ``reward.pkl`` of the original tmrl.

    When ``path`` is None, ``<data folder>/reward/reward.npy`` is used, else ``reward.pkl`` next
    to it.

    Returns:
        float64 array ``(N, 3)``.

    Raises:
        RewardFileError: no file, or a file that is not a reward trajectory (message: how to
            record one).
    """
    if path is None:
        path = default_reward_path()
        if not path.exists() and path.with_suffix(".pkl").exists():
            path = path.with_suffix(".pkl")
    path = Path(path)
    if not path.exists():
        raise RewardFileError(f"no reward file at {path}: {RECORD_HINT}")
    try:
        if path.suffix == ".pkl":
            arr = read_legacy_reward_pickle(path)
        else:
            arr = np.load(path, allow_pickle=False)
    except (ValueError, OSError, EOFError) as err:
        raise RewardFileError(f"{path} is not a reward trajectory ({err}): {RECORD_HINT}") from None
    arr = np.asarray(arr)
    problem = trajectory_problem(arr)
    if problem is not None:
        raise RewardFileError(f"{path} {problem}: {RECORD_HINT}")
    return arr.astype(np.float64, copy=False)


def trajectory_problem(arr: np.ndarray) -> str | None:
    """Why an array is not a reward trajectory (positions ``(N >= 2, 3)`` of finite numbers), as
    words that follow a file name; None when it is one.

    Args:
        arr: the array read from a reward file.
    """
    if arr.ndim != 2 or arr.shape[1] != 3 or len(arr) < 2 or arr.dtype.kind not in "fiu":
        return f"holds an array of shape {arr.shape} and dtype {arr.dtype}, not positions (N, 3)"
    if not np.isfinite(arr).all():
        return "holds positions that are not finite numbers"
    return None


# ---------------------------------------------------------------------------------------- legacy pickle
_ARRAY_GLOBALS = {
    ("numpy.core.multiarray", "_reconstruct"): "reconstruct",
    ("numpy._core.multiarray", "_reconstruct"): "reconstruct",
    ("numpy", "ndarray"): "ndarray",
    ("numpy", "dtype"): "dtype",
    ("numpy.core.numeric", "_frombuffer"): "frombuffer",
    ("numpy._core.numeric", "_frombuffer"): "frombuffer",
    ("_codecs", "encode"): "encode",
}
_MARK = object()


class _Global:
    def __init__(self, kind: str) -> None:
        self.kind = kind


class _ArrayStub:
    def __init__(self) -> None:
        self.array: np.ndarray | None = None


class _DtypeStub:
    def __init__(self, spec: str) -> None:
        self.spec = spec
        self.order = "="


def _make_dtype(stub: Any) -> np.dtype:
    if not isinstance(stub, _DtypeStub):
        raise ValueError("array dtype is not a plain dtype")
    dt = np.dtype(stub.spec)
    if dt.kind not in "biuf" or dt.fields is not None or dt.subdtype is not None:
        raise ValueError(f"dtype {stub.spec!r} is not a plain numeric dtype")
    if stub.order == "<":
        dt = dt.newbyteorder("<")
    elif stub.order == ">":
        dt = dt.newbyteorder(">")
    return dt


def _build_array(raw: Any, dtype: np.dtype, shape: Any, fortran: bool) -> np.ndarray:
    if isinstance(raw, str):  # Python 2 pickles hold the data as a latin-1 str
        raw = raw.encode("latin-1")
    if not isinstance(raw, (bytes, bytearray)):
        raise ValueError("array data is not a byte string")
    if not (
        isinstance(shape, tuple)
        and all(isinstance(s, int) and not isinstance(s, bool) and s >= 0 for s in shape)
    ):
        raise ValueError("array shape is not a tuple of sizes")
    count = math.prod(shape)  # exact Python integers: no overflow to fool the size check
    if count * dtype.itemsize != len(raw):
        raise ValueError("array data does not match its shape")
    return (
        np.frombuffer(bytes(raw), dtype=dtype, count=count)
        .reshape(shape, order="F" if fortran else "C")
        .copy()
    )


def read_legacy_reward_pickle(path: str | os.PathLike[str], max_bytes: int = 512 * 2**20) -> np.ndarray:
    """Read a NumPy array from a pickle file without unpickling it.

    Only the opcodes a pickled numeric NumPy array uses are interpreted (protocols 2 to 5, in-band
    data) and only the NumPy array constructors are recognised, by name; the array is built here
    with ``np.frombuffer``. Nothing in the file is imported or called.

    Args:
        path: the pickle file (tmrl 0.7's ``reward.pkl``).
        max_bytes: larger files are refused without being read (default 512 MiB).

    Raises:
        ValueError: the file holds anything other than one numeric NumPy array (message says so).
    """
    path = Path(path)
    if path.stat().st_size > max_bytes:
        raise ValueError(f"file is larger than {max_bytes} bytes")
    return read_legacy_reward_bytes(path.read_bytes(), max_bytes)


def read_legacy_reward_bytes(data: bytes, max_bytes: int = 512 * 2**20) -> np.ndarray:
    """:func:`read_legacy_reward_pickle` for a pickle already in memory (a member of an archive).

    Args:
        data: the pickle's bytes.
        max_bytes: larger pickles are refused without being read.

    Raises:
        ValueError: as :func:`read_legacy_reward_pickle`.
    """
    if len(data) > max_bytes:
        raise ValueError(f"pickle is larger than {max_bytes} bytes")
    try:
        return _interpret(bytes(data))
    except (IndexError, struct.error, UnicodeDecodeError, TypeError, KeyError) as err:
        raise ValueError(f"not a pickled NumPy array ({type(err).__name__})") from None


def _interpret(data: bytes) -> np.ndarray:  # noqa: C901 (one opcode per branch reads best)
    stack: list[Any] = []
    memo: dict[int, Any] = {}
    pos = 0

    def take(n: int) -> bytes:
        nonlocal pos
        if pos + n > len(data):
            raise ValueError("truncated pickle")
        out = data[pos : pos + n]
        pos += n
        return out

    def uint(n: int) -> int:
        return int.from_bytes(take(n), "little")

    def pop_mark() -> list[Any]:
        for i in range(len(stack) - 1, -1, -1):
            if stack[i] is _MARK:
                items = stack[i + 1 :]
                del stack[i:]
                return items
        raise ValueError("pickle MARK missing")

    def line() -> str:
        nonlocal pos
        end = data.index(b"\n", pos)
        out = data[pos:end].decode("ascii")
        pos = end + 1
        return out

    def find_global(module: str, name: str) -> _Global:
        kind = _ARRAY_GLOBALS.get((module, name))
        if kind is None:
            raise ValueError(f"refusing to reference {module}.{name}: only NumPy arrays are accepted")
        return _Global(kind)

    while True:
        op = take(1)
        if op == b"\x80":  # PROTO
            proto = uint(1)
            if proto < 2 or proto > 5:
                raise ValueError(f"unsupported pickle protocol {proto}")
        elif op == b"\x95":  # FRAME
            take(8)
        elif op == b".":  # STOP
            break
        elif op == b"(":  # MARK
            stack.append(_MARK)
        elif op == b")":  # EMPTY_TUPLE
            stack.append(())
        elif op == b"t":  # TUPLE
            stack.append(tuple(pop_mark()))
        elif op in (b"\x85", b"\x86", b"\x87"):  # TUPLE1..3
            n = op[0] - 0x84
            items = tuple(stack[-n:])
            del stack[-n:]
            stack.append(items)
        elif op == b"]":  # EMPTY_LIST (numpy never needs one, but empty lists are harmless)
            stack.append([])
        elif op == b"N":
            stack.append(None)
        elif op == b"\x88":
            stack.append(True)
        elif op == b"\x89":
            stack.append(False)
        elif op == b"K":  # BININT1
            stack.append(uint(1))
        elif op == b"M":  # BININT2
            stack.append(uint(2))
        elif op == b"J":  # BININT
            stack.append(struct.unpack("<i", take(4))[0])
        elif op == b"\x8a":  # LONG1
            n = uint(1)
            stack.append(int.from_bytes(take(n), "little", signed=True))
        elif op == b"G":  # BINFLOAT
            stack.append(struct.unpack(">d", take(8))[0])
        elif op == b"C":  # SHORT_BINBYTES
            stack.append(take(uint(1)))
        elif op == b"B":  # BINBYTES
            stack.append(take(uint(4)))
        elif op == b"\x8e":  # BINBYTES8
            stack.append(take(uint(8)))
        elif op == b"\x96":  # BYTEARRAY8
            stack.append(bytearray(take(uint(8))))
        elif op == b"U":  # SHORT_BINSTRING (protocol 2 text)
            stack.append(take(uint(1)).decode("latin-1"))
        elif op == b"T":  # BINSTRING
            stack.append(take(uint(4)).decode("latin-1"))
        elif op == b"\x8c":  # SHORT_BINUNICODE
            stack.append(take(uint(1)).decode("utf-8"))
        elif op == b"X":  # BINUNICODE
            stack.append(take(uint(4)).decode("utf-8"))
        elif op == b"\x8d":  # BINUNICODE8
            stack.append(take(uint(8)).decode("utf-8"))
        elif op == b"c":  # GLOBAL
            module = line()
            stack.append(find_global(module, line()))
        elif op == b"\x93":  # STACK_GLOBAL
            name, module = stack.pop(), stack.pop()
            if not (isinstance(module, str) and isinstance(name, str)):
                raise ValueError("malformed STACK_GLOBAL")
            stack.append(find_global(module, name))
        elif op == b"q":  # BINPUT
            memo[uint(1)] = stack[-1]
        elif op == b"r":  # LONG_BINPUT
            memo[uint(4)] = stack[-1]
        elif op == b"\x94":  # MEMOIZE
            memo[len(memo)] = stack[-1]
        elif op == b"h":  # BINGET
            stack.append(memo[uint(1)])
        elif op == b"j":  # LONG_BINGET
            stack.append(memo[uint(4)])
        elif op == b"R":  # REDUCE
            args = stack.pop()
            func = stack.pop()
            stack.append(_reduce(func, args))
        elif op == b"b":  # BUILD
            state = stack.pop()
            _build(stack[-1], state)
        elif op in (b"\x97", b"\x98"):  # NEXT_BUFFER, READONLY_BUFFER
            raise ValueError("out-of-band pickle buffers are not supported")
        else:
            raise ValueError(f"pickle opcode {op!r} is not part of a NumPy array")
    if len(stack) != 1:
        raise ValueError("pickle does not hold exactly one object")
    result = stack[0]
    if isinstance(result, _ArrayStub):
        result = result.array
    if not isinstance(result, np.ndarray):
        raise ValueError(f"pickle holds {type(result).__name__}, not a NumPy array")
    return result


def _reduce(func: Any, args: Any) -> Any:
    if not isinstance(func, _Global) or not isinstance(args, tuple):
        raise ValueError("pickle calls something other than a NumPy constructor")
    if func.kind == "reconstruct":
        if len(args) != 3 or not (isinstance(args[0], _Global) and args[0].kind == "ndarray"):
            raise ValueError("unexpected ndarray reconstruction")
        return _ArrayStub()
    if func.kind == "dtype":
        if not args or not isinstance(args[0], str):
            raise ValueError("unexpected dtype construction")
        return _DtypeStub(args[0])
    if func.kind == "encode":  # protocol 2 stores bytes as latin-1 text
        if len(args) != 2 or not isinstance(args[0], str) or args[1] != "latin1":
            raise ValueError("unexpected byte-string encoding")
        return args[0].encode("latin-1")
    if func.kind == "frombuffer":  # protocol 5: (buffer, dtype, shape, order)
        if len(args) != 4:
            raise ValueError("unexpected frombuffer arguments")
        raw, dt, shape, order = args
        return _build_array(raw, _make_dtype(dt), shape, order == "F")
    raise ValueError(f"{func.kind} cannot be called")


def _build(obj: Any, state: Any) -> None:
    if isinstance(obj, _DtypeStub):
        # dtype state: (version, byte order, subarray, names, fields, elsize, alignment, flags[, metadata])
        if not isinstance(state, tuple) or len(state) < 8 or state[2] is not None or state[3] is not None:
            raise ValueError("only plain dtypes are accepted")
        obj.order = state[1] if state[1] in ("<", ">", "|", "=") else "="
        return
    if isinstance(obj, _ArrayStub):
        # ndarray state: (version, shape, dtype, is_fortran, raw data)
        if not isinstance(state, tuple) or len(state) != 5:
            raise ValueError("unexpected ndarray state")
        _, shape, dt, fortran, raw = state
        if isinstance(raw, list):
            raise ValueError("object arrays are not accepted")
        obj.array = _build_array(raw, _make_dtype(dt), shape, bool(fortran))
        return
    raise ValueError("pickle sets the state of something other than a NumPy array")


# ---------------------------------------------------------------------------------------- recording
def record_reward(
    client: Any,
    path: str | os.PathLike[str] | None = None,
    *,
    wait_start: Callable[[], None] | None = None,
    stop_requested: Callable[[], bool] | None = None,
    step: float = RESAMPLE_STEP,
    min_length: float = 10.0,
    max_duration: float | None = None,
    frame_timeout: float | None = None,
) -> Path:
    """Record a reward trajectory from the OpenPlanet telemetry and save it.

    Every new telemetry frame's position is kept from the start (immediately, or after
    ``wait_start()`` returns) until the plugin reports the race finished. A respawn during the
    recording (the plugin's distance drops) starts the recording again, so the user can retry.
    The path is trimmed of the countdown, resampled every ``step`` metres, checked
    (:func:`validate_recording`) and saved (:func:`save_reward`).

    Args:
        client: an :class:`~tmrl.tm.openplanet.OpenPlanetClient` (or anything with
            ``retrieve_data(timeout=...)`` returning the 11 telemetry values).
        path: output file; default :func:`default_reward_path`.
        wait_start: blocks until the user asks to start (e.g. presses Enter).
        step: distance between two points of the saved trajectory, in metres.
        min_length: shortest path accepted, in metres (see :func:`validate_recording`).
        stop_requested: polled after each frame; True stops the recording (before the finish,
            which is then refused as degenerate).
        max_duration: seconds after which the recording stops.
        frame_timeout: passed to ``retrieve_data``.

    Returns:
        The saved file's path.

    Raises:
        DegenerateRecording: the recording cannot be used (message says why and what to do).
        tmrl.tm.openplanet.TelemetryTimeout: the plugin stopped sending.
    """
    if wait_start is not None:
        wait_start()
    positions: list[tuple[float, float, float]] = []
    finished = False
    armed = False  # a finish flag still up from the previous race must not end this recording
    last_distance: float | None = None
    t0 = time.monotonic()
    try:
        while True:
            data = client.retrieve_data(timeout=frame_timeout)
            distance = float(data[1])
            if last_distance is not None and distance < last_distance - 1.0 and positions:
                logger.info("respawn detected: recording again from the start")
                positions.clear()
            last_distance = distance
            if bool(data[8]):
                if armed:
                    finished = True
                    break
                continue
            armed = True
            pos = (float(data[2]), float(data[3]), float(data[4]))
            if pos == (0.0, 0.0, 0.0):  # the plugin sends zeros while a map loads: not a position
                continue
            positions.append(pos)
            if stop_requested is not None and stop_requested():
                break
            if max_duration is not None and time.monotonic() - t0 > max_duration:
                break
    except KeyboardInterrupt:
        logger.info("recording interrupted")
    raw = np.asarray(positions, dtype=np.float64).reshape(-1, 3)
    validate_recording(raw, finished, min_length=min_length)
    traj = resample_path(trim_stationary_start(raw), step=step)
    out = save_reward(traj, path)
    logger.info(
        "saved a reward trajectory of %d points (%.1f m) to %s", len(traj), (len(traj) - 1) * step, out
    )
    return out
