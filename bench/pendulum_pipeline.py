"""Pendulum-v1 through a server, a trainer and a worker (three processes): wall time and
environment steps until the mean test return exceeds -400 and -200, for this tmrl and for the
original tmrl 0.7.1 (with the settings of its own minimal Pendulum tutorial) in the same run.

    python bench/pendulum_pipeline.py                       # both, one after the other
    python bench/pendulum_pipeline.py --impl ours --timeout 300
    python bench/pendulum_pipeline.py --anchor-python /tmp/tmrl-anchor/venv/bin/python

How it measures: a fourth process (the evaluator) reloads the trainer's latest weights every
``--eval-every`` seconds and runs ``--eval-episodes`` deterministic Pendulum episodes with them;
the worker's environment writes its step count to a file that the evaluator reads. The clock
starts when the three processes are launched (so process start-up, imports and connection are
included) and stops at the first evaluation above each threshold. Both pipelines pay the same
evaluator cost. The original is installed by ``shared/anchors/setup-tmrl-0.7.1.sh``.

The figures depend on the machine's load: the script prints ``uptime`` with them.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

HERE = Path(__file__).resolve()
THRESHOLDS = (-400.0, -200.0)


# ------------------------------------------------------------------------------------------------
# shared by both implementations (runs inside the role processes)


def _counting_env(make_env, steps_file: str):
    """Wrap ``make_env()`` so that its number of steps is written to ``steps_file`` every 200."""
    import gymnasium

    class StepCounter(gymnasium.Wrapper):
        steps = 0

        def step(self, action):
            StepCounter.steps += 1
            if StepCounter.steps % 200 == 0:
                tmp = steps_file + ".tmp"
                with open(tmp, "w") as f:
                    f.write(str(StepCounter.steps))
                os.replace(tmp, steps_file)
            return self.env.step(action)

    return StepCounter(make_env())


def _read_steps(workdir: Path) -> int:
    try:
        return int((workdir / "steps").read_text())
    except (OSError, ValueError):
        return 0


# ------------------------------------------------------------------------------------------------
# this tmrl


OURS = dict(
    hidden_sizes=(64, 64),
    batch_size=256,
    memory_size=1_000_000,
    lr=3e-3,
    gamma=0.99,
    polyak=0.995,
    alpha=0.2,
    steps_per_round=500,
    rounds=10,
    update_model_interval=20,
    update_buffer_interval=20,
    max_training_steps_per_env_step=1.0,
    start_training=1000,
    worker_steps_per_update=40,
)
# Settings to try without editing this file: BENCH_OURS='{"batch_size": 128}' (JSON, keys of OURS;
# the role processes inherit it).
OURS.update(json.loads(os.environ.get("BENCH_OURS", "{}")))


def _ours_training_cls(workdir: Path):
    import gymnasium

    from tmrl.algorithms.sac import SACAgent
    from tmrl.memory import GenericTorchMemory
    from tmrl.models import MLPActorCritic
    from tmrl.training_offline import TorchTrainingOffline
    from tmrl.util import partial

    env = gymnasium.make("Pendulum-v1")
    spaces = (env.observation_space, env.action_space)
    return partial(
        TorchTrainingOffline,
        env_cls=spaces,
        memory_cls=partial(
            GenericTorchMemory, memory_size=OURS["memory_size"], batch_size=OURS["batch_size"]
        ),
        training_agent_cls=partial(
            SACAgent,
            model_cls=partial(MLPActorCritic, hidden_sizes=OURS["hidden_sizes"]),
            gamma=OURS["gamma"],
            polyak=OURS["polyak"],
            alpha=OURS["alpha"],
            lr_actor=OURS["lr"],
            lr_critic=OURS["lr"],
            lr_entropy=OURS["lr"],
            learn_entropy_coef=True,
            target_entropy=None,
        ),
        epochs=1000,
        rounds=OURS["rounds"],
        steps=OURS["steps_per_round"],
        update_buffer_interval=OURS["update_buffer_interval"],
        update_model_interval=OURS["update_model_interval"],
        max_training_steps_per_env_step=OURS["max_training_steps_per_env_step"],
        start_training=OURS["start_training"],
        device="cpu",
        sleep_between_buffer_retrieval_attempts=0.01,
    )


def ours_role(role: str, workdir: Path, port: int) -> None:
    from tmrl.networking import RolloutWorker, Server, Trainer

    common = dict(password="bench", security=None)
    if role == "server":
        server = Server(port=port, **common)
        try:
            while True:
                time.sleep(1.0)
        finally:
            server.stop()
    elif role == "trainer":
        Trainer(
            training_cls=_ours_training_cls(workdir),
            server_ip="127.0.0.1",
            server_port=port,
            model_path=str(workdir / "model_trainer.tmod"),
            checkpoint_path=None,
            **common,
        ).run()
    elif role == "worker":
        from tmrl.envs import GenericGymEnv
        from tmrl.models import SquashedGaussianMLPActor
        from tmrl.util import partial

        worker = RolloutWorker(
            env_cls=lambda: _counting_env(lambda: GenericGymEnv(id="Pendulum-v1"), str(workdir / "steps")),
            actor_module_cls=partial(SquashedGaussianMLPActor, hidden_sizes=OURS["hidden_sizes"]),
            server_ip="127.0.0.1",
            server_port=port,
            max_samples_per_episode=1000,
            model_path=str(workdir / "model_worker.tmod"),
            model_history=0,
            **common,
        )
        worker.run_synchronous(
            initial_steps=OURS["start_training"],
            max_steps_per_update=OURS["worker_steps_per_update"],
            end_episodes=False,
        )
    elif role == "eval":
        import gymnasium

        from tmrl.models import SquashedGaussianMLPActor

        env = gymnasium.make("Pendulum-v1")
        actor = SquashedGaussianMLPActor(
            env.observation_space, env.action_space, hidden_sizes=OURS["hidden_sizes"]
        )
        _eval_loop(env, actor, workdir, workdir / "model_trainer.tmod")


# ------------------------------------------------------------------------------------------------
# tmrl 0.7.1 (its tuto_minimal_pendulum.py settings)


def tmrl_role(role: str, workdir: Path, port: int) -> None:
    import tmrl.config.config_constants as cfg
    from tmrl.networking import RolloutWorker, Server, Trainer
    from tmrl.util import partial

    if role == "server":
        server = Server(security=None, password=cfg.PASSWORD, port=port)  # noqa: F841 (must stay referenced)
        while True:
            time.sleep(1.0)
    elif role == "trainer":
        import gymnasium
        from tmrl.custom.custom_memories import GenericTorchMemory

        from tmrl.custom.custom_algorithms import SpinupSacAgent
        from tmrl.custom.custom_models import MLPActorCritic
        from tmrl.training_offline import TorchTrainingOffline

        env = gymnasium.make("Pendulum-v1")
        training_cls = partial(
            TorchTrainingOffline,
            env_cls=(env.observation_space, env.action_space),
            memory_cls=partial(GenericTorchMemory, memory_size=1e6, batch_size=32, crc_debug=False),
            training_agent_cls=partial(
                SpinupSacAgent,
                model_cls=MLPActorCritic,
                gamma=0.99,
                polyak=0.995,
                alpha=0.2,
                lr_actor=1e-3,
                lr_critic=1e-3,
                lr_entropy=1e-3,
                learn_entropy_coef=True,
                target_entropy=None,
            ),
            epochs=1000,
            rounds=10,
            steps=1000,
            update_buffer_interval=1,
            update_model_interval=1,
            max_training_steps_per_env_step=0.2,
            start_training=100,
            device=None,
        )
        Trainer(
            training_cls=training_cls,
            server_ip="127.0.0.1",
            server_port=port,
            password=cfg.PASSWORD,
            model_path=str(workdir / "model_trainer.tmod"),
            checkpoint_path=str(workdir / "checkpoint.tcpt"),
            security=None,
        ).run()
    elif role == "worker":
        from tmrl.custom.custom_models import SquashedGaussianMLPActor
        from tmrl.envs import GenericGymEnv

        worker = RolloutWorker(
            env_cls=lambda: _counting_env(
                lambda: GenericGymEnv(id="Pendulum-v1", gym_kwargs={"render_mode": None}),
                str(workdir / "steps"),
            ),
            actor_module_cls=partial(SquashedGaussianMLPActor),
            sample_compressor=None,
            device="cpu",
            server_ip="127.0.0.1",
            server_port=port,
            password=cfg.PASSWORD,
            max_samples_per_episode=1000,
            model_path=str(workdir / "model_worker.tmod"),
            model_history=-1,
            crc_debug=False,
            security=None,
        )
        worker.run_synchronous(
            test_episode_interval=10, initial_steps=100, max_steps_per_update=10, end_episodes=True
        )
    elif role == "eval":
        import gymnasium

        from tmrl.custom.custom_models import SquashedGaussianMLPActor

        env = gymnasium.make("Pendulum-v1")
        actor = SquashedGaussianMLPActor(env.observation_space, env.action_space)
        _eval_loop(env, actor, workdir, workdir / "model_trainer.tmod")


# ------------------------------------------------------------------------------------------------
# evaluator (same code for both; `actor` has act(obs, test) after load(path, device))


def _eval_loop(env, actor, workdir: Path, model_path: Path) -> None:
    import numpy as np
    import torch

    torch.set_num_threads(1)
    every = float(os.environ["BENCH_EVAL_EVERY"])
    episodes = int(os.environ["BENCH_EVAL_EPISODES"])
    t0 = float(os.environ["BENCH_T0"])
    last_mtime = None
    rng_seed = 0
    while True:
        time.sleep(every)
        try:
            mtime = model_path.stat().st_mtime_ns
            if mtime == last_mtime:
                continue
            steps = _read_steps(workdir)
            actor = actor.load(str(model_path), device="cpu")
            last_mtime = mtime
        except Exception:  # noqa: BLE001 (the original writes its model file in place: retry later)
            continue
        rets = []
        for _ in range(episodes):
            obs, _ = env.reset(seed=rng_seed)
            rng_seed += 1
            ret, done = 0.0, False
            while not done:
                with torch.no_grad():
                    act = actor.act_(np.asarray(obs, np.float32), test=True)
                obs, rew, term, trunc, _ = env.step(
                    np.asarray(act, np.float32).reshape(env.action_space.shape)
                )
                ret += float(rew)
                done = term or trunc
            rets.append(ret)
        print(
            json.dumps({"t": time.monotonic() - t0, "steps": steps, "ret": sum(rets) / len(rets)}), flush=True
        )


# ------------------------------------------------------------------------------------------------
# driver


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _stop(procs: list[subprocess.Popen]) -> None:
    for p in procs:
        if p.poll() is None:
            p.send_signal(signal.SIGINT)
    deadline = time.monotonic() + 10
    for p in procs:
        try:
            p.wait(max(0.1, deadline - time.monotonic()))
        except subprocess.TimeoutExpired:
            pass
        try:  # why: also ends children (relay and endpoint processes) left behind by a role
            os.killpg(p.pid, signal.SIGKILL)
        except ProcessLookupError:
            pass
        p.wait()


def _wait_listening(port: int, timeout: float) -> None:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        try:
            with socket.create_connection(("127.0.0.1", port), timeout=0.5):
                return
        except OSError:
            time.sleep(0.1)
    raise RuntimeError(f"the server did not listen on port {port} within {timeout} s")


def run_pipeline(
    impl: str,
    python: str,
    home: str | None,
    timeout: float,
    eval_every: float,
    eval_episodes: int,
    keep: bool,
) -> dict:
    workdir = Path(tempfile.mkdtemp(prefix=f"pendulum-{impl}-"))
    port = _free_port()
    env = dict(
        os.environ,
        BENCH_EVAL_EVERY=str(eval_every),
        BENCH_EVAL_EPISODES=str(eval_episodes),
        OMP_NUM_THREADS="1",
        PYTHONUNBUFFERED="1",
    )
    if home:
        env["HOME"] = home
    else:
        env["TMRL_DATA"] = str(workdir / "TmrlData")
    t0 = time.monotonic()
    env["BENCH_T0"] = repr(t0)
    procs: list[subprocess.Popen] = []
    logs = {}

    def start(role: str, stdout=None) -> subprocess.Popen:
        logs[role] = open(workdir / f"{role}.log", "wb")
        p = subprocess.Popen(
            [
                python,
                str(HERE),
                "--role",
                role,
                "--impl",
                impl,
                "--workdir",
                str(workdir),
                "--port",
                str(port),
            ],
            cwd=str(workdir),
            env=env,
            stdout=stdout or logs[role],
            stderr=logs[role],
            start_new_session=True,
        )
        procs.append(p)
        return p

    result: dict = {"impl": impl, "wall_s": {}, "steps": {}, "evals": []}
    try:
        start("server")
        # why: the original's endpoints wait 10 s before retrying a refused connection
        _wait_listening(port, 60.0)
        start("trainer")
        start("worker")
        ev = start("eval", stdout=subprocess.PIPE)
        os.set_blocking(ev.stdout.fileno(), False)
        pending = b""
        reached = set()
        while time.monotonic() - t0 < timeout and len(reached) < len(THRESHOLDS):
            time.sleep(0.2)
            chunk = ev.stdout.read() or b""
            pending += chunk
            *lines, pending = pending.split(b"\n")
            for line in lines:
                rec = json.loads(line)
                result["evals"].append(rec)
                print(
                    f"  [{impl}] t={rec['t']:6.1f}s steps={rec['steps']:6d} mean test return={rec['ret']:8.1f}",
                    flush=True,
                )
                for th in THRESHOLDS:
                    if th not in reached and rec["ret"] > th:
                        reached.add(th)
                        result["wall_s"][th] = rec["t"]
                        result["steps"][th] = rec["steps"]
            dead = [p for p in procs if p.poll() is not None]
            if dead:
                print(f"  [{impl}] a process exited early (see {workdir}/*.log)", flush=True)
                break
    finally:
        _stop(procs)
        for f in logs.values():
            f.close()
        if not keep:
            shutil.rmtree(workdir, ignore_errors=True)
        else:
            print(f"  [{impl}] logs kept in {workdir}")
    return result


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--impl", default="ours,tmrl", help="comma-separated: ours, tmrl")
    ap.add_argument("--timeout", type=float, default=400.0, help="seconds per pipeline")
    ap.add_argument("--eval-every", type=float, default=4.0)
    ap.add_argument("--eval-episodes", type=int, default=10)
    ap.add_argument("--python", default=sys.executable, help="interpreter for this tmrl")
    ap.add_argument("--anchor-python", default="/tmp/tmrl-anchor/venv/bin/python")
    ap.add_argument("--anchor-home", default="/tmp/tmrl-anchor/home")
    ap.add_argument("--keep", action="store_true", help="keep the work folders and logs")
    ap.add_argument("--role", help=argparse.SUPPRESS)
    ap.add_argument("--workdir", help=argparse.SUPPRESS)
    ap.add_argument("--port", type=int, help=argparse.SUPPRESS)
    args = ap.parse_args()

    if args.role:
        try:
            (ours_role if args.impl == "ours" else tmrl_role)(args.role, Path(args.workdir), args.port)
        except KeyboardInterrupt:
            pass
        return

    print(f"uptime: {subprocess.run(['uptime'], capture_output=True, text=True).stdout.strip()}")
    results = []
    for impl in args.impl.split(","):
        python, home = (args.python, None) if impl == "ours" else (args.anchor_python, args.anchor_home)
        print(f"{impl}: running (timeout {args.timeout:.0f} s)", flush=True)
        results.append(
            run_pipeline(impl, python, home, args.timeout, args.eval_every, args.eval_episodes, args.keep)
        )
    print(f"uptime: {subprocess.run(['uptime'], capture_output=True, text=True).stdout.strip()}")
    print(
        f"{'impl':6} | {'to -400: wall s':>15} {'env steps':>10} | {'to -200: wall s':>15} {'env steps':>10}"
    )
    for r in results:
        cells = []
        for th in THRESHOLDS:
            if th in r["wall_s"]:
                cells += [f"{r['wall_s'][th]:15.1f}", f"{r['steps'][th]:10d}"]
            else:
                cells += [f"{'not reached':>15}", f"{'-':>10}"]
        print(f"{r['impl']:6} | {cells[0]} {cells[1]} | {cells[2]} {cells[3]}")


if __name__ == "__main__":
    main()
