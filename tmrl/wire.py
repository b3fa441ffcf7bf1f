"""The data-only wire format of tmrl: samples, weights and files travel as data, never as code.

``encode(obj) -> bytes`` and ``decode(data) -> obj`` carry ``None``, ``bool``, ``int``, ``float``,
``str``, ``bytes`` (``bytearray`` and ``memoryview`` arrive as ``bytes``), ``tuple``, ``list``,
``dict``, NumPy arrays of bool/integer/float/complex dtypes and any shape, NumPy scalars, and
PyTorch tensors (they arrive as NumPy arrays). Nothing in a message can make the decoder run code,
allocate more memory than the message holds, recurse deeper than :data:`MAX_DEPTH` or loop forever.

Layout: ``b"TMRW"``, a version byte, then one value. A value is a one-byte tag followed by its
body; lengths and counts are little-endian ``uint64``. The data of arrays of 256 bytes or more is padded so
that it starts at a multiple of 16 bytes from the start of the message, which lets :func:`decode`
return zero-copy views when the input buffer itself is aligned (``bytes`` and ``bytearray``
objects are); smaller arrays are always decoded as fresh copies.
"""

from __future__ import annotations

import math
import struct
import sys
from collections.abc import Callable
from typing import Any

import numpy as np

from tmrl.errors import UserError

__all__ = ["MAGIC", "MAX_DEPTH", "VERSION", "DecodeError", "decode", "encode"]

MAGIC = b"TMRW"
"""The four bytes every message starts with."""
VERSION = 1
"""The format version, the byte after :data:`MAGIC`; :func:`decode` refuses any other."""
MAX_DEPTH = 100
"""Deepest nesting of containers that :func:`encode` writes and :func:`decode` reads."""
MAX_BIGINT_BYTES = 8192
"""Largest integer body (bytes of two's complement); far beyond any real use, and small enough that
converting it stays cheap."""
_ALIGN = 16
_ALIGN_MIN = 256  # arrays at least this big (bytes) are aligned and decoded as views
_MAX_NDIM = 64

_HEADER = MAGIC + bytes([VERSION])
_U64 = struct.Struct("<Q")
_I64 = struct.Struct("<q")
_F64 = struct.Struct("<d")
_U8 = struct.Struct("<B")
_SHAPES = [struct.Struct(f"<{i}Q") for i in range(65)]  # index: ndim (at most _MAX_NDIM)

# Tags (one byte each).
_NONE, _TRUE, _FALSE = b"N", b"T", b"F"
_INT, _BIGINT, _FLOAT, _STR, _BYTES = b"i", b"I", b"f", b"s", b"b"
_TUPLE, _LIST, _DICT, _ARRAY, _SCALAR = b"t", b"l", b"d", b"a", b"n"

# dtype kinds that are plain numbers: bool, signed, unsigned, float, complex.
_NUMERIC_KINDS = frozenset("biufc")
_LITTLE = sys.byteorder == "little"
# Caches of dtype headers (encode) and parsed dtype codes (decode); bounded, valid entries only.
_DTYPE_HEADERS: dict[np.dtype, bytes] = {}
_DTYPES: dict[bytes, np.dtype] = {}


class DecodeError(UserError, ValueError):
    """The bytes are not a valid tmrl wire message (corrupt, truncated, foreign or malicious)."""


# ------------------------------------------------------------------------------------------------
# encoding


def encode(obj: Any) -> bytes:
    """Serialize a data-only object to bytes.

    Args:
        obj: ``None``, ``bool``, ``int``, ``float``, ``str``, bytes-like, ``tuple``, ``list``,
            ``dict`` (keys: ``str``, ``int``, ``bool``, ``float``, ``bytes``, ``None`` or tuples of
            those), NumPy arrays or scalars of bool/int/uint/float/complex dtype, or torch tensors,
            nested to at most :data:`MAX_DEPTH` levels.

    Returns:
        The message. Arrays are written in little-endian, C order; a torch ``bfloat16`` tensor is
        written as ``float32`` because NumPy has no such dtype.

    Raises:
        TypeError: ``obj`` contains a value of another type (a class instance, a function, an
            object or string dtype array...).
        ValueError: nesting deeper than :data:`MAX_DEPTH`, or an integer larger than
            :data:`MAX_BIGINT_BYTES` bytes.
    """
    enc = _Encoder()
    enc.value(obj, 0)
    return b"".join(enc.parts)


class _Encoder:
    __slots__ = ("parts", "size")

    def __init__(self) -> None:
        self.parts: list[bytes | bytearray | memoryview] = [_HEADER]
        self.size = len(_HEADER)

    def put(self, b: bytes | bytearray | memoryview) -> None:
        self.parts.append(b)
        self.size += len(b)

    def value(self, obj: Any, depth: int) -> None:
        if depth > MAX_DEPTH:
            raise ValueError(f"object nested deeper than {MAX_DEPTH} levels cannot be encoded")
        t = type(obj)
        # Exact-type fast paths first: these are by far the most common values in samples.
        if obj is None:
            self.put(_NONE)
        elif t is bool:
            self.put(_TRUE if obj else _FALSE)
        elif t is float:
            self.put(_FLOAT + _F64.pack(obj))
        elif t is int:
            self.int_(obj)
        elif t is tuple or t is list:
            self.put((_TUPLE if t is tuple else _LIST) + _U64.pack(len(obj)))
            depth += 1
            value = self.value
            for item in obj:
                value(item, depth)
        elif t is np.ndarray:
            self.array(obj)
        elif t is dict:
            self.put(_DICT + _U64.pack(len(obj)))
            for k, v in obj.items():
                self.key(k, depth + 1)
                self.value(v, depth + 1)
        elif t is str:
            text = obj.encode("utf-8", "surrogatepass")
            self.put(_STR + _U64.pack(len(text)))
            self.put(text)
        elif t is bytes or t is bytearray or t is memoryview:
            data: bytes | bytearray | memoryview = obj
            if t is memoryview:
                data = obj.cast("B") if obj.c_contiguous else memoryview(obj.tobytes())
            self.put(_BYTES + _U64.pack(len(data)))
            self.put(data)
        elif isinstance(obj, np.generic):
            self.scalar(obj)
        elif isinstance(obj, np.ndarray):
            self.array(np.asarray(obj))
        elif _is_torch_tensor(obj):
            self.array(_tensor_to_numpy(obj))
        # Subclasses of builtins (IntEnum, namedtuple, OrderedDict...) travel as their base type.
        elif isinstance(obj, bool):
            self.put(_TRUE if obj else _FALSE)
        elif isinstance(obj, int):
            self.int_(int(obj))
        elif isinstance(obj, float):
            self.put(_FLOAT + _F64.pack(float(obj)))
        elif isinstance(obj, str):
            self.value(str(obj), depth)
        elif isinstance(obj, (tuple, list)):
            self.value((tuple if isinstance(obj, tuple) else list)(obj), depth)
        elif isinstance(obj, dict):
            self.value(dict(obj), depth)
        else:
            raise TypeError(
                f"tmrl.wire cannot encode {t.__module__}.{t.__qualname__}: only None, bool, int, "
                "float, str, bytes, tuple, list, dict, numpy arrays/scalars and torch tensors travel"
            )

    def key(self, k: Any, depth: int) -> None:
        if not _valid_key(k):
            raise TypeError(f"tmrl.wire cannot encode a dict key of type {type(k).__qualname__}")
        self.value(k, depth)

    def int_(self, i: int) -> None:
        if -(2**63) <= i < 2**63:
            self.put(_INT + _I64.pack(i))
            return
        n = (i.bit_length() + 8) // 8  # room for the sign bit
        if n > MAX_BIGINT_BYTES:
            raise ValueError(f"integer too large for tmrl.wire ({n} bytes > {MAX_BIGINT_BYTES})")
        self.put(_BIGINT + _U64.pack(n) + i.to_bytes(n, "little", signed=True))

    def dtype_header(self, dt: np.dtype) -> bytes:
        head = _DTYPE_HEADERS.get(dt)
        if head is None:
            if dt.kind not in _NUMERIC_KINDS or dt.fields is not None or dt.subdtype is not None:
                raise TypeError(f"tmrl.wire cannot encode arrays of dtype {dt}: numbers and bools only")
            code = dt.newbyteorder("<").str.encode("ascii")  # '<f4', '|b1', '|u1'
            head = _U8.pack(len(code)) + code
            if len(_DTYPE_HEADERS) < 256:
                _DTYPE_HEADERS[dt] = head
        return head

    def array(self, arr: np.ndarray) -> None:
        dt = arr.dtype
        ndim = arr.ndim
        if ndim > _MAX_NDIM:
            raise ValueError(f"arrays with more than {_MAX_NDIM} dimensions cannot be encoded")
        head = _ARRAY + self.dtype_header(dt) + struct.pack(f"<B{ndim}Q", ndim, *arr.shape)
        if dt.byteorder == ">" or (dt.byteorder == "=" and not _LITTLE):
            arr = arr.astype(dt.newbyteorder("<"))
        nbytes = arr.nbytes
        if nbytes < _ALIGN_MIN:
            # Small arrays are not padded (decode copies them anyway): padding would cost more
            # bytes on the wire than the data of a typical observation.
            self.put(head + b"\x00" + arr.tobytes())
            return
        arr = np.ascontiguousarray(arr)
        pad = -(self.size + len(head) + 1) % _ALIGN
        self.put(head + _U8.pack(pad) + bytes(pad))
        self.put(arr.data.cast("B"))

    def scalar(self, s: np.generic) -> None:
        dt = s.dtype
        head = _SCALAR + self.dtype_header(dt)
        data = np.asarray(s).astype(dt.newbyteorder("<")).tobytes()
        self.put(head + data)


def _valid_key(k: Any) -> bool:
    if k is None or type(k) in (str, int, bool, float, bytes):
        return True
    if type(k) is tuple:
        return all(_valid_key(x) for x in k)
    return isinstance(k, (str, int, float, bytes, np.generic))


def _is_torch_tensor(obj: Any) -> bool:
    # Checked by module name so that tmrl.wire never imports torch.
    mod = type(obj).__module__
    return (mod == "torch" or mod.startswith("torch.")) and hasattr(obj, "detach") and hasattr(obj, "numpy")


def _tensor_to_numpy(t: Any) -> np.ndarray:
    t = t.detach()
    if str(t.dtype) == "torch.bfloat16":
        t = t.float()
    if t.device.type != "cpu":
        t = t.cpu()
    if getattr(t, "is_conj", lambda: False)():
        t = t.resolve_conj()
    return t.numpy()


# ------------------------------------------------------------------------------------------------
# decoding


def decode(data: bytes | bytearray | memoryview, copy: bool = False) -> Any:
    """Rebuild the object that :func:`encode` wrote.

    Args:
        data: one complete message.
        copy: when False (default), arrays are zero-copy views into ``data`` where possible:
            writable if ``data`` is writable (a ``bytearray``), read-only otherwise, and keeping
            ``data`` alive. When True, every array is an independent writable copy.

    Returns:
        The object; arrays are C-contiguous in native byte order, NumPy scalars keep their type,
        ``bytearray``/``memoryview`` values arrive as ``bytes``.

    Raises:
        DecodeError: ``data`` is not a complete, valid tmrl wire message of a known version.
    """
    try:
        mv = memoryview(data)
    except TypeError as e:
        raise DecodeError(f"tmrl.wire.decode needs bytes-like data, not {type(data).__qualname__}") from e
    if mv.ndim != 1 or mv.itemsize != 1:
        try:
            mv = mv.cast("B")
        except TypeError as e:
            raise DecodeError("tmrl.wire.decode needs a contiguous byte buffer") from e
    if len(mv) < len(_HEADER) or mv[:4] != MAGIC:
        raise DecodeError("not a tmrl wire message (bad magic): the peer is not tmrl or the data is corrupt")
    if mv[4] != VERSION:
        raise DecodeError(
            f"tmrl wire format version {mv[4]} is not supported (this tmrl reads version {VERSION}): "
            "use the same tmrl version on every machine"
        )
    dec = _Decoder(mv, copy)
    try:
        obj, pos = dec.value(len(_HEADER), 0)
    except DecodeError:
        raise
    except (
        struct.error,
        IndexError,
        ValueError,
        TypeError,
        OverflowError,
        UnicodeDecodeError,
        MemoryError,
    ) as e:
        # Defensive: any parsing slip on hostile input is reported as corrupt data.
        raise DecodeError(f"corrupt tmrl wire message: {e}") from None
    if pos != len(mv):
        raise DecodeError(f"corrupt tmrl wire message: {len(mv) - pos} trailing bytes")
    return obj


def _corrupt(msg: str) -> DecodeError:
    return DecodeError(f"corrupt tmrl wire message: {msg}")


class _Decoder:
    __slots__ = ("copy", "mv", "n")

    def __init__(self, mv: memoryview, copy: bool):
        self.mv = mv
        self.n = len(mv)
        self.copy = copy

    def value(self, pos: int, depth: int) -> tuple[Any, int]:
        if pos >= self.n:
            raise _corrupt("truncated")
        if depth > MAX_DEPTH:
            raise _corrupt(f"nested deeper than {MAX_DEPTH} levels")
        fn = _TABLE.get(self.mv[pos])
        if fn is None:
            raise _corrupt(f"unknown tag {self.mv[pos]:#04x} at byte {pos}")
        return fn(self, pos + 1, depth)

    def need(self, pos: int, k: int) -> int:
        end = pos + k
        if end > self.n:
            raise _corrupt(f"truncated (needs {k} bytes at byte {pos}, message has {self.n})")
        return end

    def length(self, pos: int) -> tuple[int, int]:
        end = self.need(pos, 8)
        (k,) = _U64.unpack_from(self.mv, pos)
        # Every length or count must fit in what is left: no allocation from a made-up number.
        if k > self.n - end:
            raise _corrupt(f"length {k} at byte {pos} exceeds the remaining {self.n - end} bytes")
        return k, end

    def int_(self, pos: int, depth: int) -> tuple[Any, int]:
        end = self.need(pos, 8)
        return _I64.unpack_from(self.mv, pos)[0], end

    def bigint(self, pos: int, depth: int) -> tuple[Any, int]:
        k, pos = self.length(pos)
        if k > MAX_BIGINT_BYTES:
            raise _corrupt(f"integer of {k} bytes (max {MAX_BIGINT_BYTES})")
        return int.from_bytes(self.mv[pos : pos + k], "little", signed=True), pos + k

    def float_(self, pos: int, depth: int) -> tuple[Any, int]:
        end = self.need(pos, 8)
        return _F64.unpack_from(self.mv, pos)[0], end

    def str_(self, pos: int, depth: int) -> tuple[Any, int]:
        k, pos = self.length(pos)
        try:
            return str(self.mv[pos : pos + k], "utf-8", "surrogatepass"), pos + k
        except UnicodeDecodeError:
            raise _corrupt("invalid UTF-8 in a string") from None

    def bytes_(self, pos: int, depth: int) -> tuple[Any, int]:
        k, pos = self.length(pos)
        return self.mv[pos : pos + k].tobytes(), pos + k

    def items(self, pos: int, depth: int) -> tuple[list[Any], int]:
        k, pos = self.length(pos)
        depth += 1
        if depth > MAX_DEPTH and k:
            raise _corrupt(f"nested deeper than {MAX_DEPTH} levels")
        # The body of value(), inlined: this loop runs once per element of every container.
        mv, n, table = self.mv, self.n, _TABLE
        out: list[Any] = []
        append = out.append
        for _ in range(k):
            if pos >= n:
                raise _corrupt("truncated")
            fn = table.get(mv[pos])
            if fn is None:
                raise _corrupt(f"unknown tag {mv[pos]:#04x} at byte {pos}")
            item, pos = fn(self, pos + 1, depth)
            append(item)
        return out, pos

    def tuple_(self, pos: int, depth: int) -> tuple[Any, int]:
        items, pos = self.items(pos, depth)
        return tuple(items), pos

    def list_(self, pos: int, depth: int) -> tuple[Any, int]:
        return self.items(pos, depth)

    def dict_(self, pos: int, depth: int) -> tuple[Any, int]:
        k, pos = self.length(pos)
        out: dict[Any, Any] = {}
        for _ in range(k):
            key, pos = self.value(pos, depth + 1)
            if not _valid_key(key):
                raise _corrupt(f"invalid dict key type {type(key).__qualname__}")
            val, pos = self.value(pos, depth + 1)
            out[key] = val
        return out, pos

    def dtype(self, pos: int) -> tuple[np.dtype, int]:
        end = self.need(pos, 1)
        k = self.mv[pos]
        if not 2 <= k <= 8:
            raise _corrupt("bad dtype code length")
        end2 = self.need(end, k)
        code = bytes(self.mv[end:end2])
        dt = _DTYPES.get(code)
        if dt is not None:
            return dt, end2
        if (
            code[:1] not in (b"<", b">", b"|", b"=")
            or code[1:2] not in (b"b", b"i", b"u", b"f", b"c")
            or not code[2:].isdigit()
        ):
            raise _corrupt(f"bad dtype code {code!r}")
        try:
            dt = np.dtype(code.decode("ascii"))
        except TypeError:
            raise _corrupt(f"unknown dtype {code!r}") from None
        if dt.kind not in _NUMERIC_KINDS or dt.fields is not None or dt.subdtype is not None:
            raise _corrupt(f"unsupported dtype {dt}")
        if len(_DTYPES) < 256:  # only valid codes get here: a handful at most
            _DTYPES[code] = dt
        return dt, end2

    def array(self, pos: int, depth: int) -> tuple[Any, int]:
        dt, pos = self.dtype(pos)
        mv = self.mv
        end = self.need(pos, 1)
        ndim = mv[pos]
        if ndim > _MAX_NDIM:
            raise _corrupt(f"array with {ndim} dimensions")
        pos = end
        end = self.need(pos, 8 * ndim + 1)
        shape = _SHAPES[ndim].unpack_from(mv, pos)
        pad = mv[end - 1]
        if pad >= _ALIGN:
            raise _corrupt("bad array padding")
        pos = self.need(end, pad)
        count = math.prod(shape)  # Python ints: no overflow
        nbytes = count * dt.itemsize
        if nbytes > self.n - pos:
            raise _corrupt(f"array of {nbytes} bytes exceeds the remaining {self.n - pos} bytes")
        end = pos + nbytes
        if nbytes < _ALIGN_MIN and dt.isnative:
            # Small arrays: a private writable copy (also covers empty arrays).
            arr = np.frombuffer(bytearray(mv[pos:end]), dtype=dt)
            return (arr if ndim == 1 else arr.reshape(shape)), end
        native = dt.newbyteorder("=")
        if count == 0:
            return np.zeros(shape, dtype=native), end
        arr = np.frombuffer(self.mv, dtype=dt, count=count, offset=pos).reshape(shape)
        if dt.byteorder not in ("|", "=") and (dt.byteorder == "<") != _LITTLE:
            arr = arr.astype(native)  # byte swap makes a fresh, writable array
        elif self.copy or nbytes < _ALIGN_MIN or not arr.flags.aligned:
            arr = arr.astype(native, copy=True)
        else:
            arr = arr.view(native)
        return arr, end

    def scalar(self, pos: int, depth: int) -> tuple[Any, int]:
        dt, pos = self.dtype(pos)
        end = self.need(pos, dt.itemsize)
        raw = self.mv[pos:end].tobytes()
        return np.frombuffer(raw, dtype=dt).astype(dt.newbyteorder("="))[0], end


# Tag -> unbound parser. Kept at module level: a per-decoder table of bound methods would be a
# reference cycle holding the input buffer alive until the cyclic garbage collector runs.
_TABLE: dict[int, Callable[[_Decoder, int, int], tuple[Any, int]]] = {
    _NONE[0]: lambda self, p, d: (None, p),
    _TRUE[0]: lambda self, p, d: (True, p),
    _FALSE[0]: lambda self, p, d: (False, p),
    _INT[0]: _Decoder.int_,
    _BIGINT[0]: _Decoder.bigint,
    _FLOAT[0]: _Decoder.float_,
    _STR[0]: _Decoder.str_,
    _BYTES[0]: _Decoder.bytes_,
    _TUPLE[0]: _Decoder.tuple_,
    _LIST[0]: _Decoder.list_,
    _DICT[0]: _Decoder.dict_,
    _ARRAY[0]: _Decoder.array,
    _SCALAR[0]: _Decoder.scalar,
}
