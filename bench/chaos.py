"""The whole system under a seeded schedule of faults (kills, frozen workers, partitions, latency,
a full checkpoint disk, kills during a checkpoint write), with tlspyo and with NATS: samples
produced, acknowledged, stored and lost, recovery times, memory and processes left.

    python -m bench chaos                         # 10 minutes per backend, 4 workers
    python -m bench chaos --quick                 # 2 minutes per backend
    python -m bench chaos --minutes 60 --backends nats
    python -m bench chaos --quick --no-faults     # the same run without faults (a reference)
    python -m bench chaos --env sim --minutes 3   # the built-in driving simulator instead of Pendulum

What runs: the server (tmrl's relay, or for NATS ``--nats-nodes 1`` tmrl's supervised
nats-server, ``--nats-nodes 3`` a three-node NATS cluster on 127.0.0.1), the trainer (SAC on
Pendulum-v1, or with ``--env sim`` on the built-in simulator's lidar: :mod:`bench.chaos_env`, a
checkpoint after every epoch) and ``--workers`` rollout workers, each a process
of its own started by this command, which restarts any of them that exits (its restart loop).
Every worker reaches the server through its own fault proxy (:mod:`bench.faultproxy`). The
workers' environment is paced (``rate`` steps/s, like a real-time game), so that a fault's effect
is not hidden by a flood of samples.

The faults, one at a time, in a random order drawn from ``--seed`` (each kind once per cycle):

- ``kill_trainer``, ``kill_server``, ``kill_worker``: SIGKILL of the role's process group,
  restarted at once by the restart loop; ``kill_nats_node`` (NATS): SIGKILL of one nats-server
  (tmrl's supervisor, or this command for the cluster, starts it again);
- ``stop_worker``: SIGSTOP of a worker's process group for 5-10 s, then SIGCONT (a frozen game);
- ``partition``: the worker's proxy cuts its connections while the worker sends a sample batch
  (that batch is lost on the wire) and holds new connections for 3-10 s;
- ``latency``: 50-500 ms (with jitter) and a bandwidth cap on a worker's proxy for 5-10 s;
- ``disk_full``: the checkpoint folder's file system (a small tmpfs, mounted when this runs as
  root; otherwise the kind is left out, and said) is filled for 5-10 s, then freed;
- ``kill_mid_checkpoint``: SIGKILL of the trainer as soon as it creates a checkpoint file
  (inotify), so that the kill lands during the write.

After each fault the command waits (events the roles print, no fixed delay) until samples from
every worker it touched reach the trainer again and until those workers load weights the trainer
broadcast after the fault: the two recovery times. At the end the workers are stopped
(SIGTERM; their links flush), the trainer gets what was sent, then the trainer and the server
are stopped, and every process whose command line or environment carries the run's marker is
counted (and killed) as left.

Samples are counted by payload: each worker numbers its payloads, the trainer reports every
payload it receives (source, number, size). "acknowledged" (NATS) is what the stream
acknowledged to the worker; "lost" is acknowledged and never received by any trainer.
"""

from __future__ import annotations

import argparse
import contextlib
import ctypes
import datetime
import errno
import json
import math
import os
import random
import re
import secrets
import shutil
import signal
import statistics
import struct
import subprocess
import sys
import tempfile
import threading
import time
import urllib.request
from collections.abc import Callable, Iterable
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

from bench import chaos_env, harness
from bench.faultproxy import FaultProxy

LINUX = sys.platform.startswith("linux")
NEEDS_LINUX = ("the chaos bench needs Linux: it freezes and kills process groups (SIGSTOP, SIGKILL), "
               "reads /proc and watches files with inotify")

PW = "chaos-password"
THRESHOLD = chaos_env.THRESHOLDS["pendulum"]
"""Pendulum's test return the learning figure compares with (the simulator has none: its figure is
how far its test return rose, :meth:`Chaos.learning`)."""

FAULT_KINDS = ("kill_trainer", "kill_server", "kill_nats_node", "kill_worker", "stop_worker", "partition",
               "latency", "disk_full", "kill_mid_checkpoint")
GLOBAL_FAULTS = {"kill_trainer", "kill_server", "kill_nats_node", "disk_full", "kill_mid_checkpoint"}
"""Faults after which every worker must recover; the others touch one worker."""
TRAINER_FAULTS = {"kill_trainer", "disk_full", "kill_mid_checkpoint"}
"""Faults after which the weights must come from a trainer broadcast made after the fault."""

PROFILES: dict[str, dict[str, Any]] = {
    # a CI-sized run: small networks, short episodes, frequent checkpoints
    "test": dict(hidden_sizes=[32, 32], batch_size=64, memory_size=20_000, lr=3e-3, rounds=1, steps=100,
                 update_model_interval=20, update_buffer_interval=10, max_training_steps_per_env_step=1.0,
                 start_training=100, poll_wait=0.02, rate=100.0, episode=50),
    # the benchmark: the recommended Pendulum settings of bench pendulum_pipeline, paced workers
    "bench": dict(hidden_sizes=[64, 64], batch_size=256, memory_size=1_000_000, lr=3e-3, rounds=1, steps=500,
                  update_model_interval=20, update_buffer_interval=20, max_training_steps_per_env_step=1.0,
                  start_training=1000, poll_wait=0.01, rate=250.0, episode=200),
}

PARTITION_TRIGGER_BYTES = 500
"""A partition starts when the worker sends at least this many bytes at once (a sample batch of
the test profile is about 2 kB; tlspyo's other messages are smaller; with NATS the chunk must
also hold a publication on a samples subject)."""

TLSPYO_LOSS_BOUNDS = {"server": 1000 + 64, "trainer_link": 64, "worker": 256}
"""Payloads that one kill may lose with tlspyo (docs/reliability.md): a relay holds at most
``max_consumables`` (1000) pending batches plus a trainer's credit window (64) sent and not
acknowledged; a trainer's link process at most its credit window; a worker's link at most
``max_store`` (256) unsent batches."""

DURATIONS = {"stop_worker": (5.0, 10.0), "partition": (3.0, 10.0), "latency": (5.0, 10.0), "disk_full": (5.0, 10.0)}
"""Seconds a timed fault lasts (uniform in the range)."""


# ================================================================================================
# inside the role processes


_emit_lock = threading.Lock()


def _emit(ev: str, **fields: Any) -> None:
    """One event on stdout, as a JSON line the orchestrator reads."""
    line = json.dumps({"ev": ev, "t": time.time(), "pid": os.getpid(), **fields})
    with _emit_lock:
        sys.stdout.write(line + "\n")
        sys.stdout.flush()


def _stop_on_sigterm() -> None:
    """SIGTERM and SIGHUP stop the role as Ctrl-C does (its ``finally`` blocks run)."""
    if not LINUX:
        raise RuntimeError(NEEDS_LINUX)

    def handler(signum: int, frame: Any) -> None:
        raise KeyboardInterrupt

    signal.signal(signal.SIGTERM, handler)
    signal.signal(signal.SIGHUP, handler)


def _interrupt(signum: int, frame: Any) -> None:
    raise KeyboardInterrupt


def _net_settings(cfg: dict[str, Any], urls: str) -> Any:
    from tmrl.config.loader import validate
    from tmrl.config.settings import NetSettings

    raw: dict[str, Any] = {"TRANSPORT": cfg["backend"], "PASSWORD": PW, "PORT": cfg["port"], "TLS": False}
    if cfg["backend"] == "nats":
        raw["NATS"] = {"URLS": urls, "REPLICAS": cfg["replicas"], "STORE_DIRECTORY": cfg["nats_store"]}
    return NetSettings.from_config(validate(raw), Path(cfg["workdir"]) / "data")


def _seed(seed: int) -> None:
    import numpy as np
    import torch

    random.seed(seed)
    np.random.seed(seed % 2**32)
    torch.manual_seed(seed)
    torch.set_num_threads(1)


def _role_server(cfg: dict[str, Any]) -> None:
    from tmrl.networking import Server

    # max_workers: the run's number of workers (as a user sets NB_WORKERS), so that a killed
    # worker's slot must be freed for its restarted self to be let in
    limit = {"max_workers": cfg["max_workers"]} if cfg.get("max_workers") else {}
    server = Server(port=cfg["port"], password=PW, security=None, settings=_net_settings(cfg, ""), **limit)
    relay = server._relay
    last_pid = None
    try:
        _emit("ready")
        while server.running:
            pid = getattr(relay, "pid", None)  # NATS: the nats-server tmrl supervises
            if pid != last_pid and pid:
                _emit("nats_pid", nats_pid=pid)
                last_pid = pid
            time.sleep(0.2)
        _emit("relay_gone")
    finally:
        server.stop(5.0)


def _role_worker(cfg: dict[str, Any]) -> None:
    """A rollout worker: its environment (paced: :func:`bench.chaos_env.paced`) and actor are the
    run's ``env``'s; it sends what :func:`bench.chaos_env.collector` collects, then loads weights."""
    from tmrl.networking import RolloutWorker

    env, p = cfg.get("env", "pendulum"), cfg["profile"]
    worker = RolloutWorker(
        **chaos_env.worker_parts(env, p), device="cpu", server_ip="127.0.0.1", server_port=cfg["worker_port"],
        password=PW,
        max_samples_per_episode=p["episode"], model_path=str(Path(cfg["workdir"]) / f"{cfg['name']}.tmod"),
        model_history=0, security=None, settings=_net_settings(cfg, cfg["worker_urls"]),
    )
    link = worker._link
    src = worker.source_id

    def acked() -> dict[str, Any]:
        # NATS: the batches the stream acknowledged (in order: the first `published` payloads);
        # tlspyo's worker link does not tell its owner what the relay acknowledged.
        return {"acked": getattr(link, "published", None), "link_dropped": getattr(link, "dropped", None)}

    _emit("hello", src=src)
    seq = 0
    collect = chaos_env.collector(env, p)
    try:
        while True:
            collect(worker)
            n = len(worker.buffer)
            t = time.time()
            worker.send_and_clear_buffer()
            _emit("sent", src=src, seq=seq, n=n, t_sent=t, **acked())
            seq += 1
            if worker.update_actor_weights(verbose=False):
                _emit("weights", src=src, version=worker.weights_version)
    except KeyboardInterrupt:
        pass
    finally:
        worker.close(10.0)  # flushes what the link still holds
        _emit("final", src=src, payloads=seq, **acked())


def _role_trainer(cfg: dict[str, Any]) -> None:
    from tmrl.networking import Trainer

    env, p = cfg.get("env", "pendulum"), cfg["profile"]
    trainer = Trainer(
        training_cls=chaos_env.training_cls(env, p), server_ip="127.0.0.1", server_port=cfg["port"], password=PW,
        security=None, model_path=str(Path(cfg["workdir"]) / "trainer.tmod"), checkpoint_path=cfg["checkpoint"],
        **chaos_env.trainer_parts(env, p), settings=_net_settings(cfg, cfg["trainer_urls"]),
    )
    iface = trainer.interface
    link = iface._link
    receive = link.receive_samples

    def receive_and_report() -> list[Any]:
        got = receive()
        for payload in got:
            if isinstance(payload, dict):
                _emit("recv", src=payload.get("src"), seq=payload.get("seq"), n=payload.get("n"))
        return got

    if hasattr(link, "_schedule_acks"):
        # NATS acknowledges the batches receive_samples() hands over, right after decoding them:
        # each is reported before its acknowledgement is sent, so that a trainer killed between
        # the two has reported what the stream no longer holds
        from tmrl import wire

        schedule_acks = link._schedule_acks

        def report_then_ack(msgs: list[Any]) -> None:
            for m in msgs:
                with contextlib.suppress(Exception):
                    payload = wire.decode(m.data)
                    if isinstance(payload, dict):
                        _emit("recv", src=payload.get("src"), seq=payload.get("seq"), n=payload.get("n"))
            schedule_acks(msgs)

        link._schedule_acks = report_then_ack
    else:
        link.receive_samples = receive_and_report
    broadcast = iface.broadcast_model

    def broadcast_and_report(model: Any) -> None:
        broadcast(model)
        _emit("broadcast", version=iface.weights_version)

    iface.broadcast_model = broadcast_and_report
    dump = trainer.dump_run_instance_fn

    def dump_and_report(run: Any, path: str) -> None:
        t0 = time.monotonic()
        try:
            dump(run, path)
        except BaseException as e:
            _emit("ckpt_failed", error=f"{type(e).__name__}: {e}"[:300])
            raise
        _emit("ckpt", epoch=run.epoch, total_samples=run.total_samples, dt=time.monotonic() - t0)

    trainer.dump_run_instance_fn = dump_and_report

    def counters() -> dict[str, Any]:
        run = trainer.run_instance
        return {"total_samples": getattr(run, "total_samples", None), "total_updates": getattr(run, "total_updates", None),
                "lost_payloads": iface.lost_payloads, "duplicate_payloads": iface.duplicate_payloads,
                "link_dropped": getattr(link, "dropped", None), **iface.counters()}

    trainer.add_callback(lambda m: _emit("round", epoch=m.epoch, memory_len=m.memory_len, **counters()))
    _emit("start", resumed=trainer.checkpoint_exists())
    try:
        trainer.run()
    except KeyboardInterrupt:
        pass
    finally:
        _emit("final", **counters())


def _role_eval(cfg: dict[str, Any]) -> None:
    """Mean return of ``episodes`` deterministic episodes of the trainer's last weights
    (:class:`bench.chaos_env.Evaluation`)."""
    evaluation = chaos_env.Evaluation(cfg.get("env", "pendulum"), cfg["profile"])
    evaluation.load(Path(cfg["workdir"]) / "trainer.tmod")
    ret = evaluation.test_return(cfg["episodes"])
    _emit("eval", ret=ret, episodes=cfg["episodes"], **evaluation.extra)


def _role_evalloop(cfg: dict[str, Any]) -> None:
    """While the faults run: evaluate the trainer's weights file whenever it changed, at most every
    ``every`` seconds, until the test return first passes the environment's threshold
    (:data:`bench.chaos_env.THRESHOLDS`: Pendulum's :data:`THRESHOLD`; then exit), or, with none
    (the simulator), until stopped at the end of the faults. Each evaluation's event carries
    ``t_read``, when the weights were read: the orchestrator counts the samples produced by then."""
    import torch

    torch.set_num_threads(1)
    env = cfg.get("env", "pendulum")
    threshold = chaos_env.THRESHOLDS[env]
    evaluation = chaos_env.Evaluation(env, cfg["profile"])
    path = Path(cfg["workdir"]) / "trainer.tmod"
    last = None
    while True:
        try:
            mtime = path.stat().st_mtime_ns
            if mtime == last:
                time.sleep(0.2)
                continue
            t_read = time.time()
            evaluation.load(path)
        except Exception:  # noqa: BLE001 (not written yet, or replaced while read: try again soon)
            time.sleep(0.2)
            continue
        last = mtime
        ret = evaluation.test_return(cfg["episodes"])
        _emit("eval", ret=ret, t_read=t_read, episodes=cfg["episodes"], **evaluation.extra)
        if threshold is not None and ret > threshold:
            return
        time.sleep(cfg["every"])


def child_main(argv: list[str]) -> None:
    """One role: ``--role server|trainer|worker|eval --config FILE`` (written by the orchestrator)."""
    ap = argparse.ArgumentParser()
    ap.add_argument("--role", required=True)
    ap.add_argument("--config", required=True)
    ap.add_argument("--name", required=True)
    ap.add_argument("--incarnation", type=int, default=0)
    args = ap.parse_args(argv)
    cfg = json.loads(Path(args.config).read_text())
    cfg["name"], cfg["incarnation"] = args.name, args.incarnation
    _stop_on_sigterm()
    _seed(cfg["seed"] * 1000 + cfg.get("incarnation", 0) * 10 + sum(args.name.encode()))
    {"server": _role_server, "trainer": _role_trainer, "worker": _role_worker, "eval": _role_eval,
     "evalloop": _role_evalloop}[args.role](cfg)


# ================================================================================================
# the orchestrator


@dataclass
class ChaosConfig:
    """One run: a backend, its roles, its faults.

    Attributes:
        backend: ``"tlspyo"`` or ``"nats"``.
        workers: rollout workers (each behind its own proxy).
        faults: the kinds to draw from (each once per cycle, in a seeded random order), or an
            explicit sequence when ``cycle`` is False.
        minutes: how long faults are injected (the cycle starts again until then); with
            ``cycle`` False, the run ends after the listed faults.
        cycle: draw faults until ``minutes`` are over (True), or inject ``faults`` once, in order.
        seed: the schedule's and the roles' seed.
        profile: ``"test"`` or ``"bench"`` (see :data:`PROFILES`; for ``env`` ``"sim"``,
            :data:`bench.chaos_env.SIM_PROFILES`).
        env: ``"pendulum"`` (Pendulum-v1) or ``"sim"`` (the built-in driving simulator's lidar
            observations on the ``oval`` track): :mod:`bench.chaos_env`.
        nats_nodes: 1 (tmrl's supervised nats-server) or 3 (a cluster this command runs).
        durations: seconds of each timed fault (low, high).
        gap: seconds between a recovery and the next fault (low, high).
        recovery_timeout: seconds a recovery may take before the fault counts as not recovered.
        workdir: where logs, checkpoints and stores go (a new folder by default).
        evaluate: evaluate the final weights (episodes; 0: not); with ``learning``, also the
            trainer's weights while the faults run: on Pendulum until they first pass
            :data:`THRESHOLD` (the samples produced by then are the learning figure), on the
            simulator until the faults end (the first and the best test return are the figure).
        learning: evaluate while the faults run (see ``evaluate``), at most every
            ``eval_every`` seconds.
        rss_every: seconds between two samples of every role's resident memory.
        disk_mib: size of the checkpoint tmpfs (``disk_full``).
        stop_on_unrecovered: end the faults at the first one not recovered from (a test).
    """

    backend: str = "nats"
    workers: int = 2
    faults: tuple[str, ...] = FAULT_KINDS
    minutes: float = 10.0
    cycle: bool = True
    seed: int = 0
    profile: str = "bench"
    env: str = "pendulum"
    nats_nodes: int = 1
    durations: dict[str, tuple[float, float]] = field(default_factory=lambda: dict(DURATIONS))
    gap: tuple[float, float] = (2.0, 5.0)
    recovery_timeout: float = 60.0
    warmup_timeout: float = 180.0
    workdir: str | None = None
    evaluate: int = 0
    learning: bool = False
    eval_every: float = 2.0
    rss_every: float = 5.0
    disk_mib: int = 64
    stop_on_unrecovered: bool = False
    log: Callable[[str], None] = print


class Role:
    """One role's process, restarted by its restart loop whenever it exits (until stopped)."""

    def __init__(self, chaos: Chaos, name: str, kind: str, command: Callable[[int], list[str]],
                 cwd: str) -> None:
        self.chaos, self.name, self.kind, self.command, self.cwd = chaos, name, kind, command, cwd
        self.proc: subprocess.Popen | None = None
        self.incarnation = -1
        self.exits: list[tuple[float, int]] = []
        self.restarts = 0
        self.left_in_group = 0
        self.stopping = False
        self.restart_loop = True
        self._lock = threading.Lock()
        self._thread: threading.Thread | None = None

    def start(self) -> None:
        self._spawn()
        self._thread = threading.Thread(target=self._supervise, daemon=True, name=f"chaos-{self.name}")
        self._thread.start()

    def _spawn(self) -> None:
        if not LINUX:
            raise RuntimeError(NEEDS_LINUX)
        with self._lock:
            self.incarnation += 1
            log = open(self.chaos.logdir / f"{self.name}-{self.incarnation}.log", "wb")  # noqa: SIM115
            try:
                self.proc = subprocess.Popen(
                    self.command(self.incarnation), stdout=subprocess.PIPE, stderr=log, cwd=self.cwd,
                    env=self.chaos.env, start_new_session=True)
            finally:
                log.close()
            proc, inc = self.proc, self.incarnation
        threading.Thread(target=self._read, args=(proc, inc), daemon=True).start()

    def _read(self, proc: subprocess.Popen, inc: int) -> None:
        assert proc.stdout is not None
        for raw in proc.stdout:
            if raw.startswith(b"{"):
                try:
                    ev = json.loads(raw)
                except ValueError:
                    continue
                ev["role"], ev["inc"] = self.name, inc
                self.chaos.record(ev)

    def _supervise(self) -> None:
        """The restart loop: a role that exits is started again, 0.5 s later (doubling up to 5 s
        while it keeps exiting within 5 s of its start: a crash loop)."""
        delay = 0.25
        while True:
            proc = self.proc
            assert proc is not None
            started = time.monotonic()
            code = proc.wait()
            self.exits.append((time.time(), code))
            self.chaos.record({"ev": "exit", "role": self.name, "inc": self.incarnation, "code": code,
                               "t": time.time()})
            if self.stopping or not self.restart_loop:
                return
            delay = min(5.0, delay * 2) if time.monotonic() - started < 5 else 0.5
            if self.chaos.stop_event.wait(delay) or self.stopping:
                return
            self.restarts += 1
            self._spawn()

    @property
    def pid(self) -> int | None:
        return self.proc.pid if self.proc is not None and self.proc.poll() is None else None

    def signal_group(self, sig: int) -> bool:
        if not LINUX:
            raise RuntimeError(NEEDS_LINUX)
        proc = self.proc
        if proc is None or proc.poll() is not None:
            return False
        try:
            os.killpg(proc.pid, sig)
            return True
        except ProcessLookupError:
            return False

    def stop(self, grace: float) -> bool:
        """SIGTERM, then SIGKILL after ``grace`` seconds; True when it ended by itself."""
        if not LINUX:
            raise RuntimeError(NEEDS_LINUX)
        self.stopping = True
        proc = self.proc
        if proc is None or proc.poll() is not None:
            return True
        self.signal_group(signal.SIGCONT)
        with contextlib.suppress(ProcessLookupError):
            os.kill(proc.pid, signal.SIGTERM)
        deadline = time.monotonic() + grace
        try:
            proc.wait(grace)
            clean = True
        except subprocess.TimeoutExpired:
            clean = False
        while group_members(proc.pid) and time.monotonic() < deadline:
            time.sleep(0.1)  # polling /proc: the role's network process ends after it
        self.left_in_group = len(group_members(proc.pid))
        with contextlib.suppress(ProcessLookupError, PermissionError):
            os.killpg(proc.pid, signal.SIGKILL)
        proc.wait()
        return clean and not self.left_in_group


@dataclass
class Fault:
    """One injected fault and what followed."""

    kind: str
    target: str
    t_start: float
    t_end: float = 0.0
    detail: dict[str, Any] = field(default_factory=dict)
    flow_s: float | None = None
    weights_s: float | None = None


def _stat(pid: int | str) -> list[str] | None:
    """The fields of ``/proc/<pid>/stat`` after the command name (state, ppid, pgrp, ...)."""
    if not LINUX:
        raise RuntimeError(NEEDS_LINUX)
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().rsplit(")", 1)[1].split()
    except (OSError, IndexError):
        return None


def group_members(pgid: int) -> list[int]:
    """Live (not zombie) processes of process group ``pgid``."""
    if not LINUX:
        raise RuntimeError(NEEDS_LINUX)
    out = []
    for entry in os.listdir("/proc"):
        if entry.isdigit():
            st = _stat(entry)
            if st and st[0] != "Z" and int(st[2]) == pgid:
                out.append(int(entry))
    return out


def _rss_kib(pid: int) -> int:
    if not LINUX:
        raise RuntimeError(NEEDS_LINUX)
    try:
        with open(f"/proc/{pid}/status") as f:
            return next((int(line.split()[1]) for line in f if line.startswith("VmRSS:")), 0)
    except (OSError, ValueError):
        return 0


def _children(pid: int) -> list[int]:
    if not LINUX:
        raise RuntimeError(NEEDS_LINUX)
    out = []
    for entry in os.listdir("/proc"):
        if entry.isdigit():
            st = _stat(entry)
            if st and st[0] != "Z" and int(st[1]) == pid:
                out.append(int(entry))
    return out


def tree_rss_mib(pid: int | None) -> float | None:
    """Resident memory of ``pid`` and its children (a role's network process, its nats-server)."""
    if pid is None:
        return None
    return sum(_rss_kib(p) for p in [pid, *_children(pid)]) / 1024


def _go_heap_mib(prof_port: int) -> dict[str, float] | None:
    """A Go program's heap (MiB) from its profiling port: ``alloc`` (live objects and garbage not
    yet collected), ``idle`` (freed and kept), ``released`` (given back to the system), ``sys``
    (all it took); None when it does not answer within a second."""
    try:
        with urllib.request.urlopen(f"http://127.0.0.1:{prof_port}/debug/pprof/heap?debug=1", timeout=1.0) as r:
            text = r.read().decode(errors="replace")
    except OSError:
        return None
    stats = {}
    for line in text.splitlines():
        parts = line.split()
        if len(parts) == 4 and parts[0] == "#" and parts[2] == "=" and parts[3].isdigit():
            stats[parts[1]] = int(parts[3]) / 2**20
    names = {"alloc": "HeapAlloc", "idle": "HeapIdle", "released": "HeapReleased", "sys": "Sys"}
    return {k: round(stats[v], 1) for k, v in names.items() if v in stats} or None


def marked_processes(marker: str) -> list[int]:
    """Processes whose command line or environment holds ``marker`` (this one excluded)."""
    if not LINUX:
        raise RuntimeError(NEEDS_LINUX)
    found = []
    needle = marker.encode()
    for entry in os.listdir("/proc"):
        if not entry.isdigit() or int(entry) == os.getpid():
            continue
        st = _stat(entry)
        if not st or st[0] == "Z":
            continue
        for part in ("cmdline", "environ"):
            try:
                with open(f"/proc/{entry}/{part}", "rb") as f:
                    if needle in f.read():
                        found.append(int(entry))
                        break
            except OSError:
                continue
    return found


def _mid_write(path: Path) -> bool:
    """Whether a write of ``path`` (the header or its temporary file) is under way: a temporary
    file still there, or a header that does not parse (a write in place, caught half done)."""
    if path.name.endswith(".tmp"):
        return path.exists()
    try:
        json.loads(path.read_bytes())
        return False
    except FileNotFoundError:
        return False
    except (OSError, ValueError):
        return True


class _Inotify:
    """Linux inotify through ctypes: wait for a file created in a folder."""

    IN_MODIFY = 0x2
    IN_CREATE = 0x100

    def __init__(self, folder: Path) -> None:
        self.libc = ctypes.CDLL(None, use_errno=True)
        self.fd = self.libc.inotify_init1(os.O_NONBLOCK | os.O_CLOEXEC)
        mask = self.IN_CREATE | self.IN_MODIFY
        if self.fd < 0 or self.libc.inotify_add_watch(self.fd, str(folder).encode(), mask) < 0:
            raise OSError(ctypes.get_errno(), "inotify is not available")

    def wait_written(self, match: Callable[[str], bool], timeout: float) -> str | None:
        """The name of the next file created or written in the folder that ``match`` accepts."""
        import select

        deadline = time.monotonic() + timeout
        while (left := deadline - time.monotonic()) > 0:
            ready, _, _ = select.select([self.fd], [], [], left)
            if not ready:
                return None
            buf = os.read(self.fd, 65536)
            i = 0
            while i + 16 <= len(buf):
                _, _, _, length = struct.unpack_from("iIII", buf, i)
                name = buf[i + 16:i + 16 + length].rstrip(b"\0").decode(errors="replace")
                i += 16 + length
                if match(name):
                    return name
        return None

    def close(self) -> None:
        os.close(self.fd)


class Chaos:
    """Runs one :class:`ChaosConfig`; :meth:`run` returns the figures."""

    def __init__(self, cfg: ChaosConfig) -> None:
        self.cfg = cfg
        self.rng = random.Random(cfg.seed)
        self.marker = f"tmrl-chaos-{secrets.token_hex(6)}"
        root = Path(cfg.workdir) if cfg.workdir else Path(tempfile.gettempdir())
        self.workdir = root / self.marker
        self.logdir = self.workdir / "logs"
        self.logdir.mkdir(parents=True)
        self.events: list[dict[str, Any]] = []
        self._cv = threading.Condition()
        self.stop_event = threading.Event()
        self.env = dict(os.environ, TMRL_CHAOS_RUN=self.marker, OMP_NUM_THREADS="1", PYTHONUNBUFFERED="1",
                        TMRL_DATA=str(self.workdir / "data"))
        self.env["PYTHONPATH"] = os.pathsep.join(p for p in (str(harness.REPO), self.env.get("PYTHONPATH", "")) if p)
        self.env.pop("TMRL_CONFIG_OVERRIDE", None)
        self.roles: dict[str, Role] = {}
        self.proxies: dict[str, list[FaultProxy]] = {}
        self.faults: list[Fault] = []
        self.notes: list[str] = []
        self.mounted = False
        self.nats_pids: dict[str, int] = {}
        self.final_eval: dict[str, Any] = {}
        """The final evaluation's figures besides its return (the simulator's lap time and progress)."""
        self._events_file = open(self.workdir / "events.jsonl", "w")  # noqa: SIM115

    # --- events -----------------------------------------------------------------------------------

    def record(self, ev: dict[str, Any]) -> None:
        with self._cv:
            self.events.append(ev)
            self._events_file.write(json.dumps(ev) + "\n")
            self._cv.notify_all()

    def wait_for(self, find: Callable[[list[dict[str, Any]]], Any], timeout: float) -> Any:
        """The first truthy ``find(events)``, re-evaluated at each new event; None after ``timeout``."""
        deadline = time.monotonic() + timeout
        with self._cv:
            while True:
                got = find(self.events)
                if got or self.stop_event.is_set():
                    return got
                left = deadline - time.monotonic()
                if left <= 0:
                    return None
                self._cv.wait(min(left, 1.0))

    def select(self, ev: str, role: str | None = None, since: float = 0.0, **match: Any) -> list[dict[str, Any]]:
        with self._cv:
            return [e for e in self.events if e["ev"] == ev and (role is None or e["role"] == role)
                    and e.get("t", 0) > since and all(e.get(k) == v for k, v in match.items())]

    def say(self, text: str) -> None:
        self.cfg.log(f"  [{self.cfg.backend} {time.strftime('%H:%M:%S')}] {text}")

    # --- set-up -----------------------------------------------------------------------------------

    def _role_config(self) -> dict[str, Any]:
        cfg = self.cfg
        workers = {}
        for i in range(cfg.workers):
            ports = [p.port for p in self.proxies[f"worker{i}"]]
            workers[f"worker{i}"] = {"worker_port": ports[0],
                                     "worker_urls": ",".join(f"nats://127.0.0.1:{p}" for p in ports)
                                     if cfg.backend == "nats" else ""}
        return workers

    def _write_config(self, name: str, extra: dict[str, Any]) -> Path:
        cfg = self.cfg
        common = {
            "backend": cfg.backend, "port": self.port, "seed": cfg.seed, "workdir": str(self.workdir),
            "env": cfg.env, "profile": chaos_env.profile(cfg.env, cfg.profile, PROFILES[cfg.profile]),
            "replicas": 3 if cfg.nats_nodes == 3 else 1,
            "nats_store": str(self.workdir / "nats-store"), "checkpoint": str(self.checkpoint),
            "trainer_urls": ",".join(f"nats://127.0.0.1:{p}" for p in self.node_ports) if cfg.nats_nodes == 3 else "",
            "worker_port": self.port, "worker_urls": "", "marker": self.marker, "max_workers": cfg.workers,
        }
        path = self.workdir / f"{name}.json"
        path.write_text(json.dumps({**common, **extra}))
        return path

    def _add_role(self, name: str, kind: str, extra: dict[str, Any] | None = None) -> Role:
        path = self._write_config(name, extra or {})

        def command(incarnation: int) -> list[str]:
            return [sys.executable, str(harness.CHILD), "chaos", "--role", kind, "--config", str(path), "--name", name,
                    "--incarnation", str(incarnation)]

        role = Role(self, name, kind, command, str(self.workdir))
        self.roles[name] = role
        return role

    def _add_nats_node(self, i: int) -> Role:
        """Node ``i`` of a three-node cluster on 127.0.0.1 (no TLS, the role users tmrl derives
        from the password, routes on loopback, no advertised client URLs: the workers reach the
        cluster only through their proxies)."""
        from tmrl.transport._nats_server import find_server_binary, role_credentials, users_block

        users = {role: role_credentials(role, PW, None, None) for role in ("worker", "trainer")}
        conf = {
            "server_name": f"n{i}", "host": "127.0.0.1", "port": self.node_ports[i],
            "http": f"127.0.0.1:{self.monitor_ports[i]}",  # /jsz: which node leads each stream
            "prof_port": self.prof_ports[i],  # the Go heap behind the resident memory
            "max_payload": 8 * 2**20,
            "jetstream": {"store_dir": str(self.workdir / f"node{i}")},
            "cluster": {"name": "tmrl-chaos", "listen": f"127.0.0.1:{self.route_ports[i]}", "no_advertise": True,
                        "routes": [f"nats://127.0.0.1:{self.route_ports[j]}" for j in range(3) if j != i]},
            "authorization": {"users": users_block(users, "tmrl-samples", "tmrl-weights")},
        }
        path = self.workdir / f"node{i}.conf"
        path.write_text(json.dumps(conf))
        binary = find_server_binary()
        role = Role(self, f"node{i}", "nats-node", lambda inc: [binary, "-c", str(path)], str(self.workdir))
        self.roles[role.name] = role
        return role

    def _mount_checkpoint_disk(self) -> None:
        disk = self.workdir / "ckpt-disk"
        disk.mkdir()
        if hasattr(os, "geteuid") and os.geteuid() == 0:
            done = subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={self.cfg.disk_mib}m", "tmpfs", str(disk)],
                                  capture_output=True, text=True, check=False)
            self.mounted = done.returncode == 0
            if not self.mounted:
                self.notes.append(f"disk_full left out: mount -t tmpfs failed ({done.stderr.strip()})")
        else:
            self.notes.append("disk_full left out: mounting a small tmpfs needs root")
        self.checkpoint = disk / "checkpoint"

    def setup(self) -> None:
        cfg = self.cfg
        self.port = harness.free_port()
        self.checkpoint = self.workdir / "checkpoint"
        if "disk_full" in cfg.faults:
            self._mount_checkpoint_disk()
        self.node_ports: list[int] = []
        self.route_ports: list[int] = []
        self.monitor_ports: list[int] = []
        self.prof_ports: list[int] = []
        if cfg.backend == "nats" and cfg.nats_nodes == 3:
            self.node_ports = [harness.free_port() for _ in range(3)]
            self.route_ports = [harness.free_port() for _ in range(3)]
            self.monitor_ports = [harness.free_port() for _ in range(3)]
            self.prof_ports = [harness.free_port() for _ in range(3)]
            targets = self.node_ports
        else:
            targets = [self.port]
        for i in range(cfg.workers):
            self.proxies[f"worker{i}"] = [FaultProxy(t, seed=cfg.seed * 100 + i, name=f"worker{i}->{t}").start()
                                          for t in targets]
        extra = self._role_config()
        if cfg.backend == "nats" and cfg.nats_nodes == 3:
            for i in range(3):
                self._add_nats_node(i).start()
            for port in self.node_ports:
                harness.wait_listening(port, 60.0, "a NATS node")
        else:
            self._add_role("server", "server").start()
            if not self.wait_for(lambda evs: any(e["ev"] == "ready" and e["role"] == "server" for e in evs),
                                 cfg.warmup_timeout):
                raise RuntimeError(f"the server did not start (logs in {self.logdir})")
        self._add_role("trainer", "trainer").start()
        for i in range(cfg.workers):
            self._add_role(f"worker{i}", "worker", extra[f"worker{i}"]).start()

    def worker_names(self) -> list[str]:
        return [n for n, r in self.roles.items() if r.kind == "worker"]

    def current_src(self, name: str, since: float = 0.0, timeout: float = 0.0) -> int | None:
        """The source id of worker ``name``'s current incarnation (its hello event)."""
        role = self.roles[name]

        def find(evs: list[dict[str, Any]]) -> int | None:
            for e in reversed(evs):
                if e["ev"] == "hello" and e["role"] == name and e["inc"] == role.incarnation and e["t"] > since:
                    return e["src"]
            return None

        with self._cv:
            got = find(self.events)
        return got if got is not None or timeout <= 0 else self.wait_for(find, timeout)

    def warm_up(self) -> float:
        """Wait until every worker's samples reach the trainer and every worker loaded weights of
        the training (a version after the trainer's first broadcast, its initial weights: until
        its memory holds ``start_training`` samples no other comes, and a fault then would count
        that wait as its recovery)."""
        t0 = time.time()

        def ready(evs: list[dict[str, Any]]) -> bool:
            srcs = {n: self.current_src(n) for n in self.worker_names()}
            if None in srcs.values():
                return False
            got = {e["src"] for e in evs if e["ev"] == "recv"}
            loaded = {e["role"] for e in evs if e["ev"] == "weights" and e.get("version", 0) >= 2}
            return set(srcs.values()) <= got and set(srcs) <= loaded

        def crashing(evs: list[dict[str, Any]]) -> str | None:
            for name, role in self.roles.items():
                if role.restarts >= 3:
                    return name
            return None

        if not self.wait_for(lambda evs: ready(evs) or crashing(evs), self.cfg.warmup_timeout) or crashing([]):
            name = crashing([])
            if name:
                log = self.logdir / f"{name}-0.log"
                tail = log.read_text(errors="replace").strip().splitlines()[-3:] if log.exists() else []
                raise RuntimeError(f"{name} keeps exiting during the warm-up: {' | '.join(tail)}")
        with self._cv:
            warm = ready(self.events)
        if not warm:
            raise RuntimeError(f"the roles did not exchange samples and weights within {self.cfg.warmup_timeout:g} s "
                               f"(logs in {self.logdir})")
        return time.time() - t0

    # --- faults -----------------------------------------------------------------------------------

    def _duration(self, kind: str) -> float:
        low, high = self.cfg.durations.get(kind, DURATIONS.get(kind, (5.0, 5.0)))
        return self.rng.uniform(low, high)

    def available(self, kind: str) -> bool:
        if kind == "kill_nats_node":
            return self.cfg.backend == "nats"
        if kind == "disk_full":
            return self.mounted
        if kind == "kill_server":
            return "server" in self.roles  # a NATS cluster has no tmrl server: kill_nats_node kills a node
        return True

    def inject(self, kind: str) -> Fault:
        if not LINUX:
            raise RuntimeError(NEEDS_LINUX)
        workers = self.worker_names()
        target = self.rng.choice(workers) if kind not in GLOBAL_FAULTS else "all"
        fault = Fault(kind, target, time.time())
        self.say(f"fault {len(self.faults) + 1}: {kind}" + ("" if target == "all" else f" on {target}"))
        if kind in ("kill_trainer", "kill_worker"):
            role = self.roles["trainer" if kind == "kill_trainer" else target]
            fault.detail["killed"] = role.signal_group(signal.SIGKILL)
        elif kind == "kill_server" or kind == "kill_nats_node":
            self._kill_server(kind, fault)
        elif kind == "kill_mid_checkpoint":
            self._kill_mid_checkpoint(fault)
        elif kind == "stop_worker":
            role = self.roles[target]
            seconds = self._duration(kind)
            role.signal_group(signal.SIGSTOP)
            self.stop_event.wait(seconds)  # the fault's length
            role.signal_group(signal.SIGCONT)
            fault.detail["seconds"] = seconds
        elif kind == "partition":
            # armed: the link goes down while the worker sends a sample batch (lost on the wire,
            # to be sent again), or after 10 s without one
            seconds = self._duration(kind)
            proxies = self.proxies[target]
            for proxy in proxies:
                proxy.partition(mode="cut", on_chunk_bytes=PARTITION_TRIGGER_BYTES,
                                on_chunk_holding=b"PUB tmrl.samples." if self.cfg.backend == "nats" else None)
            deadline = time.monotonic() + 10.0
            while not any(p.partitioned for p in proxies) and time.monotonic() < deadline:
                time.sleep(0.005)  # polling the proxies' own state (they change on their thread)
            fault.detail["on_a_batch"] = any(p.partitioned for p in proxies)
            fault.t_start = time.time()
            for proxy in proxies:
                proxy.partition(mode="cut")
            self.stop_event.wait(seconds)  # the fault's length
            for proxy in proxies:
                proxy.heal()
            fault.detail["seconds"] = seconds
        elif kind == "latency":
            seconds = self._duration(kind)
            ms = self.rng.uniform(50, 500)
            bandwidth = self.rng.choice([None, 200_000, 50_000])
            for proxy in self.proxies[target]:
                proxy.set_latency(ms, jitter_ms=ms / 2)
                proxy.set_bandwidth(bandwidth)
            src = self.current_src(target)
            self.stop_event.wait(seconds)  # the fault's length
            fault.detail.update(seconds=seconds, latency_ms=ms, jitter_ms=ms / 2, bandwidth=bandwidth,
                                flowed_during=bool(self.select("recv", since=fault.t_start, src=src)))
            for proxy in self.proxies[target]:
                proxy.heal()
        elif kind == "disk_full":
            self._disk_full(fault)
        else:
            raise ValueError(f"unknown fault kind {kind!r}")
        fault.t_end = time.time()
        self.faults.append(fault)
        return fault

    def _kill_server(self, kind: str, fault: Fault) -> None:
        if not LINUX:
            raise RuntimeError(NEEDS_LINUX)
        if self.cfg.backend == "nats" and self.cfg.nats_nodes == 3:
            name = self.rng.choice(["node0", "node1", "node2"])
            fault.detail["node"] = name
            fault.detail["led"] = self._streams_led_by(int(name[-1]))
            fault.detail["killed"] = self.roles[name].signal_group(signal.SIGKILL)
        elif kind == "kill_server":
            fault.detail["killed"] = self.roles["server"].signal_group(signal.SIGKILL)
        else:  # the nats-server tmrl's server supervises
            pid = next((e["nats_pid"] for e in reversed(self.select("nats_pid", "server"))), None)
            fault.detail["nats_pid"] = pid
            try:
                os.kill(pid, signal.SIGKILL)
                fault.detail["killed"] = True
            except (TypeError, ProcessLookupError):
                fault.detail["killed"] = False

    def _streams_led_by(self, i: int) -> list[str] | None:
        """The streams (samples, weights' key-value and object buckets) and the consumers
        (``stream/consumer``) node ``i`` leads now, from its monitoring endpoint; None when it does
        not answer within a second."""
        url = f"http://127.0.0.1:{self.monitor_ports[i]}/jsz?accounts=true&streams=true&consumers=true"
        try:
            with urllib.request.urlopen(url, timeout=1.0) as answer:
                jsz = json.load(answer)
        except (OSError, ValueError):
            return None
        led = []
        for account in jsz.get("account_details") or []:
            for stream in account.get("stream_detail") or []:
                if (stream.get("cluster") or {}).get("leader") == f"n{i}":
                    led.append(stream.get("name"))
                for consumer in stream.get("consumer_detail") or []:
                    if (consumer.get("cluster") or {}).get("leader") == f"n{i}":
                        led.append(f"{stream.get('name')}/{consumer.get('name')}")
        return sorted(led)

    def _kill_mid_checkpoint(self, fault: Fault) -> None:
        """SIGKILL the trainer while it writes its checkpoint's header (``checkpoint.json``, the
        commit point: written in place, a kill there would leave a checkpoint no trainer resumes)."""
        if not LINUX:
            raise RuntimeError(NEEDS_LINUX)
        folder = self.checkpoint
        role = self.roles["trainer"]
        landed = False
        try:
            watch = _Inotify(folder)
        except OSError as e:
            watch = None
            fault.detail["inotify"] = str(e)
        # The trainer is frozen (SIGSTOP) as soon as it creates or writes the header's file (its
        # temporary file when the write is atomic); when that file is still there (the write is
        # not over), it is killed; otherwise it goes on and the next checkpoint is tried (a small
        # file may be written before the signal lands). After 60 s it is killed anyway.
        deadline = time.monotonic() + 60.0
        name, tries = None, 0
        try:
            while watch is not None and (left := deadline - time.monotonic()) > 0 and tries < 50:
                name = watch.wait_written(lambda n: "checkpoint.json" in n, left)
                if name is None:
                    break
                tries += 1
                role.signal_group(signal.SIGSTOP)
                if _mid_write(folder / name):
                    landed = True
                    break
                role.signal_group(signal.SIGCONT)
            proc = role.proc
            role.signal_group(signal.SIGKILL)
            if proc is not None:
                proc.wait()
        finally:
            if watch:
                watch.close()
        fault.detail.update(during=name, tries=tries, left_a_partial_file=landed)

    def _disk_full(self, fault: Fault) -> None:
        disk = self.checkpoint.parent
        filler = disk / "filler"
        seconds = self._duration("disk_full")
        written = 0
        usage = shutil.disk_usage(disk)
        fault.detail["used_before_mib"] = round((usage.total - usage.free) / 2**20, 1)
        try:
            with open(filler, "wb") as f:
                block = b"\0" * 2**20
                try:
                    while True:
                        f.write(block)
                        f.flush()
                        written += len(block)
                except OSError as e:
                    if e.errno != errno.ENOSPC:
                        raise
        except OSError as e:
            if e.errno != errno.ENOSPC:
                raise
            # already full without the filler: say what fills it (the fault still lasts its time)
            biggest = sorted(((f.stat().st_size, str(f.relative_to(disk))) for f in disk.rglob("*") if f.is_file()),
                             reverse=True)[:5]
            fault.detail["already_full"] = True
            self.notes.append(f"the checkpoint disk was already full at a disk_full fault "
                              f"({fault.detail['used_before_mib']} MiB used; biggest files: {biggest})")
        fault.detail["filled_mib"] = written // 2**20
        self.stop_event.wait(seconds)  # the fault's length
        fault.detail["trainer_exits_meanwhile"] = len([e for e in self.select("exit", "trainer", fault.t_start)])
        fault.detail["failed_checkpoints"] = len(self.select("ckpt_failed", "trainer", fault.t_start))
        filler.unlink(missing_ok=True)
        fault.detail["seconds"] = seconds

    def measure(self, fault: Fault) -> None:
        """Wait for the recovery of every worker the fault touched: samples from it at the trainer,
        and weights broadcast after the fault loaded by it."""
        timeout = self.cfg.recovery_timeout
        names = self.worker_names() if fault.target == "all" else [fault.target]
        t_end = fault.t_end
        since_weights = t_end
        if fault.kind in TRAINER_FAULTS:
            first = self.wait_for(lambda evs: next((e for e in evs if e["ev"] == "broadcast" and e["t"] > t_end
                                                    and e["role"] == "trainer"), None), timeout)
            since_weights = first["t"] if first else math.inf
        flow: list[float] = []
        weights: list[float] = []
        deadline = time.monotonic() + timeout
        for name in names:
            since = fault.t_start if fault.kind == "kill_worker" else 0.0
            src = self.current_src(name, since=since, timeout=max(0.0, deadline - time.monotonic()))
            if src is None:
                flow.append(math.inf)
                weights.append(math.inf)
                continue
            got = self.wait_for(lambda evs, s=src: next((e for e in evs if e["ev"] == "recv" and e["src"] == s
                                                         and e["t"] > t_end), None),
                                max(0.0, deadline - time.monotonic()))
            flow.append(got["t"] - t_end if got else math.inf)
            got = self.wait_for(lambda evs, n=name: next((e for e in evs if e["ev"] == "weights" and e["role"] == n
                                                          and e["t"] > since_weights), None),
                                max(0.0, deadline - time.monotonic()))
            weights.append(got["t"] - t_end if got else math.inf)
        fault.flow_s = max(flow) if flow and max(flow) < math.inf else None
        fault.weights_s = max(weights) if weights and max(weights) < math.inf else None
        shown = ", ".join(f"{k} {'NOT recovered' if v is None else f'{v:.1f} s'}"
                          for k, v in (("samples", fault.flow_s), ("weights", fault.weights_s)))
        self.say(f"  recovered: {shown}" + (f" {fault.detail}" if fault.detail else ""))

    def schedule(self) -> Iterable[str]:
        kinds = [k for k in self.cfg.faults if self.available(k)]
        left_out = [k for k in self.cfg.faults if not self.available(k)]
        if left_out:
            self.notes.append(f"fault kinds not available here: {', '.join(left_out)}")
        if not self.cfg.cycle:
            yield from kinds
            return
        end = time.monotonic() + self.cfg.minutes * 60
        if not kinds:  # a run without faults: as long, for comparison
            self.stop_event.wait(self.cfg.minutes * 60)
        while kinds and time.monotonic() < end:
            cycle = list(kinds)
            self.rng.shuffle(cycle)
            for kind in cycle:
                if time.monotonic() >= end:
                    return
                yield kind

    # --- the end ----------------------------------------------------------------------------------

    def rss(self) -> dict[str, float | None]:
        return {name: tree_rss_mib(role.pid) for name, role in self.roles.items() if role.kind != "evalloop"}

    def _sample_rss(self) -> None:
        """Every ``rss_every`` seconds, every role's resident memory as an ``rss`` event; every
        30 s, the Go heap of each NATS node of a cluster as a ``heap`` event (what its resident
        memory holds: the live heap, what the collector freed and kept, what it gave back)."""
        last_heap = 0.0
        while not self.stop_event.wait(self.cfg.rss_every):
            self.record({"ev": "rss", "role": "chaos", "t": time.time(), "mib": self.rss()})
            if self.prof_ports and time.monotonic() - last_heap >= 30.0:
                last_heap = time.monotonic()
                self.record({"ev": "heap", "role": "chaos", "t": time.time(),
                             "mib": {f"node{i}": _go_heap_mib(port) for i, port in enumerate(self.prof_ports)}})

    def rss_figures(self, t_faults: float, t_end: float) -> dict[str, Any]:
        """Each role's resident memory around the tenth minute of faults (a sixth of a shorter
        run) and over the last four minutes: the median of the samples in each window, so that a
        role restarted just before a sample (low until it has loaded its state) or a spike of a
        nats-server's garbage collector does not stand for the role."""
        mark = t_faults + min(600.0, (t_end - t_faults) / 6)
        samples = self.select("rss")
        out: dict[str, Any] = {"mark_s": mark - t_faults, "mid": {}, "end": {}, "samples": len(samples)}
        for name in self.rss():
            def median(lo: float, hi: float, n: str = name) -> float | None:
                vals = [e["mib"].get(n) for e in samples if lo <= e["t"] <= hi and e["mib"].get(n)]
                return statistics.median(vals) if vals else None
            out["mid"][name] = median(mark - 120, mark + 120)
            out["end"][name] = median(t_end - 240, t_end + 1)
        heaps = self.select("heap")
        out["heap_mid"], out["heap_end"] = {}, {}
        for name in sorted({n for e in heaps for n in e["mib"]}):
            for key, lo, hi in (("heap_mid", mark - 120, mark + 120), ("heap_end", t_end - 240, t_end + 1)):
                got = [e["mib"][name] for e in heaps if lo <= e["t"] <= hi and e["mib"].get(name)]
                if got:
                    out[key][name] = {k: statistics.median(g[k] for g in got if k in g) for k in got[0]}
        return out

    def learning(self, t_warm: float) -> dict[str, Any]:
        """Pendulum: the first evaluation during the faults that passed :data:`THRESHOLD`: samples
        produced when its weights were read, and seconds since the roles were warm. The simulator
        (no threshold): the test return of the first evaluation and the best one (``rising``: best
        minus first), when the weights of the first evaluation within 1 % of the best were read
        (seconds, samples produced by then), the first evaluation that completed a lap, and the
        best lap time (a lap's return hardly depends on its time: the lap time says what the
        returns no longer do)."""
        evals = self.select("eval", "evaluator")
        if chaos_env.THRESHOLDS[self.cfg.env] is None:
            return self._rising(evals, t_warm)
        passed = next((e for e in evals if e["ret"] > THRESHOLD), None)
        out: dict[str, Any] = {"evaluations": len(evals), "reached": passed is not None,
                               "best": max((e["ret"] for e in evals), default=None)}
        if passed is not None:
            out["samples"] = sum(e["n"] for e in self.select("sent") if e["t_sent"] <= passed["t_read"])
            out["s"] = passed["t_read"] - t_warm
            out["faults_before"] = sum(1 for f in self.faults if f.t_start <= passed["t_read"])
        return out

    def _rising(self, evals: list[dict[str, Any]], t_warm: float) -> dict[str, Any]:
        """The simulator's learning figure (see :meth:`learning`)."""
        out: dict[str, Any] = {"evaluations": len(evals), "reached": None, "first": None, "best": None}
        if not evals:
            return out

        def when(e: dict[str, Any]) -> dict[str, Any]:
            return {"s": e["t_read"] - t_warm,
                    "samples": sum(s["n"] for s in self.select("sent") if s["t_sent"] <= e["t_read"])}

        best = max(e["ret"] for e in evals)
        # the first evaluation within 1 % of the best (laps of the same line differ in the decimals)
        near = next(e for e in evals if e["ret"] >= best - 0.01 * abs(best))
        lap = next((e for e in evals if e.get("lap_time") is not None), None)
        out.update(first=evals[0]["ret"], best=best, rising=best - evals[0]["ret"],
                   best_at=when(near), first_lap=None if lap is None else {"lap_time": lap["lap_time"], **when(lap)},
                   laps=sum(1 for e in evals if e.get("lap_time") is not None),
                   best_lap=min((e["lap_time"] for e in evals if e.get("lap_time") is not None), default=None),
                   best_progress=max(e.get("progress") or 0.0 for e in evals))
        return out

    def _missing(self) -> set[tuple[int, int]]:
        """Payloads that must still reach the trainer at the end: every acknowledged one (NATS),
        and the last one of each worker stopped cleanly (delivered in order per worker: the ones
        before it arrived or are lost for good)."""
        got = {(e["src"], e["seq"]) for e in self.select("recv")}
        payloads = self.payloads()
        must = {key for key, info in payloads.items() if info["acked"]}
        last: dict[int, int] = {}
        for (src, seq), info in payloads.items():
            if not info["killed"]:
                last[src] = max(last.get(src, -1), seq)
        must |= set(last.items())
        return must - got

    def payloads(self) -> dict[tuple[int, int], dict[str, Any]]:
        """Every payload a worker handed to its link: size, time, acknowledged, whether its worker
        was killed."""
        out: dict[tuple[int, int], dict[str, Any]] = {}
        acked: dict[int, int] = {}
        for e in self.select("sent") + self.select("final"):
            if e["role"].startswith("worker") and e.get("acked") is not None:
                acked[e["src"]] = max(acked.get(e["src"], 0), e["acked"])
        finals = {e["src"] for e in self.select("final") if e["role"].startswith("worker")}
        killed = {e["src"] for e in self.select("hello")} - finals  # no final event: killed
        for e in self.select("sent"):
            out[(e["src"], e["seq"])] = {"n": e["n"], "t": e["t_sent"], "acked": e["seq"] < acked.get(e["src"], 0),
                                         "killed": e["src"] in killed}
        return out

    def drain_and_stop(self) -> dict[str, Any]:
        """Stop the workers (their links flush), wait until the trainer has what it must get,
        stop the trainer and the server; count what is left."""
        if not LINUX:
            raise RuntimeError(NEEDS_LINUX)
        out: dict[str, Any] = {"stopped_cleanly": {}}
        for proxies in self.proxies.values():
            for p in proxies:
                p.heal()
        for name in self.worker_names():
            out["stopped_cleanly"][name] = self.roles[name].stop(20.0)
        t0 = time.monotonic()
        self.wait_for(lambda evs: not self._missing(), 30.0)
        out["undelivered_at_end"] = len(self._missing())
        out["drain_s"] = time.monotonic() - t0
        for name in ["trainer"] + [n for n in self.roles if n not in ("trainer",) and not n.startswith("worker")]:
            out["stopped_cleanly"][name] = self.roles[name].stop(20.0)
        self.stop_event.set()
        for proxies in self.proxies.values():
            for p in proxies:
                p.close()
        left = marked_processes(self.marker)
        deadline = time.monotonic() + 10
        while left and time.monotonic() < deadline:
            time.sleep(0.2)  # polling /proc: a process that was told to stop may take a moment
            left = marked_processes(self.marker)
        out["processes_left"] = len(left) + sum(r.left_in_group for r in self.roles.values())
        out["processes_left_cmdlines"] = [_cmdline(p) for p in left]
        for pid in left:
            with contextlib.suppress(ProcessLookupError):
                os.kill(pid, signal.SIGKILL)
        return out

    def elections(self) -> None:
        """For each NATS node kill, how long the cluster took to elect a new leader for each stream
        and consumer the killed node led (``detail["elected_s"]``, seconds from the kill to the
        first "new ... leader" line of a node's log; None: none within 60 s). What a link does
        after a kill cannot come before that: it is the floor of the recovery."""
        found: list[tuple[float, str]] = []
        line_re = re.compile(r"(\d{4}/\d\d/\d\d \d\d:\d\d:\d\d\.\d+) \[INF\] JetStream cluster new "
                             r"(?:stream|consumer) leader for '[^>']+ > ([^']+)'")
        for path in self.logdir.glob("node*-*.log"):
            for line in path.read_text(errors="replace").splitlines():
                m = line_re.search(line)
                if m:  # the server writes its local time
                    t = datetime.datetime.strptime(m.group(1), "%Y/%m/%d %H:%M:%S.%f").timestamp()
                    found.append((t, m.group(2).replace(" > ", "/")))
        for fault in self.faults:
            if fault.kind != "kill_nats_node" or not fault.detail.get("led"):
                continue
            fault.detail["elected_s"] = {
                name: min((round(t - fault.t_start, 2) for t, n in found if n == name and 0 < t - fault.t_start < 60),
                          default=None)
                for name in fault.detail["led"]}

    def election_figures(self) -> dict[str, Any]:
        """Over the NATS node kills that took a leader of the samples (the stream or its consumer)
        or of the weights (their two buckets): the elections' seconds (the slowest of those the
        node led) and the recovery's seconds beyond them (what tmrl added), medians and maxima."""
        out: dict[str, Any] = {}
        for what, names, measured in (("samples", ("tmrl-samples", "tmrl-samples/tmrl-trainer"), "flow_s"),
                                      ("weights", ("KV_tmrl-weights", "OBJ_tmrl-weights"), "weights_s")):
            floors, beyond = [], []
            for f in self.faults:
                elected = [v for n, v in (f.detail.get("elected_s") or {}).items() if n in names]
                if f.kind != "kill_nats_node" or not elected or None in elected:
                    continue
                floors.append(max(elected))
                if getattr(f, measured) is not None:
                    beyond.append(getattr(f, measured) - max(elected))
            out[what] = {"n": len(floors), "election_median_s": _median(floors), "election_max_s": max(floors, default=None),
                         "beyond_median_s": _median(beyond), "beyond_max_s": max(beyond, default=None)}
        return out

    def account(self) -> dict[str, Any]:
        payloads = self.payloads()
        received = {(e["src"], e["seq"]): e["n"] for e in self.select("recv")}
        server_kills = [f.t_start for f in self.faults if f.kind in ("kill_server", "kill_nats_node")]
        trainer_deaths = [t for t, code in self.roles["trainer"].exits if code != 0] if "trainer" in self.roles else []
        recv_times: dict[int, list[tuple[float, int]]] = {}
        for e in self.select("recv"):
            recv_times.setdefault(e["src"], []).append((e["t"], e["seq"]))
        last_seq = {src: max(s for _, s in ts) for src, ts in recv_times.items()}
        lost_acked = lost_with_worker = lost_with_server = lost_in_trainer_link = unexplained = 0
        per_kill: dict[tuple[str, Any], int] = {}  # payloads lost, by the kill that explains them
        lost_detail: list[dict[str, Any]] = []

        def held_at(t_kill: float, src: int, seq: int, t_sent: float) -> bool:
            """Sent before ``t_kill`` and after the last payload of its worker the trainer got before."""
            before = max((s for t, s in recv_times.get(src, []) if t < t_kill), default=-1)
            return t_sent <= t_kill and seq > before

        for (src, seq), info in payloads.items():
            if (src, seq) in received:
                continue
            if self.cfg.backend == "nats" and info["acked"]:
                lost_acked += info["n"]
                lost_detail.append({"src": src, "seq": seq, "t_sent": info["t"],
                                    "faults": [(f.kind, round(f.t_start - info["t"], 2)) for f in self.faults
                                               if abs(f.t_start - info["t"]) < 30]})
            elif info["killed"] and seq > last_seq.get(src, -1):
                lost_with_worker += info["n"]
                per_kill[("worker", src)] = per_kill.get(("worker", src), 0) + 1
            elif self.cfg.backend == "nats":
                unexplained += info["n"]  # the stream keeps what it stored; a worker, what it did not
            elif any(held_at(tk, src, seq, info["t"]) for tk in server_kills):
                lost_with_server += info["n"]
                tk = next(tk for tk in server_kills if held_at(tk, src, seq, info["t"]))
                per_kill[("server", tk)] = per_kill.get(("server", tk), 0) + 1
            elif any(held_at(tk, src, seq, info["t"]) for tk in trainer_deaths):
                lost_in_trainer_link += info["n"]
                tk = next(tk for tk in trainer_deaths if held_at(tk, src, seq, info["t"]))
                per_kill[("trainer_link", tk)] = per_kill.get(("trainer_link", tk), 0) + 1
            else:
                unexplained += info["n"]
        worst = {kind: max((n for (k, _), n in per_kill.items() if k == kind), default=0)
                 for kind in TLSPYO_LOSS_BOUNDS}
        finals = self.select("final", "trainer")
        last = finals[-1] if finals else {}
        rounds = self.select("round", "trainer")
        per_inc: dict[int, dict[str, Any]] = {}
        for e in rounds + finals:
            per_inc[e["inc"]] = e
        produced = sum(i["n"] for i in payloads.values())
        got = sum(received.values())
        stored = last.get("total_samples")
        return {
            "produced": produced,
            "payloads": len(payloads),
            "acknowledged": sum(i["n"] for i in payloads.values() if i["acked"]) if self.cfg.backend == "nats" else None,
            "received": got,
            "stored": stored,
            "lost_acknowledged": lost_acked if self.cfg.backend == "nats" else None,
            "lost_acknowledged_payloads": lost_detail,
            "lost_with_killed_workers": lost_with_worker,
            "lost_with_killed_servers": lost_with_server,
            "lost_in_killed_trainer_links": lost_in_trainer_link,
            "lost_unexplained": unexplained,
            "loss_worst_kill_payloads": worst,
            "loss_within_bounds": all(worst[k] <= TLSPYO_LOSS_BOUNDS[k] for k in worst),
            "lost_with_killed_trainers": None if stored is None else got - stored,
            "trainer_lost_payloads": sum(e.get("lost_payloads") or 0 for e in per_inc.values()),
            "trainer_duplicate_payloads": sum(e.get("duplicate_payloads") or 0 for e in per_inc.values()),
            "worker_link_dropped": sum(e.get("link_dropped") or 0 for e in self.select("final")
                                       if e["role"].startswith("worker")),
        }

    def evaluate(self) -> float | None:
        if not self.cfg.evaluate or not (self.workdir / "trainer.tmod").exists():
            return None
        path = self._write_config("eval", {"episodes": self.cfg.evaluate})
        done = subprocess.run([sys.executable, str(harness.CHILD), "chaos", "--role", "eval", "--config", str(path),
                               "--name", "eval"], capture_output=True, text=True, env=self.env, timeout=300,
                              check=False)
        for line in done.stdout.splitlines():
            if line.startswith("{"):
                ev = json.loads(line)
                self.final_eval = {k: ev[k] for k in ("lap_time", "progress") if k in ev}
                return ev.get("ret")
        self.notes.append(f"evaluation failed: {done.stderr.strip().splitlines()[-1:] }")
        return None

    def cleanup(self, keep: bool) -> None:
        self.stop_event.set()
        for role in self.roles.values():
            role.stop(5.0)
        for proxies in self.proxies.values():
            for p in proxies:
                p.close()
        self._events_file.close()
        if self.mounted:
            subprocess.run(["umount", "-l", str(self.checkpoint.parent)], capture_output=True, check=False)
            self.mounted = False
        if not keep:
            shutil.rmtree(self.workdir, ignore_errors=True)

    # --- the run ----------------------------------------------------------------------------------

    def run(self) -> dict[str, Any]:
        cfg = self.cfg
        t0 = time.time()
        self.setup()
        warm = self.warm_up()
        self.say(f"warm: samples and weights flow after {warm:.1f} s; faults for {cfg.minutes:g} min"
                 if cfg.cycle else f"warm after {warm:.1f} s; {len(cfg.faults)} faults")
        rss_start = self.rss()
        t_warm = t_faults = time.time()
        threading.Thread(target=self._sample_rss, daemon=True, name="chaos-rss").start()
        if cfg.evaluate and cfg.learning:
            evaluator = self._add_role("evaluator", "evalloop", {"episodes": cfg.evaluate, "every": cfg.eval_every})
            evaluator.restart_loop = False
            evaluator.start()
        for kind in self.schedule():
            fault = self.inject(kind)
            self.measure(fault)
            if cfg.stop_on_unrecovered and (fault.flow_s is None or fault.weights_s is None):
                self.notes.append(f"faults ended after {kind}: not recovered from")
                break
            if cfg.gap[1] > 0:
                self.stop_event.wait(self.rng.uniform(*cfg.gap))  # the calm between two faults
        rss_end = self.rss()
        t_faults_end = time.time()
        if "evaluator" in self.roles:
            self.roles["evaluator"].stop(5.0)
        rss_figures = self.rss_figures(t_faults, t_faults_end)
        learning = self.learning(t_warm)
        end = self.drain_and_stop()
        self.elections()
        figures = self.account()
        ret = self.evaluate()
        kinds: dict[str, dict[str, Any]] = {}
        for f in self.faults:
            k = kinds.setdefault(f.kind, {"n": 0, "flow": [], "weights": [], "not_recovered": 0})
            k["n"] += 1
            if f.flow_s is None or f.weights_s is None:
                k["not_recovered"] += 1
            if f.flow_s is not None:
                k["flow"].append(f.flow_s)
            if f.weights_s is not None:
                k["weights"].append(f.weights_s)
        return {
            "backend": cfg.backend, "env": cfg.env, "workers": cfg.workers, "seed": cfg.seed, "profile": cfg.profile,
            "nats_nodes": cfg.nats_nodes if cfg.backend == "nats" else None, "marker": self.marker,
            "wall_s": time.time() - t0, "warmup_s": warm, **figures, **end,
            "rss_start_mib": rss_start, "rss_end_mib": rss_end, "rss_mid_mib": rss_figures["mid"],
            "rss_late_mib": rss_figures["end"], "rss_mark_s": rss_figures["mark_s"],
            "go_heap_mid_mib": rss_figures["heap_mid"], "go_heap_late_mib": rss_figures["heap_end"],
            "learning": learning,
            "faults": [asdict(f) for f in self.faults],
            "recovery": {k: {"n": v["n"], "not_recovered": v["not_recovered"],
                             "flow_median_s": _median(v["flow"]), "flow_max_s": max(v["flow"], default=None),
                             "weights_median_s": _median(v["weights"]), "weights_max_s": max(v["weights"], default=None)}
                         for k, v in kinds.items()},
            "elections": self.election_figures(),
            "restarts": {n: r.restarts for n, r in self.roles.items()},
            "test_return": ret, "test_extra": self.final_eval, "notes": self.notes, "workdir": str(self.workdir),
        }


def _median(values: list[float]) -> float | None:
    return statistics.median(values) if values else None


def _cmdline(pid: int) -> str:
    if not LINUX:
        raise RuntimeError(NEEDS_LINUX)
    try:
        with open(f"/proc/{pid}/cmdline", "rb") as f:
            return f.read().replace(b"\0", b" ").decode(errors="replace")[:200]
    except OSError:
        return "?"


def run_chaos(cfg: ChaosConfig, keep: bool = False) -> dict[str, Any]:
    """Run ``cfg`` and return its figures (the work folder is removed unless ``keep``)."""
    chaos = Chaos(cfg)
    failed = True
    try:
        result = chaos.run()
        failed = False
        return result
    finally:
        chaos.cleanup(keep=keep or failed)
        if failed:
            cfg.log(f"  logs kept in {chaos.workdir}")


# ================================================================================================
# the command


def _fmt_s(value: float | None) -> str:
    return "-" if value is None else f"{value:.1f}"


def _rows(results: dict[str, dict[str, Any]]) -> list[tuple[str, list[str]]]:
    """The table: one row per figure, one column per backend."""
    backends = list(results)

    def row(label: str, fn: Callable[[dict[str, Any]], Any]) -> tuple[str, list[str]]:
        cells = []
        for b in backends:
            try:
                v = fn(results[b])
            except (KeyError, TypeError, ZeroDivisionError):
                v = None
            cells.append("-" if v is None else (harness.fmt(v) if isinstance(v, (int, float)) and not isinstance(v, bool)
                                                 else str(v)))
        return label, cells

    rows = [
        row("faults injected", lambda r: len(r["faults"])),
        row("  not recovered", lambda r: sum(k["not_recovered"] for k in r["recovery"].values())),
        row("load average (start / end)", lambda r: f"{r['load_start']:.1f} / {r['load_end']:.1f}"),
        row("samples produced", lambda r: r["produced"]),
        row("  acknowledged by the stream", lambda r: r["acknowledged"]),
        row("  received by a trainer", lambda r: r["received"]),
        row("  stored (final trainer's memory)", lambda r: r["stored"]),
        row("lost: acknowledged, never received", lambda r: r["lost_acknowledged"]),
        row("lost: unexplained", lambda r: r["lost_unexplained"]),
        row("lost: with a killed worker (unsent)", lambda r: r["lost_with_killed_workers"]),
        row("lost: held by a killed server", lambda r: r["lost_with_killed_servers"]),
        row("lost: in a killed trainer's link", lambda r: r["lost_in_killed_trainer_links"]),
        row("lost: received, not checkpointed", lambda r: r["lost_with_killed_trainers"]),
        row("lost payloads, worst kill: server / trainer link / worker",
            lambda r: " / ".join(f"{r['loss_worst_kill_payloads'][k]}" for k in TLSPYO_LOSS_BOUNDS)
            + (" (within bounds)" if r["loss_within_bounds"] else " (OVER the bounds)")),
        row("worker links: batches dropped", lambda r: r["worker_link_dropped"]),
        row("trainer: lost / duplicate payloads", lambda r: f"{r['trainer_lost_payloads']} / "
                                                            f"{r['trainer_duplicate_payloads']}"),
    ]
    kinds = [k for k in FAULT_KINDS if any(k in r["recovery"] for r in results.values())]
    for kind in kinds:
        rows.append(row(f"recovery {kind} (n): samples median / max s",
                        lambda r, k=kind: f"({r['recovery'][k]['n']}) {_fmt_s(r['recovery'][k]['flow_median_s'])} / "
                                          f"{_fmt_s(r['recovery'][k]['flow_max_s'])}"
                        + (f" [{r['recovery'][k]['not_recovered']} not]" if r['recovery'][k]['not_recovered'] else "")))
        rows.append(row("    weights median / max s",
                        lambda r, k=kind: f"{_fmt_s(r['recovery'][k]['weights_median_s'])} / "
                                          f"{_fmt_s(r['recovery'][k]['weights_max_s'])}"))
    def elections(r: dict[str, Any], what: str) -> str | None:
        e = (r.get("elections") or {}).get(what)
        if not e or not e.get("n"):
            return None
        return (f"({e['n']}) {_fmt_s(e['election_median_s'])} ({_fmt_s(e['election_max_s'])}) / "
                f"{_fmt_s(e['beyond_median_s'])} ({_fmt_s(e['beyond_max_s'])})")

    for what in ("samples",):  # the weights come back before their buckets' logged elections, often: not a floor
        if any((r.get("elections") or {}).get(what, {}).get("n") for r in results.values()):
            rows.append(row(f"node kills taking a {what} leader (n): election / recovery after it, median (max) s",
                            lambda r, w=what: elections(r, w)))
    roles = sorted({n for r in results.values() for n in r["rss_start_mib"]})
    for name in roles:
        def rss(r: dict[str, Any], n: str = name) -> str | None:
            a, m, b = r["rss_start_mib"].get(n), r["rss_mid_mib"].get(n), r["rss_late_mib"].get(n)
            if a is None or m is None or b is None:
                return None
            return f"{a:.0f}, {m:.0f} -> {b:.0f} ({100 * (b - m) / m:+.1f} %)"
        rows.append(row(f"RSS MiB {name} (start, mark -> end)", rss))
    for name in sorted({n for r in results.values() for n in r.get("go_heap_mid_mib") or {}}):
        def heap(r: dict[str, Any], n: str = name) -> str | None:
            m, b = (r.get("go_heap_mid_mib") or {}).get(n), (r.get("go_heap_late_mib") or {}).get(n)
            if not m or not b or "alloc" not in m or "alloc" not in b:
                return None
            kept = f", kept {m.get('idle', 0) - m.get('released', 0):.0f} -> {b.get('idle', 0) - b.get('released', 0):.0f}"
            return f"{m['alloc']:.0f} -> {b['alloc']:.0f}{kept}"
        rows.append(row(f"  Go heap MiB {name} (mark -> end: in use{', freed and kept'})", heap))
    rows += [
        row("restarts (trainer / server / workers)",
            lambda r: f"{r['restarts'].get('trainer', 0)} / "
                      f"{sum(v for k, v in r['restarts'].items() if not k.startswith(('trainer', 'worker')))} / "
                      f"{sum(v for k, v in r['restarts'].items() if k.startswith('worker'))}"),
        row("stopped by SIGTERM", lambda r: f"{sum(r['stopped_cleanly'].values())} of {len(r['stopped_cleanly'])}"),
        row("processes left", lambda r: r["processes_left"]),
    ]
    env = next(iter(results.values()), {}).get("env", "pendulum")
    return rows + (_learning_rows(row) if chaos_env.THRESHOLDS[env] is None else [
        row(f"learning: samples to a test return > {THRESHOLD:g} (s)",
            lambda r: None if not r["learning"]["evaluations"] else
            (f"{r['learning']['samples']:,} ({r['learning']['s']:.0f} s, after {r['learning']['faults_before']} faults)"
             if r["learning"]["reached"] else f"not reached (best {r['learning']['best']:.0f})")),
        row(f"Pendulum test return (> {THRESHOLD:g}?)",
            lambda r: None if r["test_return"] is None else f"{r['test_return']:.0f} "
                                                           f"({'yes' if r['test_return'] > THRESHOLD else 'no'})"),
    ])


def _learning_rows(row: Callable[[str, Callable[[dict[str, Any]], Any]], tuple[str, list[str]]]
                   ) -> list[tuple[str, list[str]]]:
    """The simulator's learning rows (no threshold: how far its test return rose during the faults)."""

    def lap(extra: dict[str, Any]) -> str:
        if extra.get("lap_time") is not None:
            return f"lap {extra['lap_time']:.1f} s"
        return "no lap" + (f", {100 * extra['progress']:.0f} % of it" if extra.get("progress") is not None else "")

    return [
        row("learning: test return first -> best (rising; evaluations)",
            lambda r: None if not r["learning"]["evaluations"] else
            f"{r['learning']['first']:.1f} -> {r['learning']['best']:.1f} ({r['learning']['rising']:+.1f}; "
            f"{r['learning']['evaluations']})"),
        row("  best (first within 1 %): s after warm, samples",
            lambda r: None if not r["learning"]["evaluations"] else
            f"{r['learning']['best_at']['s']:.0f} s, {r['learning']['best_at']['samples']:,}"),
        row("  first test lap: s after warm, samples (laps, best lap s)",
            lambda r: None if not r["learning"]["evaluations"] else
            (f"none (best {100 * r['learning']['best_progress']:.0f} % of a lap)" if not r["learning"]["first_lap"]
             else f"{r['learning']['first_lap']['s']:.0f} s, {r['learning']['first_lap']['samples']:,} "
                  f"({r['learning']['laps']}, {r['learning']['best_lap']:.1f})")),
        row("simulator test return at the end",
            lambda r: None if r["test_return"] is None else
            f"{r['test_return']:.1f} ({lap(r.get('test_extra') or {})})"),
    ]


def print_table(results: dict[str, dict[str, Any]]) -> None:
    rows = _rows(results)
    width = max(len(label) for label, _ in rows)
    cols = [max(len(b), *(len(cells[i]) for _, cells in rows)) for i, b in enumerate(results)]
    print()
    print(f"{'':{width}}  " + "  ".join(f"{b:>{w}}" for b, w in zip(results, cols)))
    for label, cells in rows:
        print(f"{label:{width}}  " + "  ".join(f"{c:>{w}}" for c, w in zip(cells, cols)))


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(prog="python -m bench chaos", description=__doc__.split("\n\n")[0])
    ap.add_argument("--minutes", type=float, default=10.0, help="minutes of faults per backend (default 10)")
    ap.add_argument("--quick", action="store_true", help="2 minutes per backend")
    ap.add_argument("--backends", default="tlspyo,nats", help="comma-separated: tlspyo, nats")
    ap.add_argument("--workers", type=int, default=4)
    ap.add_argument("--env", choices=chaos_env.ENVS, default="pendulum",
                    help="pendulum (Pendulum-v1, the default) or sim (the built-in driving simulator, lidar, "
                         "track oval): bench/chaos_env.py")
    ap.add_argument("--nats-nodes", type=int, choices=(1, 3), default=3,
                    help="3: a NATS cluster on 127.0.0.1 run by this command; 1: tmrl's supervised nats-server")
    ap.add_argument("--seed", type=int, default=0, help="draws the fault schedule (and seeds the roles)")
    ap.add_argument("--faults", default=",".join(FAULT_KINDS), help=f"among {', '.join(FAULT_KINDS)}")
    ap.add_argument("--no-faults", action="store_true", help="the same run without faults (a reference)")
    ap.add_argument("--eval-episodes", type=int, default=10,
                    help="test episodes at each evaluation (the simulator's are deterministic: one is driven)")
    ap.add_argument("--recovery-timeout", type=float, default=60.0)
    ap.add_argument("--gap", default="2,5", help="seconds between a recovery and the next fault: LOW,HIGH")
    ap.add_argument("--memory-size", type=int, default=None,
                    help="the trainer's replay memory, in samples (Pendulum; default "
                    f"{PROFILES['bench']['memory_size']:,}): a memory full early tells the roles' memory growth "
                    "from the memory filling")
    ap.add_argument("--eval-every", type=float, default=2.0,
                    help="seconds between two evaluations while the faults run (pendulum: until the test return "
                         f"first passes {THRESHOLD:g}; sim: until the faults end); 0: evaluate only at the end")
    ap.add_argument("--keep", action="store_true", help="keep the work folders (logs, events.jsonl)")
    args = ap.parse_args(argv)
    if not LINUX:
        ap.error(NEEDS_LINUX)
    signal.signal(signal.SIGTERM, _interrupt)  # `kill` ends the run as Ctrl-C does: its roles are stopped
    minutes = 2.0 if args.quick else args.minutes
    backends = [b for b in args.backends.split(",") if b]
    if set(backends) - {"tlspyo", "nats"}:
        ap.error(f"unknown backend(s) {sorted(set(backends) - {'tlspyo', 'nats'})}")
    faults = () if args.no_faults else tuple(k for k in args.faults.split(",") if k)
    if set(faults) - set(FAULT_KINDS):
        ap.error(f"unknown fault kind(s) {sorted(set(faults) - set(FAULT_KINDS))}")
    try:
        gap = tuple(float(x) for x in args.gap.split(","))
        if len(gap) != 2 or not 0 <= gap[0] <= gap[1]:
            raise ValueError
    except ValueError:
        ap.error(f"--gap must be LOW,HIGH seconds (0 <= LOW <= HIGH), not {args.gap!r}")
    if args.memory_size is not None:
        if args.memory_size < PROFILES["bench"]["batch_size"]:
            ap.error(f"--memory-size must be at least the batch size ({PROFILES['bench']['batch_size']})")
        PROFILES["bench"]["memory_size"] = args.memory_size  # written into every role's settings
    settings = {"minutes": minutes, "gap_s": list(gap), "eval_every_s": args.eval_every, "workers": args.workers, "nats_nodes": args.nats_nodes, "seed": args.seed,
                "faults": list(faults), "env": args.env,
                "profile": chaos_env.profile(args.env, "bench", PROFILES["bench"]), "durations": DURATIONS,
                "recovery_timeout_s": args.recovery_timeout, "eval_episodes": args.eval_episodes}
    rec = harness.Recorder("chaos", settings)
    results: dict[str, dict[str, Any]] = {}
    for backend in backends:
        cfg = ChaosConfig(backend=backend, workers=args.workers, faults=faults, minutes=minutes, seed=args.seed,
                          profile="bench", env=args.env, nats_nodes=args.nats_nodes,
                          recovery_timeout=args.recovery_timeout,
                          evaluate=args.eval_episodes, learning=args.eval_every > 0,
                          eval_every=max(args.eval_every, 0.0), gap=gap)
        load_start = harness.load_average()
        print(f"{backend}: {args.env}, {minutes:g} min, {args.workers} workers"
              + (f", NATS nodes {args.nats_nodes}" if backend == "nats" else "") + f", load {load_start:.2f}",
              flush=True)
        res = run_chaos(cfg, keep=args.keep)
        res.update(load_start=load_start, load_end=harness.load_average())
        results[backend] = res
        for key in ("produced", "acknowledged", "received", "stored", "lost_acknowledged", "lost_unexplained",
                    "lost_with_killed_workers", "lost_with_killed_servers", "lost_in_killed_trainer_links",
                    "lost_with_killed_trainers", "worker_link_dropped", "processes_left", "test_return"):
            rec.add(backend, key, "ours", res.get(key), echo=False)
        if chaos_env.THRESHOLDS[args.env] is not None:
            rec.add(backend, "samples_to_threshold", "ours", res["learning"].get("samples"), higher_is_better=False,
                    echo=False)
        else:
            for key in ("first", "best", "rising"):
                rec.add(backend, f"test_return_{key}", "ours", res["learning"].get(key), echo=False)
        for kind, r in res["recovery"].items():
            for metric in ("flow_median_s", "flow_max_s", "weights_median_s", "weights_max_s"):
                rec.add(f"{backend} {kind}", metric, "ours", r[metric], higher_is_better=False, unit="s", echo=False)
        for name, mib in res["rss_late_mib"].items():
            mid = res["rss_mid_mib"].get(name)
            rec.add(f"{backend} {name}", "rss_growth_pct", "ours",
                    None if not mid or mib is None else 100 * (mib - mid) / mid, higher_is_better=False,
                    unit="%", echo=False)
        rec.add(backend, "result", "ours", None, echo=False, detail=res)
        for note in res["notes"]:
            print(f"  note: {note}")
    print_table(results)
    rec.close()
