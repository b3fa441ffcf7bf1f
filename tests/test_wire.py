"""Tests of tmrl.wire: round trips of every carried type, refusals, and hostile input."""

from __future__ import annotations

import math
import pickle
import random
import struct

import numpy as np
import pytest

from tmrl import wire
from tmrl.errors import UserError


def _same(a, b) -> bool:
    if isinstance(a, np.ndarray):
        return (
            isinstance(b, np.ndarray)
            and a.dtype.newbyteorder("=") == b.dtype
            and a.shape == b.shape
            and np.array_equal(a, b, equal_nan=a.dtype.kind in "fc")
        )
    if isinstance(a, np.generic):
        return type(a) is type(b) and (a == b or (np.isnan(a) and np.isnan(b)))
    if isinstance(a, (tuple, list)):
        return type(a) is type(b) and len(a) == len(b) and all(_same(x, y) for x, y in zip(a, b))
    if isinstance(a, dict):
        return type(b) is dict and list(a) == list(b) and all(_same(a[k], b[k]) for k in a)
    if isinstance(a, float) and math.isnan(a):
        return isinstance(b, float) and math.isnan(b)
    return type(a) is type(b) and a == b


SCALARS = [
    None,
    True,
    False,
    0,
    1,
    -1,
    2**63 - 1,
    -(2**63),
    2**63,
    -(2**63) - 1,
    3**200,
    -(7**300),
    0.0,
    -0.0,
    1.5,
    float("inf"),
    float("-inf"),
    float("nan"),
    "",
    "hé\u20ac\U0001f600",
    b"",
    b"\x00\xff",
]

DTYPES = [
    "bool",
    "int8",
    "uint8",
    "int16",
    "uint16",
    "int32",
    "uint32",
    "int64",
    "uint64",
    "float16",
    "float32",
    "float64",
    "complex64",
    "complex128",
]


@pytest.mark.parametrize("value", SCALARS, ids=repr)
def test_scalars_round_trip(value):
    assert _same(value, wire.decode(wire.encode(value)))


def test_containers_round_trip():
    obj = {
        "tuple": (1, (2, (3,)), ()),
        "list": [[], [1, "a"], [None]],
        7: {"nested": {"deeper": [1.5]}},
        (1, "k", (2,)): "tuple key",
        -3: b"bytes",
        None: 0,
    }
    back = wire.decode(wire.encode(obj))
    assert _same(obj, back)
    assert list(back) == list(obj)  # key order kept


def test_bytes_like_arrive_as_bytes():
    arr = np.arange(6, dtype=np.uint8).reshape(2, 3)
    back = wire.decode(wire.encode([bytearray(b"ab"), memoryview(b"cd"), memoryview(arr[:, ::2])]))
    assert back == [b"ab", b"cd", bytes([0, 2, 3, 5])]


@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("shape", [(), (0,), (5,), (3, 4), (2, 0, 3), (2, 3, 4, 1)])
def test_arrays_round_trip(dtype, shape):
    rng = np.random.default_rng(0)
    arr = (rng.standard_normal(shape) * 100).astype(dtype)
    back = wire.decode(wire.encode(arr))
    assert _same(arr, back)
    assert back.flags.c_contiguous


@pytest.mark.parametrize("dtype", DTYPES)
def test_numpy_scalars_round_trip(dtype):
    value = np.array(3, dtype=dtype)[()]
    back = wire.decode(wire.encode(value))
    assert type(back) is type(value) and back == value


def test_big_endian_and_non_contiguous_arrays_arrive_native_and_contiguous():
    big = np.arange(24, dtype=">f8").reshape(4, 6)
    view = big[::2, 1::2]
    for arr in (big, view, np.asfortranarray(np.arange(12.0).reshape(3, 4)), np.arange(10)[::-3]):
        back = wire.decode(wire.encode(arr))
        assert back.dtype.isnative and back.flags.c_contiguous
        assert np.array_equal(back, arr)


def test_decode_views_and_copies():
    arr = np.arange(1000, dtype=np.float32)
    data = wire.encode({"x": arr})
    ro = wire.decode(data)["x"]
    assert not ro.flags.writeable  # a view into immutable bytes
    rw = wire.decode(bytearray(data))["x"]
    assert rw.flags.writeable and not rw.flags.owndata  # zero copy
    rw[0] = 42
    cp = wire.decode(data, copy=True)["x"]
    assert cp.flags.writeable and cp.flags.owndata
    assert np.array_equal(cp, arr)


def test_unaligned_input_still_decodes():
    data = wire.encode(np.arange(10, dtype=np.float64))
    shifted = bytearray(b"x" + data)
    back = wire.decode(memoryview(shifted)[1:])
    assert np.array_equal(back, np.arange(10.0)) and back.flags.aligned


def test_torch_tensors_arrive_as_numpy():
    torch = pytest.importorskip("torch")
    t = torch.arange(12, dtype=torch.float32).reshape(3, 4).t()  # non-contiguous
    back = wire.decode(
        wire.encode(
            {"w": t, "h": torch.ones(2, dtype=torch.bfloat16), "p": torch.nn.Parameter(torch.zeros(2))}
        )
    )
    assert isinstance(back["w"], np.ndarray) and np.array_equal(back["w"], t.numpy())
    assert back["h"].dtype == np.float32 and back["p"].shape == (2,)


def test_subclasses_of_builtins_travel_as_base_types():
    import collections
    import enum

    class Color(enum.IntEnum):
        RED = 3

    point = collections.namedtuple("Point", "x y")(1, 2)
    back = wire.decode(wire.encode([Color.RED, point, collections.OrderedDict(a=1)]))
    assert back == [3, (1, 2), {"a": 1}] and type(back[0]) is int and type(back[1]) is tuple


@pytest.mark.parametrize(
    "bad",
    [
        object(),
        {1, 2},
        np.array(["a"]),
        np.array([object()]),
        np.zeros(2, dtype="datetime64[s]"),
        np.zeros(2, dtype=[("a", "f4")]),
        lambda: 0,
        {[1]: 2} if False else {frozenset(): 1},
    ],
    ids=lambda v: type(v).__name__,
)
def test_encode_refuses_code_and_unsupported_types(bad):
    with pytest.raises(TypeError):
        wire.encode(bad)


def test_encode_refuses_absurd_depth_and_size():
    deep: list = []
    for _ in range(wire.MAX_DEPTH + 5):
        deep = [deep]
    with pytest.raises(ValueError):
        wire.encode(deep)
    with pytest.raises(ValueError):
        wire.encode(1 << (8 * wire.MAX_BIGINT_BYTES + 8))


def test_decode_error_is_a_user_error_and_value_error():
    assert issubclass(wire.DecodeError, UserError) and issubclass(wire.DecodeError, ValueError)


@pytest.mark.parametrize(
    "data",
    [
        b"",
        b"TMRW",
        b"TMRX\x01N",
        b"TMRW\x02N",
        b"TMRW\x01",
        b"TMRW\x01NN",
        b"TMRW\x01?",
        pickle.dumps({"a": 1}),
        pickle.dumps(print),
    ],
    ids=repr,
)
def test_decode_refuses_malformed_messages(data):
    with pytest.raises(wire.DecodeError):
        wire.decode(data)


def test_decode_refuses_lengths_beyond_the_input():
    head = wire.MAGIC + bytes([wire.VERSION])
    for tag in b"sbltd":
        with pytest.raises(wire.DecodeError, match="exceeds"):
            wire.decode(head + bytes([tag]) + struct.pack("<Q", 2**62))
    # An array claiming 2**40 elements in a tiny message.
    arr = head + b"a" + b"\x03<f8" + b"\x02" + struct.pack("<QQ", 2**20, 2**20) + b"\x00"
    with pytest.raises(wire.DecodeError):
        wire.decode(arr)


def test_decode_refuses_excessive_depth():
    head = wire.MAGIC + bytes([wire.VERSION])
    nested = head + (b"l" + struct.pack("<Q", 1)) * (wire.MAX_DEPTH + 10) + b"N"
    with pytest.raises(wire.DecodeError, match="deeper"):
        wire.decode(nested)


def test_decode_refuses_unhashable_keys_and_object_dtypes():
    head = wire.MAGIC + bytes([wire.VERSION])
    bad_key = head + b"d" + struct.pack("<Q", 1) + b"l" + struct.pack("<Q", 0) + b"N"
    with pytest.raises(wire.DecodeError, match="key"):
        wire.decode(bad_key)
    obj_dtype = head + b"n" + b"\x03|O8" + bytes(8)
    with pytest.raises(wire.DecodeError):
        wire.decode(obj_dtype)


def _sample_messages() -> list[bytes]:
    rng = np.random.default_rng(1)
    return [
        wire.encode(
            (
                rng.standard_normal(3).astype(np.float32),
                (rng.standard_normal((2, 4)), np.int64(3), np.arange(5, dtype=">u2")),
                -1.25,
                False,
                True,
                {"crc": 2**70, "name": "ép", "raw": b"\x00" * 9, (1, 2): [None, 3.5]},
            )
        ),
        wire.encode([{"a": [1, [2, [3, (4, "x")]]]}] * 3),
        wire.encode(np.complex64(1 + 2j)),
    ]


@pytest.mark.timeout(60)
def test_fuzz_truncations_and_byte_flips_give_decode_error_or_a_value():
    rnd = random.Random(1234)
    outcomes = {"error": 0, "value": 0}

    def attempt(data: bytes | bytearray) -> None:
        try:
            wire.decode(data)
            outcomes["value"] += 1
        except wire.DecodeError:
            outcomes["error"] += 1

    for msg in _sample_messages():
        for cut in range(len(msg)):
            attempt(msg[:cut])
        for _ in range(1500):
            data = bytearray(msg)
            for _ in range(rnd.randint(1, 4)):
                data[rnd.randrange(len(data))] = rnd.randrange(256)
            attempt(data)
            if rnd.random() < 0.2:
                attempt(bytes(data[: rnd.randrange(len(data) + 1)]))
    # Every truncation must be refused; flips mostly are (flips inside payload bytes are valid).
    assert outcomes["error"] > outcomes["value"] > 0


def test_big_array_round_trip_is_exact():
    arr = np.random.default_rng(2).standard_normal(5_000_000).astype(np.float32)
    back = wire.decode(bytearray(wire.encode(arr)))
    assert np.array_equal(arr, back) and not back.flags.owndata


def test_decode_keeps_no_reference_to_its_input():
    import gc
    import weakref

    class Buf(bytearray):
        pass

    gc.disable()  # a reference cycle would keep the buffer until the cyclic collector runs
    try:
        data = Buf(wire.encode([1, "x", b"y", {"k": 2.5}]))
        ref = weakref.ref(data)
        assert wire.decode(data) == [1, "x", b"y", {"k": 2.5}]
        del data
        assert ref() is None
    finally:
        gc.enable()
