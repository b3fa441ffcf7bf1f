"""Trainer-side cost of received samples: from the bytes of one 1000-sample payload (the 3-float
trivial environment of bench/pipeline_throughput.py) to the replay memory's ring buffers.

    python bench/trainer_ingest.py

Prints microseconds per sample (best of ``--repeats``) for: decode and unpack only; the same plus
building the sample tuples (reading ``buffer.memory``); decode, unpack and
``GenericTorchMemory.append_buffer`` through the columns (what the trainer did before samples
were checked); the same with the run's schema check (shapes, dtypes, finite values, action
bounds: what the trainer does now); the same through the tuples (what a buffer without columns
costs).
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

import pipeline_throughput as pt  # noqa: E402  (the trivial environment and actor)

from tmrl import wire  # noqa: E402
from tmrl.memory import GenericTorchMemory  # noqa: E402
from tmrl.networking import RolloutWorker, pack_buffer, unpack_buffer  # noqa: E402
from tmrl.spaces import SampleSchema  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--samples", type=int, default=1000, help="samples per payload")
    ap.add_argument("--repeats", type=int, default=50)
    args = ap.parse_args()
    worker = RolloutWorker(
        env_cls=pt._trivial_env_cls(),
        actor_module_cls=pt._actor_cls("ours", 1),
        standalone=True,
        max_samples_per_episode=args.samples,
        model_path=os.devnull + "_none",
        model_history=0,
    )
    worker.collect_train_episode(args.samples)
    n = len(worker.buffer)
    data = wire.encode(pack_buffer(worker.buffer, 1, 0))
    memory = GenericTorchMemory(device="cpu", nb_steps=1, memory_size=1_000_000, batch_size=256)
    schema = SampleSchema(worker.env.observation_space, worker.env.action_space)

    def best_us(fn) -> float:
        best = float("inf")
        for _ in range(args.repeats):
            t = time.perf_counter()
            fn()
            best = min(best, time.perf_counter() - t)
        return best * 1e6 / n

    def through_tuples() -> None:
        buf = unpack_buffer(wire.decode(data))
        buf.memory  # noqa: B018  (builds the tuples)
        memory.append_buffer(buf)

    rows = [
        ("decode + unpack", lambda: unpack_buffer(wire.decode(data))),
        ("decode + unpack + tuples", lambda: unpack_buffer(wire.decode(data)).memory),
        ("decode + unpack + append_buffer (columns)", lambda: memory.append_buffer(unpack_buffer(wire.decode(data)))),
        (
            "decode + unpack + check + append_buffer",
            lambda: memory.append_buffer(unpack_buffer(wire.decode(data), schema=schema)),
        ),
        ("decode + unpack + append_buffer (tuples)", through_tuples),
    ]
    print(f"{n} samples per payload, {len(data) / n:.1f} bytes/sample, best of {args.repeats}")
    for name, fn in rows:
        print(f"{name:45} {best_us(fn):6.3f} µs/sample")


if __name__ == "__main__":
    main()
