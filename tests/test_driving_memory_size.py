"""Replay memory size of the full (image) TrackMania/simulator pipeline: one stored sample costs
one 64x64 uint8 frame plus its scalars, not a history of float images.

The memory is the one the product builds for ``TM20FULL`` (:func:`tmrl.sim.interfaces.pipeline_parts`),
filled through the product's preprocessor and sample compressor.
"""

from __future__ import annotations

import gc
import tracemalloc
from collections import deque
from typing import Any

import numpy as np
import pytest

from tmrl.sim.interfaces import pipeline_parts

HIST = 4
ACT_BUF = 2
SIDE = 64
FRAME_BYTES = SIDE * SIDE  # one grayscale uint8 frame
# speed, gear, rpm (float32 each), the action (3 float32), the reward (float32), terminated and
# truncated (one byte each).
SCALAR_BYTES = 3 * 4 + 3 * 4 + 4 + 2
N = 3000


class _Buffer:
    """What a trainer hands to ``memory.append``: samples in ``.memory`` plus the statistics."""

    def __init__(self, samples: list) -> None:
        self.memory = samples
        self.sources = None
        self.stat_train_return = 0.0
        self.stat_test_return = 0.0
        self.stat_train_steps = 0
        self.stat_test_steps = 0

    def __len__(self) -> int:
        return len(self.memory)


def _samples(n: int, parts: dict[str, Any], seed: int = 0) -> list:
    """``n`` samples of 64x64 full observations as a worker sends them: raw observation (uint8
    history, action buffer), the product's preprocessor, then its compressor. Episodes of 250
    steps, the last one terminated."""
    rng = np.random.default_rng(seed)
    pre, compress = parts["obs_preprocessor"], parts["sample_compressor"]
    out: list = []
    default = np.zeros(3, np.float32)
    while len(out) < n:
        frames = rng.integers(0, 256, (250, SIDE, SIDE), dtype=np.uint8)
        hist: deque = deque([frames[0]] * HIST, maxlen=HIST)
        acts: deque = deque([default] * ACT_BUF, maxlen=ACT_BUF)
        for t in range(len(frames)):
            if len(out) >= n:
                break
            act = default if t == 0 else rng.uniform(-1, 1, 3).astype(np.float32)
            if t:
                hist.append(frames[t])
                acts.append(act)
            raw = (np.array([rng.uniform(0, 300)], np.float32), np.array([3.0], np.float32),
                   np.array([rng.uniform(0, 11000)], np.float32), np.stack(hist), *acts)
            last = t == len(frames) - 1
            out.append(compress(act, pre(raw), 0.0 if t == 0 else float(rng.uniform(0, 1)), last, False, {}))
    return out


def _arrays_held(obj: Any) -> list[np.ndarray]:
    """NumPy arrays among the memory's attributes (directly, in lists, tuples and dicts, or in the
    memory's parts: the objects of tmrl.memory's modules it is composed of), each counted once."""
    found: list[np.ndarray] = []
    seen: set[int] = set()

    def walk(x: Any) -> None:
        if id(x) in seen:
            return
        seen.add(id(x))
        if isinstance(x, np.ndarray):
            found.append(x)
        elif type(x).__module__.startswith("tmrl.memory."):
            walk(vars(x))
        elif isinstance(x, (list, tuple)):
            for y in x:
                walk(y)
        elif isinstance(x, dict):
            for y in x.values():
                walk(y)

    walk(vars(obj))
    return found


@pytest.fixture(scope="module")
def parts() -> dict[str, Any]:
    return pipeline_parts("TM20FULL")


def _filled_memory(parts: dict[str, Any], n: int) -> Any:
    memory = parts["memory_cls"](hist_len=HIST, act_buf_len=ACT_BUF, memory_size=n, batch_size=64, device="cpu")
    memory.append(_Buffer(_samples(n, parts)))
    return memory


def test_stored_sample_is_one_uint8_frame_plus_scalars(parts: dict[str, Any]) -> None:
    memory = _filled_memory(parts, N)
    batch = memory.sample()  # the memory is usable, and its sampling caches count below
    imgs = batch[0][3]
    assert tuple(imgs.shape) == (64, HIST, SIDE, SIDE)  # histories rebuilt from single frames

    arrays = _arrays_held(memory)
    frames = [a for a in arrays if a.shape[1:] == (SIDE, SIDE)]
    assert len(frames) == 1 and frames[0].dtype == np.uint8, "one uint8 frame per slot, no float history"
    assert frames[0].shape[0] == N

    per_sample = sum(a.nbytes for a in arrays) / N
    target = FRAME_BYTES + SCALAR_BYTES
    assert abs(per_sample - target) <= 0.10 * target, f"{per_sample:.0f} B per sample, target {target} B"


def test_bytes_held_per_sample_measured_by_tracemalloc(parts: dict[str, Any]) -> None:
    """Everything the memory keeps allocated (arrays, Python objects, caches), not only the
    arrays we know of, once the samples handed to it are released."""
    _filled_memory(parts, 16)  # imports and first-use allocations outside the measurement
    gc.collect()
    tracemalloc.start()
    try:
        base = tracemalloc.get_traced_memory()[0]
        memory = _filled_memory(parts, N)
        memory.sample()
        gc.collect()
        held = tracemalloc.get_traced_memory()[0] - base
    finally:
        tracemalloc.stop()
    assert len(memory) > 0
    per_sample = held / N
    target = FRAME_BYTES + SCALAR_BYTES
    assert abs(per_sample - target) <= 0.10 * target, f"{per_sample:.0f} B per sample, target {target} B"
