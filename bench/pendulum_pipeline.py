"""Pendulum-v1 through a server, a trainer and a worker (three processes), ours beside tmrl 0.7.1
on the same settings: wall time, environment steps and updates until the mean test return
exceeds -200.

    python -m bench pendulum_pipeline                              # both profiles, 5 seeds per side
    python -m bench pendulum_pipeline --profiles recommended --seeds 3 --timeout 300
    python -m bench pendulum_pipeline --profiles tutorial --seeds 1 --py-spy /tmp/spy   # where the time goes
    python -m bench pendulum_pipeline --spy-summary /tmp/spy

Two profiles, each one settings dict applied to both sides (the original accepts every one of
those arguments, ``hidden_sizes`` included):

- ``tutorial``: the original's own minimal Pendulum tutorial (256x256, batch 32, lr 1e-3, 0.2
  updates per environment step, weights and samples exchanged at every update, 1 s buffer polls,
  a test episode every 10 episodes, worker pacing 100/10/True);
- ``recommended``: our recommended settings (64x64, batch 256, lr 3e-3, at most 1 update per
  environment step, exchange every 20 updates, 0.01 s polls, no test episodes, worker pacing
  1000/40/False).

Both sides checkpoint at the end of every epoch (the original always does) and load weights the
same way. Seeds alternate the order of the sides (ours, tmrl, then tmrl, ours...). Our SAC runs
its default update order (the actor loss reads the critics before their step);
``--update-order sequential`` gives it the original's (after their step). Our worker starts
every episode with the newest weights it received; ``--weights-when-waiting-only`` gives it the
original's behaviour (weights loaded only when the worker has to wait for them).

How it measures: a fourth process (the evaluator, the same code on both sides) reloads the
trainer's weights file when it changed, at most every ``--eval-every`` seconds (a failed load is
retried 50 ms later: the original writes that file in place, ours moves a new one there), and
runs ``--eval-episodes`` deterministic episodes; the worker's environment writes its step count to a file, the trainer
its update count. The clock starts when the processes are launched (start-up, imports and
connection included) and stops at the first evaluation above the threshold. The steps and
updates to the threshold come from snapshots of the weights file taken every ``--grid``
environment steps: once an evaluation passes, the snapshots made since the evaluation before it
are evaluated in order and the first that passes gives the counts (the passing evaluation's own
counts are kept as ``steps_eval``, ``updates_eval``): evaluations every 2 s would otherwise count
against the side that steps faster, which takes more steps between two of them. A run that does not
get there within the profile's timeout (``--timeout``) counts as not reached, and is listed with
its last evaluation at the end. Each side's rates over the run (environment steps and updates
per second, at its last evaluation) are printed beside the figures.

Where the time goes: ``--py-spy DIR`` records every role process and the processes it started
(network processes) with py-spy, from ``--py-spy-after`` seconds for ``--py-spy-for`` seconds, and
their CPU use; ``--spy-summary DIR`` prints, per side and role, the share of the main thread's
wall time in each part (the update, the weights publish, the samples' ingest; the worker's
environment step, actor inference, weights install...) and each process's CPU seconds per second.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import sys
import tempfile
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from bench import harness

THRESHOLD = -200.0

PROFILES: dict[str, dict[str, Any]] = {
    "tutorial": dict(
        hidden_sizes=[256, 256], batch_size=32, memory_size=1_000_000, lr=1e-3, gamma=0.99, polyak=0.995,
        alpha=0.2, rounds=10, steps_per_round=1000, update_model_interval=1, update_buffer_interval=1,
        max_training_steps_per_env_step=0.2, start_training=100, poll_wait=1.0,
        initial_steps=100, max_steps_per_update=10, end_episodes=True, test_episode_interval=10,
        max_samples_per_episode=1000,
    ),
    "recommended": dict(
        hidden_sizes=[64, 64], batch_size=256, memory_size=1_000_000, lr=3e-3, gamma=0.99, polyak=0.995,
        alpha=0.2, rounds=10, steps_per_round=500, update_model_interval=20, update_buffer_interval=20,
        max_training_steps_per_env_step=1.0, start_training=1000, poll_wait=0.01,
        initial_steps=1000, max_steps_per_update=40, end_episodes=False, test_episode_interval=0,
        max_samples_per_episode=1000,
    ),
}
"""Each profile is applied to both sides."""

TIMEOUTS = {"tutorial": 300.0, "recommended": 120.0}
"""Default seconds per run, per profile: long enough for every run of both sides to get there on a
loaded 2-core machine (tmrl 0.7.1 took up to 117 s on the tutorial's settings at load 6), so that
a run that does not is a result, not a cut. Typically both profiles, 5 seeds per side, take about
15 minutes."""


# --- inside the role processes (either interpreter) ---------------------------------------------


def _seed(seed: int) -> None:
    import random

    import numpy as np
    import torch

    random.seed(seed)
    np.random.seed(seed)
    torch.manual_seed(seed)


class _RunningCount:
    """A running count that the driver and the evaluator read (:func:`harness.read_int`), rewritten
    in place every ``every`` counts, at a fixed width (a file renamed over the old one cost the
    worker about 5% of its time: ext4 writes a renamed file out at once)."""

    def __init__(self, path: Path, every: int) -> None:
        self.fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644)
        self.every = every
        self.n = 0

    def add(self) -> None:
        self.n += 1
        if self.n % self.every == 0:
            os.pwrite(self.fd, b"%20d\n" % self.n, 0)


def _counting_env(env: Any, steps_file: Path) -> Any:
    """``env`` whose ``step`` writes its running count to ``steps_file`` every 50 steps."""
    step = env.step
    count = _RunningCount(steps_file, 50)

    def counted(action: Any) -> Any:
        count.add()
        return step(action)

    env.step = counted
    return env


def _count_updates(agent_cls: type, updates_file: Path) -> None:
    """Make ``agent_cls.train`` write its running count to ``updates_file`` every 20 calls (the
    class itself is patched, in the trainer process only, so that the original's pickled
    checkpoints still find it by name)."""
    train = agent_cls.train
    count = _RunningCount(updates_file, 20)

    def counted(self: Any, batch: Any) -> Any:
        out = train(self, batch)
        count.add()
        return out

    agent_cls.train = counted


def _imports(impl: str) -> dict[str, Any]:
    """The classes each side's tutorial uses, by role."""
    if impl == "ours":
        from tmrl.algorithms.sac import SACAgent
        from tmrl.envs import GenericGymEnv
        from tmrl.memory import GenericTorchMemory
        from tmrl.models import MLPActorCritic, SquashedGaussianMLPActor
        from tmrl.networking import RolloutWorker, Server, Trainer
        from tmrl.training_offline import TorchTrainingOffline
        from tmrl.util import partial
    else:
        from tmrl.custom.custom_algorithms import SpinupSacAgent as SACAgent
        from tmrl.custom.custom_memories import GenericTorchMemory
        from tmrl.custom.custom_models import MLPActorCritic, SquashedGaussianMLPActor
        from tmrl.envs import GenericGymEnv
        from tmrl.networking import RolloutWorker, Server, Trainer
        from tmrl.training_offline import TorchTrainingOffline
        from tmrl.util import partial
    return dict(SACAgent=SACAgent, GenericGymEnv=GenericGymEnv, GenericTorchMemory=GenericTorchMemory,
                MLPActorCritic=MLPActorCritic, Actor=SquashedGaussianMLPActor, RolloutWorker=RolloutWorker,
                Server=Server, Trainer=Trainer, TorchTrainingOffline=TorchTrainingOffline, partial=partial)


def _trainer(impl: str, s: dict[str, Any], workdir: Path, port: int, update_order: str | None = None) -> None:
    import gymnasium

    m = _imports(impl)
    partial = m["partial"]
    _count_updates(m["SACAgent"], workdir / "updates")
    order = {} if update_order is None or impl == "tmrl" else {"update_order": update_order}
    env = gymnasium.make("Pendulum-v1")
    training_cls = partial(
        m["TorchTrainingOffline"],
        env_cls=(env.observation_space, env.action_space),
        memory_cls=partial(m["GenericTorchMemory"], memory_size=s["memory_size"], batch_size=s["batch_size"],
                           crc_debug=False),
        training_agent_cls=partial(
            m["SACAgent"], model_cls=partial(m["MLPActorCritic"], hidden_sizes=tuple(s["hidden_sizes"])),
            gamma=s["gamma"], polyak=s["polyak"], alpha=s["alpha"], lr_actor=s["lr"], lr_critic=s["lr"],
            lr_entropy=s["lr"], learn_entropy_coef=True, target_entropy=None, **order,
        ),
        epochs=1000, rounds=s["rounds"], steps=s["steps_per_round"],
        update_buffer_interval=s["update_buffer_interval"], update_model_interval=s["update_model_interval"],
        max_training_steps_per_env_step=s["max_training_steps_per_env_step"], start_training=s["start_training"],
        device="cpu", sleep_between_buffer_retrieval_attempts=s["poll_wait"],
    )
    m["Trainer"](training_cls=training_cls, server_ip="127.0.0.1", server_port=port, password="bench-password",
                 model_path=str(workdir / "model_trainer.tmod"), checkpoint_path=str(workdir / "checkpoint"),
                 security=None).run()


def _worker(impl: str, s: dict[str, Any], workdir: Path, port: int, newest: bool = True) -> None:
    m = _imports(impl)
    pickup = {} if newest or impl == "tmrl" else {"newest_each_episode": False}
    worker = m["RolloutWorker"](
        env_cls=lambda: _counting_env(m["GenericGymEnv"](id="Pendulum-v1", gym_kwargs={"render_mode": None}),
                                      workdir / "steps"),
        actor_module_cls=m["partial"](m["Actor"], hidden_sizes=tuple(s["hidden_sizes"])),
        sample_compressor=None, device="cpu", server_ip="127.0.0.1", server_port=port, password="bench-password",
        max_samples_per_episode=s["max_samples_per_episode"], model_path=str(workdir / "model_worker.tmod"),
        model_history=0, crc_debug=False, security=None,
    )
    worker.run_synchronous(test_episode_interval=s["test_episode_interval"], initial_steps=s["initial_steps"],
                           max_steps_per_update=s["max_steps_per_update"], end_episodes=s["end_episodes"], **pickup)


def _test_return(actor: Any, env: Any, episodes: int, first_seed: int) -> float:
    """Mean return of ``episodes`` deterministic episodes of ``actor``, seeds from ``first_seed``."""
    import numpy as np
    import torch

    returns = []
    for i in range(episodes):
        obs, _ = env.reset(seed=first_seed + i)
        ret, done = 0.0, False
        while not done:
            with torch.no_grad():
                act = actor.act_(np.asarray(obs, np.float32), test=True)
            act = np.asarray(act, np.float32).reshape(env.action_space.shape)
            obs, rew, terminated, truncated, _ = env.step(act)
            ret += float(rew)
            done = terminated or truncated
        returns.append(ret)
    return sum(returns) / len(returns)


class _Snapshots(threading.Thread):
    """Copies of the trainer's weights file on a grid of environment steps: each time the step
    counter passes the next multiple of ``grid``, the file's bytes with the step and update counts
    read then. The evaluator takes them in batches (:meth:`take`): those made since its last
    evaluation, so that only a few seconds of them are ever kept."""

    def __init__(self, path: Path, workdir: Path, t0: float, grid: int) -> None:
        super().__init__(daemon=True, name="snapshots")
        self.path, self.workdir, self.t0, self.grid = path, workdir, t0, grid
        self.lock = threading.Lock()
        self.taken: list[dict[str, Any]] = []

        self.due = grid

    def run(self) -> None:
        while True:
            time.sleep(0.01)
            self.poll()

    def poll(self) -> bool:
        """Take a snapshot if the step counter passed the next grid line; whether one was taken."""
        steps = harness.read_int(self.workdir / "steps")
        if steps < self.due:
            return False
        try:
            before = self.path.stat().st_mtime_ns
            data = self.path.read_bytes()
            if self.path.stat().st_mtime_ns != before:
                return False  # written in place while read (the original's): again at the next poll
        except OSError:
            return False
        snap = {"steps": steps, "updates": harness.read_int(self.workdir / "updates"),
                "t_read": time.monotonic() - self.t0, "data": data}
        with self.lock:
            self.taken.append(snap)
        self.due = (steps // self.grid + 1) * self.grid
        return True

    def take(self) -> list[dict[str, Any]]:
        with self.lock:
            out, self.taken = self.taken, []
        return out


def first_passing(window: list[dict[str, Any]], steps_now: int,
                  test: Callable[[bytes], float | None]) -> tuple[dict[str, Any] | None, int]:
    """The first snapshot of ``window`` (in order) taken before ``steps_now`` whose test return
    passes :data:`THRESHOLD`, without its data and with its return; and how many were tested.
    ``test`` returns None for a snapshot it cannot load (skipped)."""
    tried = 0
    for snap in window:
        if snap["steps"] >= steps_now:
            break
        ret = test(snap["data"])
        if ret is None:
            continue
        tried += 1
        if ret > THRESHOLD:
            return {k: v for k, v in snap.items() if k != "data"} | {"ret": ret}, tried
    return None, tried


def _evaluate(impl: str, s: dict[str, Any], workdir: Path, episodes: int, every: float, t0: float,
              grid: int = 0) -> None:
    """Evaluate the trainer's weights when its file changed, at most once every ``every`` seconds;
    one JSON line per evaluation.

    With ``grid`` (environment steps), an evaluation that passes :data:`THRESHOLD` is followed by
    the evaluation, in order, of the snapshots made on that grid since the previous evaluation
    (:class:`_Snapshots`); its line then carries ``first``: the first of them that passes, or this
    evaluation itself. Steps and updates to the threshold then no longer depend on how fast a side
    steps: with evaluations every ``every`` seconds, a side that takes more steps per second also
    takes more steps between the moment its weights first pass and the next evaluation."""
    import gymnasium
    import torch

    torch.set_num_threads(1)
    env = gymnasium.make("Pendulum-v1")
    actor = _imports(impl)["Actor"](env.observation_space, env.action_space, hidden_sizes=tuple(s["hidden_sizes"]))
    path = workdir / "model_trainer.tmod"
    snapshots = None
    if grid:
        snapshots = _Snapshots(path, workdir, t0, grid)
        snapshots.start()
    last_mtime, episode_seed, next_eval = None, 10_000, time.monotonic()
    while True:
        time.sleep(max(0.0, next_eval - time.monotonic()))
        try:
            mtime = path.stat().st_mtime_ns
            if mtime == last_mtime:
                time.sleep(0.05)
                continue
            t_read = time.monotonic() - t0
            steps, updates = harness.read_int(workdir / "steps"), harness.read_int(workdir / "updates")
            actor = actor.load(str(path), device="cpu")
            window = snapshots.take() if snapshots is not None else []  # after the load: a failed one keeps them
            last_mtime, next_eval = mtime, time.monotonic() + every
        except Exception:  # noqa: BLE001 (missing, or being written in place by the original: retry soon)
            time.sleep(0.05)
            continue
        ret = _test_return(actor, env, episodes, episode_seed)
        episode_seed += episodes
        rec: dict[str, Any] = {"t": time.monotonic() - t0, "t_read": t_read, "steps": steps, "updates": updates,
                               "ret": ret}
        if ret > THRESHOLD and snapshots is not None:
            snap_file = workdir / "snapshot.tmod"

            def test(data: bytes, snap_file: Path = snap_file, actor: Any = actor) -> float | None:
                nonlocal episode_seed
                snap_file.write_bytes(data)
                try:
                    candidate = actor.load(str(snap_file), device="cpu")
                except Exception:  # noqa: BLE001 (a copy of a file the original was writing: skipped)
                    return None
                episode_seed += episodes
                return _test_return(candidate, env, episodes, episode_seed - episodes)

            first, tried = first_passing(window, steps, test)
            first = (dict(first, snapshot=True) if first is not None else
                     {"steps": steps, "updates": updates, "t_read": t_read, "ret": ret, "snapshot": False})
            rec["first"] = dict(first, snapshots=len(window), tried=tried)
        harness.print_json(rec)


def child_main(argv: list[str]) -> None:
    """One role of one side: ``--impl ours|tmrl --role server|trainer|worker|eval``."""
    p = argparse.ArgumentParser()
    for name in ("--impl", "--role", "--profile", "--workdir"):
        p.add_argument(name, required=True)
    p.add_argument("--port", type=int, required=True)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--eval-episodes", type=int, default=10)
    p.add_argument("--eval-every", type=float, default=2.0)
    p.add_argument("--t0", type=float, default=0.0)
    p.add_argument("--grid", type=int, default=0)
    p.add_argument("--update-order", default=None)
    p.add_argument("--weights-when-waiting-only", action="store_true")
    args = p.parse_args(argv)
    s, workdir = PROFILES[args.profile], Path(args.workdir)
    _seed(args.seed * 10 + ("server", "trainer", "worker", "eval").index(args.role))
    if args.role == "server":
        server = _imports(args.impl)["Server"](port=args.port, password="bench-password", security=None)
        try:
            while True:
                time.sleep(1.0)
        finally:
            if hasattr(server, "stop"):
                server.stop()
    elif args.role == "trainer":
        _trainer(args.impl, s, workdir, args.port, args.update_order)
    elif args.role == "worker":
        _worker(args.impl, s, workdir, args.port, not args.weights_when_waiting_only)
    else:
        _evaluate(args.impl, s, workdir, args.eval_episodes, args.eval_every, args.t0, args.grid)


# --- driver ---------------------------------------------------------------------------------------


def _cpu_seconds(pid: int) -> float:
    """CPU time (user + system) of process ``pid`` so far, 0 when it is gone (Linux only)."""
    if not sys.platform.startswith("linux"):
        raise RuntimeError("--spy needs Linux: it reads the processes' CPU time in /proc")
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    except OSError:
        return 0.0
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def _spy(roles: dict[str, Any], out: Path, label: str, duration: float, rate: int) -> None:
    """Record each role process and each process it started (our network processes, the
    original's tlspyo processes) with ``py-spy record`` for ``duration`` seconds, idle stacks and
    threads included (py-spy pauses a process for each sample: keep ``rate`` low): raw stacks go
    to ``out/<label>-<role>.txt``; the CPU seconds each process used per second of that window to
    ``out/<label>-cpu.json``. Linux only (it finds the children in /proc)."""
    import subprocess

    if not sys.platform.startswith("linux"):
        raise RuntimeError("--spy needs Linux: it finds each role's children in /proc")

    out.mkdir(parents=True, exist_ok=True)
    targets = {}
    for role, proc in roles.items():
        if proc.poll() is not None:
            continue
        targets[role] = proc.pid
        try:
            children = Path(f"/proc/{proc.pid}/task/{proc.pid}/children").read_text().split()
        except OSError:
            children = []
        for k, child in enumerate(children):
            targets[f"{role}-child{k}"] = int(child)
    cpu0 = {name: _cpu_seconds(pid) for name, pid in targets.items()}
    t0 = time.monotonic()
    spies = [subprocess.Popen(["py-spy", "record", "--pid", str(pid), "--idle", "--threads", "--rate", str(rate),
                               "--duration", str(max(1, int(duration))), "--format", "raw",
                               "--output", str(out / f"{label}-{name}.txt")],
                              stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
             for name, pid in targets.items()]
    time.sleep(max(1, int(duration)))
    cpu = {name: round((_cpu_seconds(pid) - cpu0[name]) / (time.monotonic() - t0), 3) for name, pid in targets.items()}
    for spy in spies:
        spy.wait()
    (out / f"{label}-cpu.json").write_text(json.dumps({"cpu_per_s": cpu, "load": harness.load_average()}))


_CATEGORIES: dict[str, list[tuple[str, tuple[str, ...]]]] = {
    "trainer": [
        ("checkpoint", ("dump_run_instance", "checkpoint.py")),
        ("update (agent.train)", ("Agent.train (", "SACUpdate", "_count_updates")),
        ("weights publish", ("broadcast_model", "ensure_finite", "TrainingOffline._broadcast")),
        ("receive and ingest samples", ("update_buffer", "retrieve_buffer")),
        ("batch sampling", ("Memory.__iter__", "Memory.sample", "collate")),
        ("wait for samples (ratio)", ("check_ratio",)),
    ],
    "worker": [
        ("test episodes", ("run_episode",)),
        ("bench step counter", ("write_atomic", "_RunningCount")),
        ("wait for weights", ("Condition.wait", "latest_weights", "receive_all (")),
        ("install weights", ("update_actor_weights", "_load_weights")),
        ("actor inference", (".act_ (", ".act (")),
        ("environment step", ("Env.step", "Wrapper.step", "Pendulum")),
        ("send samples", ("send_and_clear_buffer",)),
        ("record sample", ("_record", "append_sample", ".step (")),
        ("reset", ("reset",)),
    ],
}


def _main_thread(stack: str) -> bool:
    return "<module> (bench/_child.py" in stack and "Thread._bootstrap" not in stack \
        and "BaseProcess._bootstrap" not in stack


def spy_summary(folder: str) -> None:
    """Print, per side and role, where the main thread of each recorded role spent its wall time
    (shares of py-spy's samples, idle included, by the categories of ``_CATEGORIES``) and the
    CPU each process used."""
    files = sorted(Path(folder).glob("*-*-seed*-*.txt"))
    shares: dict[tuple[str, str], dict[str, float]] = {}
    for f in files:
        side, _profile, _seed, role = f.stem.split("-", 3)
        if role not in _CATEGORIES:
            continue
        counts: dict[str, int] = {}
        for line in f.read_text().splitlines():
            stack, _, n = line.rpartition(" ")
            if not _main_thread(stack):
                continue
            label = next((c for c, keys in _CATEGORIES[role] if any(k in stack for k in keys)), "other")
            counts[label] = counts.get(label, 0) + int(n)
        total = sum(counts.values()) or 1
        acc = shares.setdefault((side, role), {})
        for label, n in counts.items():
            acc[label] = acc.get(label, 0.0) + n / total / len([g for g in files if g.stem.startswith(side)
                                                                 and g.stem.endswith("-" + role)])
    for role, cats in _CATEGORIES.items():
        sides = sorted({s for s, r in shares if r == role})
        print(f"\n{role} main thread, share of wall time | " + " | ".join(sides))
        for label in [c for c, _ in cats] + ["other"]:
            print(f"  {label:28s} | " + " | ".join(f"{shares[(s, role)].get(label, 0.0):6.1%}" for s in sides))
    for f in sorted(Path(folder).glob("*-cpu.json")):
        rec = json.loads(f.read_text())
        print(f"\n{f.stem}: CPU s/s {rec['cpu_per_s']} (load {rec['load']:.2f})")


def run_once(side: harness.Side, profile: str, seed: int, timeout: float, eval_episodes: int,
             eval_every: float, keep: bool, spy: dict[str, Any] | None = None,
             update_order: str | None = None, weights_when_waiting_only: bool = False,
             grid: int = 0) -> dict[str, Any]:
    """One pipeline run; returns the evaluations and, when reached, time, steps and updates (with
    ``grid``, the steps and updates of the first snapshot that passed, see :func:`_evaluate`; the
    passing evaluation's own counts as ``steps_eval`` and ``updates_eval``).
    With ``spy`` (``dir``, ``after``, ``duration``, ``rate``), py-spy records every role from
    ``after`` seconds on (see :func:`_spy`)."""
    workdir = Path(tempfile.mkdtemp(prefix=f"pendulum-{side.name}-"))
    port = harness.free_port()
    env = dict(side.env, OMP_NUM_THREADS="1", PYTHONUNBUFFERED="1")
    if side.name == "ours":
        env["TMRL_DATA"] = str(workdir / "TmrlData")
    t0 = time.monotonic()
    common = ["--impl", side.name, "--profile", profile, "--workdir", str(workdir), "--port", str(port),
              "--seed", str(seed), "--eval-episodes", str(eval_episodes), "--eval-every", str(eval_every),
              "--t0", repr(t0), "--grid", str(grid)] + ([] if update_order is None else ["--update-order", update_order]) \
        + (["--weights-when-waiting-only"] if weights_when_waiting_only else [])
    procs = []
    result: dict[str, Any] = {"reached": False, "evals": []}
    try:
        procs.append(harness.start_group(side.command("pendulum_pipeline", "--role", "server", *common), side,
                                         workdir / "server.log", env=env, cwd=str(workdir)))
        harness.wait_listening(port, 60.0)  # the original's links retry only every 10 s
        for role in ("trainer", "worker"):
            procs.append(harness.start_group(side.command("pendulum_pipeline", "--role", role, *common), side,
                                             workdir / f"{role}.log", env=env, cwd=str(workdir)))
        ev = harness.start_group(side.command("pendulum_pipeline", "--role", "eval", *common), side,
                                 workdir / "eval.log", stdout=-1, env=env, cwd=str(workdir))
        procs.append(ev)
        if spy is not None:
            roles = dict(zip(("server", "trainer", "worker", "eval"), procs))
            timer = threading.Timer(max(0.0, spy["after"] - (time.monotonic() - t0)), _spy,
                                    (roles, Path(spy["dir"]), f"{side.name}-{profile}-seed{seed}", spy["duration"],
                                     spy["rate"]))
            timer.daemon = True
            timer.start()
        for rec in harness.JsonLines(ev).wait(max(0.0, timeout - (time.monotonic() - t0)), interval=0.2):
            result["evals"].append(rec)
            if rec["ret"] > THRESHOLD:
                first = rec.get("first") or rec
                result.update(reached=True, wall_s=rec["t"], steps=first["steps"], updates=first["updates"],
                              steps_eval=rec["steps"], updates_eval=rec["updates"], first=rec.get("first"))
                break
            if any(p.poll() is not None for p in procs):
                print(f"  [{side.name}] a process exited early (logs in {workdir})", flush=True)
                keep = True
                break
    finally:
        if spy is not None:
            timer.cancel()
            if timer.is_alive():  # recording: let it end before the processes stop
                timer.join()
        harness.stop_groups(procs)
        if keep:
            print(f"  [{side.name}] logs kept in {workdir}")
        else:
            shutil.rmtree(workdir, ignore_errors=True)
    return result


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(prog="python -m bench pendulum_pipeline", description=__doc__.split("\n\n")[0])
    ap.add_argument("--profiles", default="tutorial,recommended", help=f"among {', '.join(PROFILES)}")
    ap.add_argument("--seeds", type=int, default=5, help="runs per side and profile")
    ap.add_argument("--timeout", type=float, default=None,
                    help="seconds per run before it counts as not reached (default: per profile, "
                    + ", ".join(f"{p} {t:g}" for p, t in TIMEOUTS.items()) + ")")
    ap.add_argument("--eval-episodes", type=int, default=10)
    ap.add_argument("--eval-every", type=float, default=2.0, help="seconds between two evaluations, at least")
    ap.add_argument("--grid", type=int, default=1000,
                    help="environment steps between two snapshots of the trainer's weights: once an evaluation "
                    "passes the threshold, the snapshots since the one before are evaluated in order, and the "
                    "steps and updates are those of the first that passes (0: those of the passing evaluation)")
    ap.add_argument("--keep", action="store_true", help="keep the work folders and logs")
    ap.add_argument("--update-order", choices=("simultaneous", "sequential"), default=None,
                    help="our SAC's update order (default: the library's, simultaneous); sequential is the "
                    "original's (its actor loss reads the critics after their step); tmrl 0.7.1 always does that")
    ap.add_argument("--weights-when-waiting-only", action="store_true",
                    help="our worker loads weights only when it has to wait for them, as tmrl 0.7.1's does "
                    "(run_synchronous(newest_each_episode=False)); by default it starts every episode with the "
                    "newest it received")
    ap.add_argument("--py-spy", metavar="DIR", default=None,
                    help="record every role (and its network processes) with py-spy into DIR, raw stacks "
                    "(needs py-spy and the right to trace; `python -m bench pendulum_pipeline --spy-summary DIR` "
                    "sums them up)")
    ap.add_argument("--py-spy-after", type=float, default=15.0, help="seconds after launch the recording starts")
    ap.add_argument("--py-spy-for", type=float, default=20.0, help="seconds recorded")
    ap.add_argument("--py-spy-rate", type=int, default=100, help="samples per second")
    harness.add_side_arguments(ap, tmrl=True)
    ap.add_argument("--spy-summary", metavar="DIR", default=None,
                    help="only print the summary of the recordings in DIR (made with --py-spy)")
    args = ap.parse_args(argv)
    if args.spy_summary:
        spy_summary(args.spy_summary)
        return
    profiles = [p for p in args.profiles.split(",") if p]
    if set(profiles) - set(PROFILES):
        ap.error(f"unknown profile(s) {sorted(set(profiles) - set(PROFILES))}: use {', '.join(PROFILES)}")
    sides = harness.sides_from_args(args)
    timeouts = {p: args.timeout or TIMEOUTS[p] for p in profiles}
    rec = harness.Recorder("pendulum_pipeline", {p: PROFILES[p] for p in profiles} | {
        "seeds": args.seeds, "timeout_s": timeouts, "eval_episodes": args.eval_episodes,
        "eval_every_s": args.eval_every, "grid_steps": args.grid, "threshold": THRESHOLD, "checkpoint": "every epoch, both sides",
        "update_order_ours": args.update_order or "simultaneous (library default)",
        "worker_weights_ours": "when waiting only" if args.weights_when_waiting_only else "newest each episode"})
    most = sum(len(sides) * args.seeds * (timeouts[p] + 8) for p in profiles) / 60
    print(f"{len(profiles) * len(sides) * args.seeds} runs, {most:.0f} min at most", flush=True)
    missed: list[str] = []
    for profile in profiles:
        for seed, side in harness.alternate(sides, args.seeds):
            spy = None if args.py_spy is None else {"dir": args.py_spy, "after": args.py_spy_after,
                                                    "duration": args.py_spy_for, "rate": args.py_spy_rate}
            res = run_once(side, profile, seed, timeouts[profile], args.eval_episodes, args.eval_every, args.keep,
                           spy, args.update_order, args.weights_when_waiting_only, args.grid)
            last = res["evals"][-1] if res["evals"] else {}
            extra = {"last_eval": last, "evaluations": len(res["evals"]), "first": res.get("first")}
            for metric, unit in (("wall_s", "s"), ("steps", "steps"), ("updates", "updates"),
                                 ("steps_eval", "steps"), ("updates_eval", "updates")):
                rec.add(f"{profile} to {THRESHOLD:g}", metric, side.name, res.get(metric), round=seed,
                        higher_is_better=False, unit=unit, echo=metric == "wall_s", **extra)
            # rates over the whole run, reached or not: counts when the last evaluation read them
            t_read = last.get("t_read") or 0.0
            for metric, key, unit in (("steps_per_s", "steps", "steps/s"), ("updates_per_s", "updates", "upd/s")):
                rec.add(f"{profile} rates", metric, side.name, last[key] / t_read if t_read > 0 else None,
                        round=seed, unit=unit, echo=False, **extra)
            if not res["reached"]:
                missed.append(f"{profile} {side.name} seed {seed}: not reached in {timeouts[profile]:g} s; last "
                              f"evaluation {last.get('ret', float('nan')):.1f} at {last.get('t', 0.0):.1f} s "
                              f"({last.get('steps', 0)} steps, {last.get('updates', 0)} updates)")
    rec.print_table()
    print(f"(n = runs that reached {THRESHOLD:g} within the timeout, {timeouts}, of {args.seeds} per side)")
    print("every run reached it" if not missed else "runs that did not reach it:\n  " + "\n  ".join(missed))
    rec.close()
