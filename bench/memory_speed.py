"""Replay-memory speed: append throughput, sample() time for a batch, checkpoint time of a big
memory (first save, incremental save, load).

Run: ``python bench/memory_speed.py`` (1M samples; ``--size`` to change, ``--act-buf-len 0`` for
GenericTorchMemory). Observations look like the lidar driving environment: speed (1,), lidar
history (4, 19) float32, then an action buffer rebuilt by RealTimeTorchMemory.
Needs about 1 GB of RAM and disk per million samples. Prints figures; asserts nothing.
"""

from __future__ import annotations

import argparse
import os
import shutil
import tempfile
import time
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import torch

from tmrl.checkpoint import load_checkpoint, save_checkpoint
from tmrl.memory import GenericTorchMemory, RealTimeTorchMemory


class Buf:
    def __init__(self, samples):
        self.memory = samples
        self.sources = None
        self.stat_train_return = self.stat_test_return = 0.0
        self.stat_train_steps = self.stat_test_steps = 0

    def __len__(self):
        return len(self.memory)


def make_samples(n: int, start: int, rng: np.random.Generator, episode_len: int = 1000) -> list[tuple]:
    speeds = rng.random((n, 1), dtype=np.float32)
    lidars = rng.random((n, 4, 19), dtype=np.float32)
    acts = rng.uniform(-1, 1, (n, 3)).astype(np.float32)
    out = []
    for k in range(n):
        t = (start + k) % episode_len
        out.append((acts[k], (speeds[k], lidars[k]), float(t), t == episode_len - 1, False, {}))
    return out


class TinyAgent:
    def __init__(self):
        self.model = torch.nn.Linear(100, 3)
        self.optimizer = torch.optim.Adam(self.model.parameters())

    def state_dict(self):
        return {"model": self.model.state_dict(), "optimizer": self.optimizer.state_dict()}

    def load_state_dict(self, state):
        self.model.load_state_dict(state["model"])
        self.optimizer.load_state_dict(state["optimizer"])


def timed(fn, repeat: int = 1) -> float:
    t0 = time.perf_counter()
    for _ in range(repeat):
        fn()
    return (time.perf_counter() - t0) / repeat


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--size", type=int, default=1_000_000, help="samples in the memory")
    parser.add_argument("--batch-size", type=int, default=256)
    parser.add_argument("--act-buf-len", type=int, default=2, help="0: GenericTorchMemory")
    parser.add_argument("--folder", default=None, help="checkpoint folder (default: a temporary one)")
    args = parser.parse_args()
    torch.set_num_threads(1)
    rng = np.random.default_rng(0)

    def make_memory():
        if args.act_buf_len > 0:
            return RealTimeTorchMemory(act_buf_len=args.act_buf_len, memory_size=args.size, batch_size=args.batch_size)
        return GenericTorchMemory(memory_size=args.size, batch_size=args.batch_size)

    memory = make_memory()
    print(f"load average: {os.getloadavg()[0]:.2f} {os.getloadavg()[1]:.2f} (1, 5 min), {os.cpu_count()} CPUs")
    print(f"{type(memory).__name__}, memory_size={args.size}, batch_size={args.batch_size}")

    chunk = 50_000
    append_time = make_time = 0.0
    for start in range(0, args.size, chunk):
        n = min(chunk, args.size - start)
        t0 = time.perf_counter()
        buf = Buf(make_samples(n, start, rng))
        t1 = time.perf_counter()
        memory.append(buf)
        make_time += t1 - t0
        append_time += time.perf_counter() - t1
    print(f"append: {args.size / append_time:,.0f} samples/s ({append_time:.1f} s for {args.size:,} samples)")

    memory.sample()  # warm-up (valid-index cache)
    fast = timed(memory.sample, repeat=200)
    indices = memory.sample_indices()
    slow = timed(lambda: super(GenericTorchMemory, memory).sample(indices), repeat=5)
    print(f"sample() batch {args.batch_size}: {fast * 1e3:.2f} ms (fast path); per-item slow path: {slow * 1e3:.1f} ms")

    folder = Path(args.folder) if args.folder else Path(tempfile.mkdtemp(prefix="tmrl-bench-"))
    target = folder / "ckpt"
    training = SimpleNamespace(agent=TinyAgent(), memory=memory, epoch=1, total_updates=0, total_samples=args.size)
    try:
        first = timed(lambda: save_checkpoint(training, target))
        size = sum(p.stat().st_size for p in target.iterdir()) / 1e6
        print(f"checkpoint, first save: {first:.2f} s ({size:,.0f} MB on disk)")
        new = 10_000
        memory.append(Buf(make_samples(new, args.size, rng)))
        training.epoch = 2
        incremental = timed(lambda: save_checkpoint(training, target))
        print(f"checkpoint, incremental save after {new:,} new samples: {incremental * 1e3:.0f} ms")
        restored = SimpleNamespace(agent=TinyAgent(), memory=make_memory(), epoch=0, total_updates=0, total_samples=0,
                                   run_epoch=None)
        load = timed(lambda: load_checkpoint(target, restored))
        assert restored.memory.total == memory.total
        print(f"checkpoint load: {load:.2f} s")
    finally:
        if not args.folder:
            shutil.rmtree(folder, ignore_errors=True)


if __name__ == "__main__":
    main()
