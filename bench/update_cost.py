"""Compute per environment step: the measured time of one update of each ``track_learning``
variant on this CPU, times its updates per step, beside ``REDQSAC-UTD8-CAP-R250``.

    python -m bench update_cost                                   # the default variants, 5 rounds
    python -m bench update_cost --agents BRO-UTD4-CAP-R250,REDQSAC-UTD8-CAP-R250 --rounds 3

One process, one torch thread (as ``track_learning`` and the demo's trainer). Each variant's agent
is built as :func:`bench.track_learning._agent` builds it (same model, same settings) on the
simulator's lidar spaces; its batches of 256 come from a replay memory filled with 2,000 samples
of a random driver on ``classic`` through a real ``RolloutWorker``. A round times ``--updates``
consecutive updates of every variant (a multiple of 6, so that CrossQ's policy every third update
and the other agents' own rhythms count in their share), in ABBA order over the rounds so that a
drift of the machine's load favours none; the first updates of each agent (warm-up) are not
timed. Printed per variant: ms per update, median [min..max] over the rounds; updates per step
(the variant's ratio); ms per environment step (their product, from the medians); that against
``REDQSAC-UTD8-CAP-R250``'s; the load average before and after, and the processor. A record goes
to bench/out/update_cost-<stamp>.jsonl.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import time
from pathlib import Path
from typing import Any

from bench import harness

REFERENCE = "REDQSAC-UTD8-CAP-R250"

DEFAULT_AGENTS = ("BRO-W128-UTD8-CAP-R250", "BRO-W128-UTD4-CAP-R250", "BRO-UTD4-CAP-R250", "SIMBAV2-UTD4-CAP-R250",
                  REFERENCE, "SAC-UTD4-FA",
                  "SAC-TMRL", "CROSSQ")


def _filled_memory(batch_size: int, samples: int) -> tuple[Any, tuple[Any, Any]]:
    """A replay memory of ``samples`` random-driver samples on ``classic`` and the spaces."""
    from bench.pendulum_learning import _parts, _UniformActor
    from tmrl.networking import RolloutWorker

    p = _parts("simlidar", batch_size, 10 * samples, track="classic")
    worker = RolloutWorker(env_cls=p["env_cls"], actor_module_cls=p["actor_cls"], standalone=True, model_history=0,
                           max_samples_per_episode=p["max_samples"], model_path=os.devnull + "_none", **p["worker"])
    worker.env.action_space.seed(0)
    worker.actor = _UniformActor(worker.env.action_space)
    memory = p["memory"]
    obs, _ = worker.reset(collect_samples=True)
    for step in range(1, samples + 1):
        obs, _, terminated, truncated, _ = worker.step(obs, test=False, collect_samples=True,
                                                       last_step=step % p["max_samples"] == 0)
        if terminated or truncated:
            obs, _ = worker.reset(collect_samples=True)
        if step % 100 == 0:
            memory.append(worker.buffer)
            worker.buffer.clear()
    return memory, (worker.env.observation_space, worker.env.action_space)


def main(argv: list[str] | None = None) -> None:
    """Time each variant's update; print the table and write the record."""
    ap = argparse.ArgumentParser(prog="python -m bench update_cost", description=__doc__.split("\n\n")[0])
    ap.add_argument("--agents", default=",".join(DEFAULT_AGENTS), help="comma-separated track_learning variants")
    ap.add_argument("--rounds", type=int, default=5)
    ap.add_argument("--updates", type=int, default=60, help="updates timed per variant and round (a multiple of 6)")
    ap.add_argument("--warmup", type=int, default=12, help="untimed updates of each agent first")
    ap.add_argument("--batch-size", type=int, default=256)
    args = ap.parse_args(argv)
    import numpy as np
    import torch

    from bench.track_learning import VARIANTS, _agent, utd_of

    labels = [s.strip() for s in args.agents.split(",") if s.strip()]
    unknown = [lab for lab in labels if lab not in VARIANTS]
    if unknown:
        sys.exit(f"update_cost: unknown variant(s) {', '.join(unknown)}: use track_learning's ({', '.join(VARIANTS)})")
    if REFERENCE not in labels:
        labels.append(REFERENCE)
    if args.updates < 1 or args.rounds < 1:
        sys.exit("update_cost: --updates and --rounds must be at least 1")
    torch.set_num_threads(1)
    torch.manual_seed(0)
    np.random.seed(0)
    load_before = harness.load_averages()
    memory, spaces = _filled_memory(args.batch_size, 2_000)
    agents = {lab: _agent(lab, spaces, "classic", utd_of(lab)) for lab in labels}
    for agent in agents.values():
        for _ in range(args.warmup):
            agent.train(memory.sample())
    times: dict[str, list[float]] = {lab: [] for lab in labels}
    for rnd, lab in harness.alternate(labels, args.rounds):
        agent = agents[lab]
        batches = [memory.sample() for _ in range(args.updates)]
        start = time.perf_counter()
        for batch in batches:
            agent.train(batch)
        times[lab].append(1000.0 * (time.perf_counter() - start) / args.updates)
        print(f"  round {rnd}: {lab:<26s} {times[lab][-1]:7.2f} ms/update", file=sys.stderr, flush=True)
    load_after = harness.load_averages()
    install = harness.install()
    rows = []
    for lab in labels:
        med = statistics.median(times[lab])
        rows.append({"agent": lab, "ms_per_update": med, "min": min(times[lab]), "max": max(times[lab]),
                     "updates_per_step": utd_of(lab), "ms_per_step": med * utd_of(lab), "rounds": times[lab]})
    ref = next(r["ms_per_step"] for r in rows if r["agent"] == REFERENCE)
    print(f"update_cost: {args.rounds} rounds of {args.updates} updates, batch {args.batch_size}, one torch thread; "
          f"processor {install['cpu']}; load {load_before[0]:.2f} before, {load_after[0]:.2f} after")
    print(f"{'agent':<26s} {'ms/update, median [min..max]':>30s} {'upd/step':>9s} {'ms/step':>9s} "
          f"{'vs ' + REFERENCE:>28s}")
    for r in rows:
        span = f"{r['ms_per_update']:.2f} [{r['min']:.2f}..{r['max']:.2f}]"
        print(f"{r['agent']:<26s} {span:>30s} {r['updates_per_step']:>9d} {r['ms_per_step']:>9.1f} "
              f"{r['ms_per_step'] / ref:>28.2f}")
    out = Path(__file__).resolve().parent / "out"
    out.mkdir(exist_ok=True)
    path = out / f"update_cost-{time.strftime('%Y%m%d-%H%M%S')}.jsonl"
    with path.open("w", encoding="utf-8") as f:
        f.write(json.dumps({"settings": vars(args), "install": install, "load_before": load_before,
                            "load_after": load_after}) + "\n")
        for r in rows:
            f.write(json.dumps(r) + "\n")
    print(f"record: {path}")


if __name__ == "__main__":
    main()
