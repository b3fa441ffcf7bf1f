"""Pendulum-v1 through a server, a trainer and a worker (three processes), ours beside tmrl 0.7.1
on the same settings: wall time, environment steps and updates until the mean test return
exceeds -200.

    python -m bench pendulum_pipeline                              # both profiles, 5 seeds per side
    python -m bench pendulum_pipeline --profiles recommended --seeds 3 --timeout 300

Two profiles, each one settings dict applied to both sides (the original accepts every one of
those arguments, ``hidden_sizes`` included):

- ``tutorial``: the original's own minimal Pendulum tutorial (256x256, batch 32, lr 1e-3, 0.2
  updates per environment step, weights and samples exchanged at every update, 1 s buffer polls,
  a test episode every 10 episodes, worker pacing 100/10/True);
- ``recommended``: our recommended settings (64x64, batch 256, lr 3e-3, at most 1 update per
  environment step, exchange every 20 updates, 0.01 s polls, no test episodes, worker pacing
  1000/40/False).

Both sides checkpoint at the end of every epoch (the original always does) and load weights the
same way. Seeds alternate the order of the sides (ours, tmrl, then tmrl, ours...).

How it measures: a fourth process (the evaluator, the same code on both sides) reloads the
trainer's weights file when it changed, at most every ``--eval-every`` seconds (a failed load is
retried 50 ms later: the original writes that file in place), and runs ``--eval-episodes``
deterministic episodes; the worker's environment writes its step count to a file, the trainer
its update count. The clock starts when the processes are launched (start-up, imports and
connection included) and stops at the first evaluation above the threshold; a run that does not
get there within the profile's timeout (``--timeout``) counts as not reached.
"""

from __future__ import annotations

import argparse
import shutil
import tempfile
import time
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

TIMEOUTS = {"tutorial": 90.0, "recommended": 50.0}
"""Default seconds per run, per profile: both profiles, 5 seeds per side, fit in 25 minutes."""


# --- inside the role processes (either interpreter) ---------------------------------------------


def _seed(seed: int) -> None:
    import random

    import numpy as np
    import torch

    random.seed(seed)
    np.random.seed(seed)
    torch.manual_seed(seed)


def _counting_env(env: Any, steps_file: Path) -> Any:
    """``env`` whose ``step`` writes its running count to ``steps_file`` every 50 steps."""
    step = env.step
    count = [0]

    def counted(action: Any) -> Any:
        count[0] += 1
        if count[0] % 50 == 0:
            harness.write_atomic(steps_file, str(count[0]))
        return step(action)

    env.step = counted
    return env


def _count_updates(agent_cls: type, updates_file: Path) -> None:
    """Make ``agent_cls.train`` write its running count to ``updates_file`` every 20 calls (the
    class itself is patched, in the trainer process only, so that the original's pickled
    checkpoints still find it by name)."""
    train = agent_cls.train
    count = [0]

    def counted(self: Any, batch: Any) -> Any:
        out = train(self, batch)
        count[0] += 1
        if count[0] % 20 == 0:
            harness.write_atomic(updates_file, str(count[0]))
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


def _trainer(impl: str, s: dict[str, Any], workdir: Path, port: int) -> None:
    import gymnasium

    m = _imports(impl)
    partial = m["partial"]
    _count_updates(m["SACAgent"], workdir / "updates")
    env = gymnasium.make("Pendulum-v1")
    training_cls = partial(
        m["TorchTrainingOffline"],
        env_cls=(env.observation_space, env.action_space),
        memory_cls=partial(m["GenericTorchMemory"], memory_size=s["memory_size"], batch_size=s["batch_size"],
                           crc_debug=False),
        training_agent_cls=partial(
            m["SACAgent"], model_cls=partial(m["MLPActorCritic"], hidden_sizes=tuple(s["hidden_sizes"])),
            gamma=s["gamma"], polyak=s["polyak"], alpha=s["alpha"], lr_actor=s["lr"], lr_critic=s["lr"],
            lr_entropy=s["lr"], learn_entropy_coef=True, target_entropy=None,
        ),
        epochs=1000, rounds=s["rounds"], steps=s["steps_per_round"],
        update_buffer_interval=s["update_buffer_interval"], update_model_interval=s["update_model_interval"],
        max_training_steps_per_env_step=s["max_training_steps_per_env_step"], start_training=s["start_training"],
        device="cpu", sleep_between_buffer_retrieval_attempts=s["poll_wait"],
    )
    m["Trainer"](training_cls=training_cls, server_ip="127.0.0.1", server_port=port, password="bench-password",
                 model_path=str(workdir / "model_trainer.tmod"), checkpoint_path=str(workdir / "checkpoint"),
                 security=None).run()


def _worker(impl: str, s: dict[str, Any], workdir: Path, port: int) -> None:
    m = _imports(impl)
    worker = m["RolloutWorker"](
        env_cls=lambda: _counting_env(m["GenericGymEnv"](id="Pendulum-v1", gym_kwargs={"render_mode": None}),
                                      workdir / "steps"),
        actor_module_cls=m["partial"](m["Actor"], hidden_sizes=tuple(s["hidden_sizes"])),
        sample_compressor=None, device="cpu", server_ip="127.0.0.1", server_port=port, password="bench-password",
        max_samples_per_episode=s["max_samples_per_episode"], model_path=str(workdir / "model_worker.tmod"),
        model_history=0, crc_debug=False, security=None,
    )
    worker.run_synchronous(test_episode_interval=s["test_episode_interval"], initial_steps=s["initial_steps"],
                           max_steps_per_update=s["max_steps_per_update"], end_episodes=s["end_episodes"])


def _evaluate(impl: str, s: dict[str, Any], workdir: Path, episodes: int, every: float, t0: float) -> None:
    """Evaluate the trainer's weights when its file changed, at most once every ``every`` seconds;
    one JSON line per evaluation."""
    import gymnasium
    import numpy as np
    import torch

    torch.set_num_threads(1)
    env = gymnasium.make("Pendulum-v1")
    actor = _imports(impl)["Actor"](env.observation_space, env.action_space, hidden_sizes=tuple(s["hidden_sizes"]))
    path = workdir / "model_trainer.tmod"
    last_mtime, episode_seed, next_eval = None, 10_000, time.monotonic()
    while True:
        time.sleep(max(0.0, next_eval - time.monotonic()))
        try:
            mtime = path.stat().st_mtime_ns
            if mtime == last_mtime:
                time.sleep(0.05)
                continue
            steps, updates = harness.read_int(workdir / "steps"), harness.read_int(workdir / "updates")
            actor = actor.load(str(path), device="cpu")
            last_mtime, next_eval = mtime, time.monotonic() + every
        except Exception:  # noqa: BLE001 (missing, or being written in place by the original: retry soon)
            time.sleep(0.05)
            continue
        returns = []
        for _ in range(episodes):
            obs, _ = env.reset(seed=episode_seed)
            episode_seed += 1
            ret, done = 0.0, False
            while not done:
                with torch.no_grad():
                    act = actor.act_(np.asarray(obs, np.float32), test=True)
                act = np.asarray(act, np.float32).reshape(env.action_space.shape)
                obs, rew, terminated, truncated, _ = env.step(act)
                ret += float(rew)
                done = terminated or truncated
            returns.append(ret)
        harness.print_json({"t": time.monotonic() - t0, "steps": steps, "updates": updates,
                             "ret": sum(returns) / len(returns)})


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
        _trainer(args.impl, s, workdir, args.port)
    elif args.role == "worker":
        _worker(args.impl, s, workdir, args.port)
    else:
        _evaluate(args.impl, s, workdir, args.eval_episodes, args.eval_every, args.t0)


# --- driver ---------------------------------------------------------------------------------------


def run_once(side: harness.Side, profile: str, seed: int, timeout: float, eval_episodes: int,
             eval_every: float, keep: bool) -> dict[str, Any]:
    """One pipeline run; returns the evaluations and, when reached, time, steps and updates."""
    workdir = Path(tempfile.mkdtemp(prefix=f"pendulum-{side.name}-"))
    port = harness.free_port()
    env = dict(side.env, OMP_NUM_THREADS="1", PYTHONUNBUFFERED="1")
    if side.name == "ours":
        env["TMRL_DATA"] = str(workdir / "TmrlData")
    t0 = time.monotonic()
    common = ["--impl", side.name, "--profile", profile, "--workdir", str(workdir), "--port", str(port),
              "--seed", str(seed), "--eval-episodes", str(eval_episodes), "--eval-every", str(eval_every),
              "--t0", repr(t0)]
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
        for rec in harness.JsonLines(ev).wait(max(0.0, timeout - (time.monotonic() - t0)), interval=0.2):
            result["evals"].append(rec)
            if rec["ret"] > THRESHOLD:
                result.update(reached=True, wall_s=rec["t"], steps=rec["steps"], updates=rec["updates"])
                break
            if any(p.poll() is not None for p in procs):
                print(f"  [{side.name}] a process exited early (logs in {workdir})", flush=True)
                keep = True
                break
    finally:
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
    ap.add_argument("--keep", action="store_true", help="keep the work folders and logs")
    harness.add_side_arguments(ap, tmrl=True)
    args = ap.parse_args(argv)
    profiles = [p for p in args.profiles.split(",") if p]
    if set(profiles) - set(PROFILES):
        ap.error(f"unknown profile(s) {sorted(set(profiles) - set(PROFILES))}: use {', '.join(PROFILES)}")
    sides = harness.sides_from_args(args)
    timeouts = {p: args.timeout or TIMEOUTS[p] for p in profiles}
    rec = harness.Recorder("pendulum_pipeline", {p: PROFILES[p] for p in profiles} | {
        "seeds": args.seeds, "timeout_s": timeouts, "eval_episodes": args.eval_episodes,
        "eval_every_s": args.eval_every, "threshold": THRESHOLD, "checkpoint": "every epoch, both sides"})
    most = sum(len(sides) * args.seeds * (timeouts[p] + 8) for p in profiles) / 60
    print(f"{len(profiles) * len(sides) * args.seeds} runs, {most:.0f} min at most", flush=True)
    for profile in profiles:
        for seed, side in harness.alternate(sides, args.seeds):
            res = run_once(side, profile, seed, timeouts[profile], args.eval_episodes, args.eval_every, args.keep)
            last = res["evals"][-1] if res["evals"] else {}
            extra = {"last_eval": last, "evaluations": len(res["evals"])}
            for metric, unit in (("wall_s", "s"), ("steps", "steps"), ("updates", "updates")):
                rec.add(f"{profile} to {THRESHOLD:g}", metric, side.name, res.get(metric), round=seed,
                        higher_is_better=False, unit=unit, echo=metric == "wall_s", **extra)
    rec.print_table()
    print(f"(n = runs that reached {THRESHOLD:g} within the timeout, {timeouts}, of {args.seeds} per side)")
    rec.close()
