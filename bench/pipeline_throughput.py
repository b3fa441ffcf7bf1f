"""Throughput of the distributed pipeline, ours beside tmrl 0.7.1: samples per second reaching the
trainer, bytes per sample on the wire, the trainer's memory, and weight-broadcast latency.

    python -m bench pipeline_throughput                       # 3 rounds, 15 s per measurement
    python -m bench pipeline_throughput --duration 60 --skip-broadcast

- samples per second reaching the trainer with 1, 2 and 4 workers on a trivial environment
  (3-float observations, a constant policy, 1000-step episodes, each sent when it ends);
- bytes per sample on the wire for that observation (one 1000-sample episode);
- the trainer's memory (PSS of the trainer process and its network children) at the end of the
  run with the most workers;
- weight broadcast latency (the trainer's ``broadcast_model`` call to the worker having loaded
  them) for 1M and 20M parameter actors (the original's 20M case takes minutes).

Every process is separate (server, trainer, workers), on 127.0.0.1, plain TCP on both sides (the
original's default); rounds alternate the order of the sides.
"""

from __future__ import annotations

import argparse
import os
import shutil
import statistics
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from bench import harness

PASSWORD = "bench-password"
EPISODE = 1000


# ------------------------------------------------------------------------------------------------
# pieces used inside the role processes (both implementations)


def _trivial_env_cls():
    import gymnasium
    import numpy as np

    class Trivial(gymnasium.Env):
        observation_space = gymnasium.spaces.Box(-1.0, 1.0, (3,), np.float32)
        action_space = gymnasium.spaces.Box(-1.0, 1.0, (1,), np.float32)

        def __init__(self):
            self._obs = np.zeros(3, np.float32)

        def reset(self, *, seed=None, options=None):
            return self._obs.copy(), {}

        def step(self, action):
            return self._obs.copy(), 0.0, False, False, {}

    return Trivial


def _actor_cls(impl: str, n_params: int):
    import numpy as np
    import torch

    from tmrl.actor import TorchActorModule  # the same module path on both sides

    class Actor(TorchActorModule):
        def __init__(self, observation_space, action_space, *args, **kwargs):
            super().__init__(observation_space, action_space)
            self.w = torch.nn.Parameter(torch.zeros(max(1, n_params)))
            self._act = np.zeros(action_space.shape, np.float32)

        def act_(self, obs, test=False):
            return self._act

        def act(self, obs, test=False):
            return self._act

    return Actor


def _rss_tree(pid: int) -> int:
    """Memory in bytes of ``pid`` and all its descendants: the sum of their PSS (proportional set
    size: pages shared between a process and its forked children are counted once). Linux only."""
    if not sys.platform.startswith("linux"):
        raise RuntimeError("bench pipeline_throughput measures memory from /proc: it needs Linux")
    total = 0
    todo = [pid]
    while todo:
        p = todo.pop()
        try:
            with open(f"/proc/{p}/smaps_rollup") as f:
                for line in f:
                    if line.startswith("Pss:"):
                        total += int(line.split()[1]) * 1024
            with open(f"/proc/{p}/task/{p}/children") as f:
                todo += [int(c) for c in f.read().split()]
        except OSError:
            pass
    return total


def role_server(impl: str, port: int) -> None:
    from tmrl.networking import Server

    server = Server(port=port, password=PASSWORD, security=None, max_workers=None)  # noqa: F841 (kept alive)
    while True:
        time.sleep(1.0)


def _trainer_interface(impl: str, port: int, workdir: Path):
    from tmrl.networking import TrainerInterface

    return TrainerInterface(
        server_ip="127.0.0.1",
        server_port=port,
        password=PASSWORD,
        security=None,
        model_path=str(workdir / "model_trainer.tmod"),
    )


def _first_weights(impl: str, iface: Any) -> None:
    """Broadcast an actor's initial weights once, as a trainer does when it starts: our workers
    wait for the trainer's first weights after their first episode (tmrl 0.7.1's do not wait, and
    load them as they would any)."""
    import gymnasium
    import numpy as np

    actor = _actor_cls(impl, 1)(gymnasium.spaces.Box(-1.0, 1.0, (3,), np.float32),
                                gymnasium.spaces.Box(-1.0, 1.0, (1,), np.float32))
    iface.broadcast_model(actor)


def role_sink(
    impl: str,
    port: int,
    workdir: Path,
    warmup: float,
    duration: float,
    cost_us: float = 0.0,
    into_memory: bool = False,
) -> None:
    """Trainer side of the throughput run: retrieve as fast as possible, count samples. With
    ``cost_us``, each retrieved sample then costs that many microseconds (a trainer that cannot
    keep up with the workers), which shows where the backlog piles up. With ``into_memory``, each
    retrieved buffer is also stored in the implementation's own replay memory (its
    GenericTorchMemory, 1M samples), as its trainer does between training steps."""
    iface = _trainer_interface(impl, port, workdir)
    _first_weights(impl, iface)
    memory = None
    if into_memory:
        if impl != "tmrl":  # ours, or an earlier checkout of ours (--before)
            from tmrl.memory import GenericTorchMemory

            memory = GenericTorchMemory(device="cpu", nb_steps=1, memory_size=1_000_000, batch_size=256)
        else:
            from tmrl.custom.custom_memories import GenericTorchMemory

            memory = GenericTorchMemory(memory_size=1e6, batch_size=256, nb_steps=1, device="cpu")
    t_first = t_measure = None
    count, next_rss = 0, 0.0
    while True:
        buf = iface.retrieve_buffer()
        n = len(buf)
        if memory is not None and n:
            memory.append(buf)
        del buf
        if n and cost_us:
            time.sleep(n * cost_us * 1e-6)
        now = time.monotonic()
        if t_first is None and n:
            t_first = now
        if t_measure is None:
            if t_first is not None and now - t_first >= warmup:
                t_measure = next_rss = now
        else:
            count += n
            if now >= next_rss:
                harness.print_json({"rss": _rss_tree(os.getpid()), "t": now - t_measure})
                next_rss += 5.0
            if now - t_measure >= duration:
                harness.print_json({"samples_per_s": count / (now - t_measure), "rss_end": _rss_tree(os.getpid())})
                break
        if not n:
            time.sleep(0.001)
    os._exit(0)


def role_worker(impl: str, port: int, workdir: Path) -> None:
    from tmrl.networking import RolloutWorker

    w = RolloutWorker(
        env_cls=_trivial_env_cls(),
        actor_module_cls=_actor_cls(impl, 1),
        server_ip="127.0.0.1",
        server_port=port,
        password=PASSWORD,
        security=None,
        max_samples_per_episode=EPISODE,
        model_path=str(workdir / f"model_worker_{os.getpid()}.tmod"),
        model_history=0,
    )
    w.run(test_episode_interval=0, verbose=False)


def role_bytes(impl: str) -> None:
    """Bytes per sample of one 1000-sample episode, as each implementation serializes it."""
    from tmrl.networking import RolloutWorker

    w = RolloutWorker(
        env_cls=_trivial_env_cls(),
        actor_module_cls=_actor_cls(impl, 1),
        standalone=True,
        max_samples_per_episode=EPISODE - 1,
        model_path=os.devnull + "_none",
        model_history=0,
    )
    w.collect_train_episode(EPISODE - 1)
    n = len(w.buffer)
    if impl != "tmrl":  # ours, or an earlier checkout of ours (--before)
        from tmrl import wire
        from tmrl.networking import pack_buffer

        size = len(wire.encode(pack_buffer(w.buffer, w.source_id, 0)))
    else:
        import pickle

        size = len(pickle.dumps(w.buffer))  # tlspyo's default serializer, as the original sends it
    harness.print_json({"bytes_per_sample": size / n, "samples": n})


def role_bcast_trainer(impl: str, port: int, workdir: Path, n_params: int, repeats: int) -> None:
    import gymnasium
    import numpy as np

    iface = _trainer_interface(impl, port, workdir)
    actor = _actor_cls(impl, n_params)(
        gymnasium.spaces.Box(-1, 1, (3,), np.float32), gymnasium.spaces.Box(-1, 1, (1,), np.float32)
    )
    ack = workdir / "ack"
    for i in range(repeats):
        while not ack.exists() or int(ack.read_text() or -1) != i:
            time.sleep(0.01)
        t = time.monotonic()
        harness.print_json({"sent": i, "t": t})
        iface.broadcast_model(actor)
    time.sleep(1.0)
    while True:  # keep the link open until the driver stops us
        time.sleep(1.0)


def role_bcast_worker(impl: str, port: int, workdir: Path, n_params: int, repeats: int) -> None:
    from tmrl.networking import RolloutWorker

    w = RolloutWorker(
        env_cls=_trivial_env_cls(),
        actor_module_cls=_actor_cls(impl, n_params),
        server_ip="127.0.0.1",
        server_port=port,
        password=PASSWORD,
        security=None,
        model_path=str(workdir / "model_worker.tmod"),
        model_history=0,
    )
    ack = workdir / "ack"
    time.sleep(2.0)  # why: let the link connect before the first broadcast (the original cannot tell)
    for i in range(repeats):
        tmp = workdir / "ack.tmp"
        tmp.write_text(str(i))
        os.replace(tmp, ack)
        while w.update_actor_weights(verbose=False, blocking=True) == 0:
            pass
        harness.print_json({"loaded": i, "t": time.monotonic()})
    while True:
        time.sleep(1.0)


# ------------------------------------------------------------------------------------------------
# child entry


def child_main(argv: list[str]) -> None:
    """One role: ``--impl ours|tmrl --role NAME [ARGS...]``."""
    ap = argparse.ArgumentParser()
    ap.add_argument("--impl", required=True)
    ap.add_argument("--port", type=int, default=0)
    ap.add_argument("--workdir", required=True)
    ap.add_argument("--role", nargs="+", required=True)
    args = ap.parse_args(argv)
    role, *rest = args.role
    wd = Path(args.workdir)
    if role == "server":
        role_server(args.impl, args.port)
    elif role == "sink":
        role_sink(args.impl, args.port, wd, float(rest[0]), float(rest[1]), float(rest[2]), rest[3] == "1")
    elif role == "worker":
        role_worker(args.impl, args.port, wd)
    elif role == "bytes":
        role_bytes(args.impl)
    elif role == "bcast_trainer":
        role_bcast_trainer(args.impl, args.port, wd, int(rest[0]), int(rest[1]))
    elif role == "bcast_worker":
        role_bcast_worker(args.impl, args.port, wd, int(rest[0]), int(rest[1]))


# ------------------------------------------------------------------------------------------------
# driver


class Run:
    """The processes of one measurement, in a work folder; all stopped (with their children) at
    the end."""

    def __init__(self, side: harness.Side) -> None:
        self.side = side
        self.workdir = Path(tempfile.mkdtemp(prefix=f"throughput-{side.name}-"))
        self.port = harness.free_port()
        self.env = dict(side.env, OMP_NUM_THREADS="1", PYTHONUNBUFFERED="1")
        if side.name == "ours":
            self.env["TMRL_DATA"] = str(self.workdir / "TmrlData")
        self.procs: list = []

    def start(self, *role: str, pipe: bool = False):
        cmd = self.side.command("pipeline_throughput", "--impl", self.side.name, "--port", str(self.port),
                                "--workdir", str(self.workdir), "--role", *role)
        p = harness.start_group(cmd, self.side, self.workdir / f"{role[0]}-{len(self.procs)}.log",
                                stdout=-1 if pipe else None, env=self.env, cwd=str(self.workdir))
        self.procs.append(p)
        return p

    def __enter__(self) -> Run:
        return self

    def __exit__(self, *exc: object) -> None:
        harness.stop_groups(self.procs, grace=5.0)
        shutil.rmtree(self.workdir, ignore_errors=True)


def measure_throughput(side: harness.Side, workers: int, warmup: float, duration: float, cost_us: float,
                       into_memory: bool) -> dict:
    with Run(side) as run:
        run.start("server")
        harness.wait_listening(run.port, 60.0)
        sink = run.start("sink", str(warmup), str(duration), str(cost_us), str(int(into_memory)), pipe=True)
        for _ in range(workers):
            run.start("worker")
        res: dict = {"rss": []}
        for rec in harness.JsonLines(sink).wait(warmup + duration + 120):
            if "rss" in rec:
                res["rss"].append(rec["rss"])
            else:
                res.update(rec)
                break
        return res


def measure_bytes(side: harness.Side) -> float | None:
    with Run(side) as run:
        for rec in harness.JsonLines(run.start("bytes", pipe=True)).wait(120):
            return rec["bytes_per_sample"]
    return None


def measure_broadcast(side: harness.Side, n_params: int, repeats: int, timeout: float) -> float | None:
    with Run(side) as run:
        run.start("server")
        harness.wait_listening(run.port, 60.0)
        trainer = harness.JsonLines(run.start("bcast_trainer", str(n_params), str(repeats), pipe=True))
        worker = run.start("bcast_worker", str(n_params), str(repeats), pipe=True)
        sent: dict[int, float] = {}
        latencies = []
        for rec in harness.JsonLines(worker).wait(timeout):
            sent.update((r["sent"], r["t"]) for r in trainer.poll())
            if "loaded" in rec and rec["loaded"] in sent:
                latencies.append(rec["t"] - sent[rec["loaded"]])
                if len(latencies) == repeats:
                    break
        return statistics.median(latencies) if latencies else None


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(prog="python -m bench pipeline_throughput", description=__doc__.split("\n\n")[0])
    ap.add_argument("--rounds", type=int, default=3, help="rounds (sides alternate their order)")
    ap.add_argument("--duration", type=float, default=15.0, help="measured seconds per throughput run")
    ap.add_argument("--warmup", type=float, default=3.0)
    ap.add_argument("--workers", default="1,2,4")
    ap.add_argument("--params", default="1000000,20000000", help="actor sizes for the broadcast latency")
    ap.add_argument("--repeats", type=int, default=3, help="broadcasts per latency measurement (median)")
    ap.add_argument("--broadcast-timeout", type=float, default=400.0)
    ap.add_argument("--skip-broadcast", action="store_true")
    ap.add_argument("--sink-cost-us", type=float, default=0.0,
                    help="microseconds of work per retrieved sample at the trainer (a trainer slower than the workers)")
    ap.add_argument("--sink-memory", action="store_true",
                    help="the trainer side also stores every retrieved buffer in its replay memory")
    harness.add_side_arguments(ap, tmrl=True)
    args = ap.parse_args(argv)
    ks = [int(x) for x in args.workers.split(",")]
    params = [] if args.skip_broadcast else [int(x) for x in args.params.split(",")]
    rec = harness.Recorder("pipeline_throughput", {
        "workers": ks, "duration_s": args.duration, "warmup_s": args.warmup, "episode": EPISODE,
        "transport": "plain TCP on 127.0.0.1", "sink_cost_us": args.sink_cost_us, "sink_memory": args.sink_memory,
        "broadcast_params": params, "rounds": args.rounds})
    for rnd, side in harness.alternate(harness.sides_from_args(args), args.rounds):
        rec.add("one episode on the wire", "bytes_per_sample", side.name, measure_bytes(side), round=rnd,
                higher_is_better=False, unit="B")
        for k in ks:
            res = measure_throughput(side, k, args.warmup, args.duration, args.sink_cost_us, args.sink_memory)
            rec.add(f"{k} worker(s)", "samples_per_s", side.name, res.get("samples_per_s"), round=rnd, unit="1/s",
                    rss_series=res["rss"])
            if k == max(ks):
                end = res.get("rss_end")
                rec.add(f"{k} worker(s)", "trainer_pss_mib", side.name, end / 2**20 if end else None, round=rnd,
                        higher_is_better=False, unit="MiB")
        for n in params:
            lat = measure_broadcast(side, n, args.repeats, args.broadcast_timeout)
            rec.add(f"broadcast {n / 1e6:g}M params", "latency_s", side.name, lat, round=rnd,
                    higher_is_better=False, unit="s")
    rec.print_table()
    rec.close()
