"""Throughput of the distributed pipeline, this tmrl beside the original tmrl 0.7.1:

- samples per second reaching the trainer with 1, 2 and 4 workers on a trivial environment
  (3-float observations, a constant policy, 1000-step episodes, each sent when it ends);
- bytes per sample on the wire for that 3-float observation (one 1000-sample episode);
- the trainer's memory (RSS of the trainer process and its network children) during and at the
  end of the 4-worker run (``--duration`` seconds; the issue's figure uses 60);
- weight broadcast latency (trainer's ``broadcast_model`` call to the worker having loaded them)
  for 1M and 20M parameter actors.

    python bench/pipeline_throughput.py                      # both, default 15 s per run
    python bench/pipeline_throughput.py --duration 60 --impl ours
    python bench/pipeline_throughput.py --skip-broadcast     # the original's 20M case takes minutes

Every process is separate (server, trainer, workers), on 127.0.0.1, plain TCP for both (the
original's default). The figures depend on the machine's load: ``uptime`` is printed with them.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import signal
import socket
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

HERE = Path(__file__).resolve()
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

    if impl == "ours":
        from tmrl.actor import TorchActorModule
    else:
        from tmrl.actor import TorchActorModule

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
    size: pages shared between a process and its forked children are counted once)."""
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


def _out(obj: dict) -> None:
    print(json.dumps(obj), flush=True)


def role_server(impl: str, port: int) -> None:
    if impl == "ours":
        from tmrl.networking import Server

        server = Server(port=port, password=PASSWORD, security=None, max_workers=None)
        try:
            while True:
                time.sleep(1.0)
        finally:
            server.stop()
    else:
        from tmrl.networking import Server

        server = Server(port=port, password=PASSWORD, security=None, max_workers=None)
        while True:
            time.sleep(1.0)


def _trainer_interface(impl: str, port: int, workdir: Path):
    if impl == "ours":
        from tmrl.networking import TrainerInterface

        return TrainerInterface(
            server_ip="127.0.0.1",
            server_port=port,
            password=PASSWORD,
            security=None,
            model_path=str(workdir / "model_trainer.tmod"),
        )
    from tmrl.networking import TrainerInterface

    return TrainerInterface(
        server_ip="127.0.0.1",
        server_port=port,
        password=PASSWORD,
        security=None,
        model_path=str(workdir / "model_trainer.tmod"),
    )


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
    memory = None
    if into_memory:
        if impl == "ours":
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
                _out({"rss": _rss_tree(os.getpid()), "t": now - t_measure})
                next_rss += 5.0
            if now - t_measure >= duration:
                _out({"samples_per_s": count / (now - t_measure), "rss_end": _rss_tree(os.getpid())})
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
    if impl == "ours":
        from tmrl import wire
        from tmrl.networking import pack_buffer

        size = len(wire.encode(pack_buffer(w.buffer, w.source_id, 0)))
    else:
        import pickle

        size = len(pickle.dumps(w.buffer))  # tlspyo's default serializer, as the original sends it
    _out({"bytes_per_sample": size / n, "samples": n})


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
        _out({"sent": i, "t": t})
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
        _out({"loaded": i, "t": time.monotonic()})
    while True:
        time.sleep(1.0)


# ------------------------------------------------------------------------------------------------
# driver


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class Run:
    """Processes of one measurement; stopped (with their children) at the end."""

    def __init__(self, impl: str, python: str, home: str | None):
        self.impl, self.python = impl, python
        self.workdir = Path(tempfile.mkdtemp(prefix=f"throughput-{impl}-"))
        self.port = _free_port()
        self.env = dict(os.environ, OMP_NUM_THREADS="1", PYTHONUNBUFFERED="1")
        if home:
            self.env["HOME"] = home
        else:
            self.env["TMRL_DATA"] = str(self.workdir / "TmrlData")
        self.procs: list[subprocess.Popen] = []

    def start(self, *role_args: str, pipe: bool = False) -> subprocess.Popen:
        log = open(self.workdir / f"{role_args[0]}-{len(self.procs)}.log", "wb")
        p = subprocess.Popen(
            [
                self.python,
                str(HERE),
                "--impl",
                self.impl,
                "--port",
                str(self.port),
                "--workdir",
                str(self.workdir),
                "--role",
                *role_args,
            ],
            cwd=str(self.workdir),
            env=self.env,
            stdout=subprocess.PIPE if pipe else log,
            stderr=log,
            start_new_session=True,
        )
        self.procs.append(p)
        return p

    def wait_listening(self, timeout: float = 60.0) -> None:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            try:
                with socket.create_connection(("127.0.0.1", self.port), timeout=0.5):
                    return
            except OSError:
                time.sleep(0.1)
        raise RuntimeError(f"server did not listen (see {self.workdir})")

    def stop(self, keep: bool = False) -> None:
        for p in self.procs:
            if p.poll() is None:
                p.send_signal(signal.SIGINT)
        deadline = time.monotonic() + 5
        for p in self.procs:
            try:
                p.wait(max(0.1, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                pass
            try:
                os.killpg(p.pid, signal.SIGKILL)
            except ProcessLookupError:
                pass
            p.wait()
        if not keep:
            shutil.rmtree(self.workdir, ignore_errors=True)


def _lines(p: subprocess.Popen, timeout: float):
    deadline = time.monotonic() + timeout
    os.set_blocking(p.stdout.fileno(), False)
    pending = b""
    while time.monotonic() < deadline:
        chunk = p.stdout.read() or b""
        pending += chunk
        *lines, pending = pending.split(b"\n")
        for line in lines:
            if line.startswith(b"{"):  # the original prints other lines on stdout
                yield json.loads(line)
        if p.poll() is not None and not chunk:
            return
        time.sleep(0.05)


def measure_throughput(
    impl: str,
    python: str,
    home: str | None,
    workers: int,
    warmup: float,
    duration: float,
    keep: bool,
    cost_us: float = 0.0,
    into_memory: bool = False,
) -> dict:
    run = Run(impl, python, home)
    try:
        run.start("server")
        run.wait_listening()
        sink = run.start("sink", str(warmup), str(duration), str(cost_us), str(int(into_memory)), pipe=True)
        for _ in range(workers):
            run.start("worker")
        res: dict = {"rss": []}
        for rec in _lines(sink, warmup + duration + 120):
            if "rss" in rec:
                res["rss"].append(rec["rss"])
            else:
                res.update(rec)
                break
        return res
    finally:
        run.stop(keep)


def measure_bytes(impl: str, python: str, home: str | None) -> float | None:
    run = Run(impl, python, home)
    try:
        p = run.start("bytes", pipe=True)
        for rec in _lines(p, 120):
            return rec["bytes_per_sample"]
    finally:
        run.stop()
    return None


def measure_broadcast(
    impl: str, python: str, home: str | None, n_params: int, repeats: int, timeout: float
) -> float | None:
    run = Run(impl, python, home)
    try:
        run.start("server")
        run.wait_listening()
        tr = run.start("bcast_trainer", str(n_params), str(repeats), pipe=True)
        wk = run.start("bcast_worker", str(n_params), str(repeats), pipe=True)
        sent, lat = {}, []
        os.set_blocking(tr.stdout.fileno(), False)
        gen = _lines(wk, timeout)
        pending = b""
        for rec in gen:
            pending += tr.stdout.read() or b""
            *lines, pending = pending.split(b"\n")
            for line in lines:
                if line.startswith(b"{"):
                    r = json.loads(line)
                    sent[r["sent"]] = r["t"]
            if "loaded" in rec and rec["loaded"] in sent:
                lat.append(rec["t"] - sent[rec["loaded"]])
                if len(lat) == repeats:
                    break
        return statistics.median(lat) if lat else None
    finally:
        run.stop()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--impl", default="ours,tmrl")
    ap.add_argument("--duration", type=float, default=15.0, help="measured seconds per throughput run")
    ap.add_argument("--warmup", type=float, default=3.0)
    ap.add_argument("--workers", default="1,2,4")
    ap.add_argument("--params", default="1000000,20000000", help="actor sizes for the broadcast latency")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--broadcast-timeout", type=float, default=400.0)
    ap.add_argument("--skip-broadcast", action="store_true")
    ap.add_argument(
        "--sink-cost-us",
        type=float,
        default=0.0,
        help="microseconds of work per retrieved sample at the trainer (a trainer slower than the workers)",
    )
    ap.add_argument(
        "--sink-memory",
        action="store_true",
        help="the trainer side also stores every retrieved buffer in its replay memory (GenericTorchMemory)",
    )
    ap.add_argument("--python", default=sys.executable)
    ap.add_argument("--anchor-python", default="/tmp/tmrl-anchor/venv/bin/python")
    ap.add_argument("--anchor-home", default="/tmp/tmrl-anchor/home")
    ap.add_argument("--keep", action="store_true")
    ap.add_argument("--role", nargs="+", help=argparse.SUPPRESS)
    ap.add_argument("--port", type=int, help=argparse.SUPPRESS)
    ap.add_argument("--workdir", help=argparse.SUPPRESS)
    args = ap.parse_args()

    if args.role:
        role, *rest = args.role
        wd = Path(args.workdir)
        try:
            if role == "server":
                role_server(args.impl, args.port)
            elif role == "sink":
                role_sink(
                    args.impl, args.port, wd, float(rest[0]), float(rest[1]), float(rest[2]), rest[3] == "1"
                )
            elif role == "worker":
                role_worker(args.impl, args.port, wd)
            elif role == "bytes":
                role_bytes(args.impl)
            elif role == "bcast_trainer":
                role_bcast_trainer(args.impl, args.port, wd, int(rest[0]), int(rest[1]))
            elif role == "bcast_worker":
                role_bcast_worker(args.impl, args.port, wd, int(rest[0]), int(rest[1]))
        except KeyboardInterrupt:
            pass
        return

    def uptime() -> str:
        return subprocess.run(["uptime"], capture_output=True, text=True).stdout.strip()

    print(f"uptime: {uptime()}", flush=True)
    table: dict[str, dict] = {}
    for impl in args.impl.split(","):
        python, home = (args.python, None) if impl == "ours" else (args.anchor_python, args.anchor_home)
        r = table.setdefault(impl, {})
        r["bytes"] = measure_bytes(impl, python, home)
        print(f"{impl}: {r['bytes']:.1f} bytes/sample", flush=True)
        for k in [int(x) for x in args.workers.split(",")]:
            res = measure_throughput(
                impl, python, home, k, args.warmup, args.duration, args.keep, args.sink_cost_us, args.sink_memory
            )
            r[f"sps{k}"] = res.get("samples_per_s")
            r[f"rss{k}"] = res.get("rss_end")
            r[f"rss_series{k}"] = res.get("rss", [])
            mb = [f"{x / 2**20:.0f}" for x in r[f"rss_series{k}"]]
            print(
                f"{impl}: {k} worker(s): {r[f'sps{k}'] or 0:,.0f} samples/s; trainer memory (PSS) every 5 s (MiB): "
                f"{' '.join(mb)}; end {(r[f'rss{k}'] or 0) / 2**20:.0f} MiB   [{uptime()}]",
                flush=True,
            )
        if not args.skip_broadcast:
            for n in [int(x) for x in args.params.split(",")]:
                lat = measure_broadcast(impl, python, home, n, args.repeats, args.broadcast_timeout)
                r[f"bcast{n}"] = lat
                print(
                    f"{impl}: broadcast of a {n / 1e6:g}M-parameter actor: "
                    f"{'timeout' if lat is None else f'{lat:.2f} s'} (median of {args.repeats})   [{uptime()}]",
                    flush=True,
                )
    print(f"uptime: {uptime()}")
    ks = [int(x) for x in args.workers.split(",")]
    head = " | ".join([f"{k} worker(s) samples/s" for k in ks] + ["B/sample", f"RSS end ({max(ks)} w)"])
    print(f"{'impl':6} | {head}")
    for impl, r in table.items():
        cells = [f"{r.get(f'sps{k}') or 0:>20,.0f}" for k in ks]
        cells.append(f"{r['bytes'] or 0:8.1f}")
        cells.append(f"{(r.get(f'rss{max(ks)}') or 0) / 2**20:10.0f} MiB")
        print(f"{impl:6} | " + " | ".join(cells))
        if not args.skip_broadcast:
            for n in [int(x) for x in args.params.split(",")]:
                lat = r.get(f"bcast{n}")
                print(
                    f"{'':6} | broadcast {n / 1e6:g}M params: {'timeout' if lat is None else f'{lat:.2f} s'}"
                )


if __name__ == "__main__":
    main()
