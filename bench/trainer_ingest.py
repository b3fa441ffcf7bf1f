"""Trainer-side cost of received samples (ours): from the bytes of one 1000-sample payload (the
3-float trivial environment of ``pipeline_throughput``) to the replay memory's ring buffers.

    python -m bench trainer_ingest [--repeats 50] [--rounds 3]

Microseconds per sample (best of ``--repeats`` per round; medians over rounds) for: decode and
unpack only; the same plus building the sample tuples (reading ``buffer.memory``); decode, unpack
and ``GenericTorchMemory.append_buffer`` through the columns (without the run's schema check);
the same with the schema check (shapes, dtypes, finite values, action bounds: what the trainer
does); the same through the tuples (what a buffer without columns costs).
"""

from __future__ import annotations

import argparse
import os
import time
from collections.abc import Callable

from bench import harness
from bench.pipeline_throughput import _actor_cls, _trivial_env_cls


def one_round(args: argparse.Namespace, rnd: int, rec: harness.Recorder) -> None:
    from tmrl import wire
    from tmrl.memory import GenericTorchMemory
    from tmrl.networking import RolloutWorker, pack_buffer, unpack_buffer
    from tmrl.spaces import SampleSchema

    worker = RolloutWorker(env_cls=_trivial_env_cls(), actor_module_cls=_actor_cls("ours", 1), standalone=True,
                           max_samples_per_episode=args.samples, model_path=os.devnull + "_none", model_history=0)
    worker.collect_train_episode(args.samples)
    n = len(worker.buffer)
    data = wire.encode(pack_buffer(worker.buffer, 1, 0))
    memory = GenericTorchMemory(device="cpu", nb_steps=1, memory_size=1_000_000, batch_size=256)
    schema = SampleSchema(worker.env.observation_space, worker.env.action_space)

    def best_us(fn: Callable[[], object]) -> float:
        best = float("inf")
        for _ in range(args.repeats):
            t = time.perf_counter()
            fn()
            best = min(best, time.perf_counter() - t)
        return best * 1e6 / n

    def through_tuples() -> None:
        buf = unpack_buffer(wire.decode(data))
        buf.memory  # noqa: B018 (builds the tuples)
        memory.append_buffer(buf)

    case = f"{n} samples per payload, {len(data) / n:.1f} B/sample"
    for name, fn in (
        ("decode + unpack", lambda: unpack_buffer(wire.decode(data))),
        ("decode + unpack + tuples", lambda: unpack_buffer(wire.decode(data)).memory),
        ("decode + unpack + append_buffer (columns)", lambda: memory.append_buffer(unpack_buffer(wire.decode(data)))),
        (
            "decode + unpack + check + append_buffer",
            lambda: memory.append_buffer(unpack_buffer(wire.decode(data), schema=schema)),
        ),
        ("decode + unpack + append_buffer (tuples)", through_tuples),
    ):
        rec.add(case, name, "ours", best_us(fn), round=rnd, higher_is_better=False, unit="us/sample")


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(prog="python -m bench trainer_ingest", description=__doc__.split("\n\n")[0])
    ap.add_argument("--samples", type=int, default=1000, help="samples per payload")
    ap.add_argument("--repeats", type=int, default=50)
    ap.add_argument("--rounds", type=int, default=3)
    args = ap.parse_args(argv)
    rec = harness.Recorder("trainer_ingest", vars(args))
    for rnd in range(args.rounds):
        one_round(args, rnd, rec)
    rec.print_table(ratios=())
    rec.close()
