"""Trainer speed: SAC and REDQ-SAC updates per second, ours against the original tmrl 0.7.1.

Both sides run in their own worker process with the same torch thread count, on the same
synthetic Pendulum-shaped data (observation ``(3,)`` in a Tuple, action ``(1,)``, episodes of
200 steps, 100k samples in memory), MLP 256x256, batch 256. Measurements are interleaved
(ours, theirs, ours, theirs ...) in several rounds because the machine is shared; the load
average is printed beside every round.

Two figures per side and algorithm:
- ``full``: ``batch = memory.sample(); agent.train(batch)`` in a loop (GenericTorchMemory on both
  sides), with the share of the time spent in ``sample``;
- ``agent``: ``agent.train(batch)`` on one ready batch.

Usage::

    /work/venv/bin/python bench/trainer_speed.py [--rounds 3] [--seconds 4] [--threads N]
        [--anchor-python /tmp/tmrl-anchor/venv/bin/python] [--anchor-home /tmp/tmrl-anchor/home]

The original is run as ``HOME=<anchor-home> <anchor-python> bench/trainer_speed.py --worker tmrl``
from a folder outside this repository, so that it imports the installed tmrl 0.7.1.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

RESULT = "@@RESULT "
OBS_HIGH = (1.0, 1.0, 8.0)
EPISODE = 200
N_SAMPLES = 100_000
BATCH = 256


# --- worker side (runs in either interpreter) -----------------------------------------------------


def _spaces():
    import numpy as np
    from gymnasium import spaces

    high = np.array(OBS_HIGH, np.float32)
    obs_space = spaces.Tuple((spaces.Box(-high, high, (3,), np.float32),))
    act_space = spaces.Box(-2.0, 2.0, (1,), np.float32)
    return obs_space, act_space


def _samples(seed: int = 0) -> list:
    """Pendulum-shaped samples ``(act, obs, rew, terminated, truncated, info)``."""
    import numpy as np

    rng = np.random.default_rng(seed)
    out = []
    for i in range(N_SAMPLES):
        t = i % EPISODE
        obs = (rng.uniform(-1, 1, 3).astype(np.float32) * np.array(OBS_HIGH, np.float32),)
        act = np.zeros(1, np.float32) if t == 0 else rng.uniform(-2, 2, 1).astype(np.float32)
        rew = 0.0 if t == 0 else float(-rng.uniform(0, 16))
        out.append((act, obs, rew, False, t == EPISODE - 1, {}))
    return out


class _PlainBuffer:
    def __init__(self, memory: list) -> None:
        self.memory = memory
        self.sources = None
        self.stat_train_return = 0.0
        self.stat_test_return = 0.0
        self.stat_train_steps = 0
        self.stat_test_steps = 0

    def __len__(self) -> int:
        return len(self.memory)


def _loop_model_cls():
    """Our models with the critics as a ModuleList of separate MLPs, evaluated one by one in
    Python (the 'before' of the batched ensemble)."""
    import torch

    from tmrl.models import SquashedGaussianMLPActor, flatten_obs, mlp, space_dim

    class Critic(torch.nn.Module):
        def __init__(self, obs_space, act_space):
            super().__init__()
            self.q = mlp([space_dim(obs_space) + act_space.shape[0], 256, 256, 1], torch.nn.ReLU)

        def forward(self, obs, act):
            return self.q(torch.cat((flatten_obs(obs), act), -1)).squeeze(-1)

    class LoopActorCritic(torch.nn.Module):
        def __init__(self, observation_space, action_space, n=2):
            super().__init__()
            self.actor = SquashedGaussianMLPActor(observation_space, action_space)
            self.qs = torch.nn.ModuleList(Critic(observation_space, action_space) for _ in range(n))

    return LoopActorCritic


def _build(side: str, algo: str, variant: str = ""):
    obs_space, act_space = _spaces()
    if side == "tmrl":
        from tmrl.custom.custom_memories import GenericTorchMemory

        from tmrl.custom.custom_algorithms import REDQSACAgent, SpinupSacAgent

        memory = GenericTorchMemory(memory_size=1e6, batch_size=BATCH, nb_steps=1, device="cpu")
        cls = SpinupSacAgent if algo == "sac" else REDQSACAgent
        agent = cls(observation_space=obs_space, action_space=act_space, device="cpu")
        memory_name = "tmrl 0.7.1 GenericTorchMemory"
    else:
        from tmrl.algorithms import REDQSACAgent, SACAgent
        from tmrl.memory import GenericTorchMemory
        from tmrl.models import MLPActorCritic, REDQMLPActorCritic
        from tmrl.util import partial

        memory = GenericTorchMemory(device="cpu", nb_steps=1, memory_size=1_000_000, batch_size=BATCH)
        cls = SACAgent if algo == "sac" else REDQSACAgent
        model = MLPActorCritic if algo == "sac" else REDQMLPActorCritic
        critic_dtype = "bfloat16" if variant == "bf16" else None
        agent = cls(
            observation_space=obs_space,
            action_space=act_space,
            device="cpu",
            model_cls=partial(model, critic_dtype=critic_dtype),
        )
        memory_name = "tmrl.memory.GenericTorchMemory"
    memory.append(_PlainBuffer(_samples()))
    return memory, agent, memory_name


def _measure(memory, agent, mode: str, seconds: float) -> dict[str, Any]:
    import torch

    batch = memory.sample()
    for _ in range(3):  # warm-up: allocator, optimizer state
        agent.train(memory.sample() if mode == "full" else batch)
    n = 0
    t_sample = 0.0
    cpu0 = time.process_time()
    start = time.perf_counter()
    while True:
        if mode == "full":
            t0 = time.perf_counter()
            batch = memory.sample()
            t_sample += time.perf_counter() - t0
        agent.train(batch)
        n += 1
        elapsed = time.perf_counter() - start
        if elapsed >= seconds and n >= 5:
            break
    cpu = time.process_time() - cpu0
    return {
        "updates_per_s": n / elapsed,
        "sample_share": t_sample / elapsed,
        "cpu_per_update_ms": 1000 * cpu / n,
        "updates": n,
        "threads": torch.get_num_threads(),
    }


def worker_main(side: str, threads: int | None) -> None:
    import torch

    if threads:
        torch.set_num_threads(threads)
    torch.manual_seed(0)
    built: dict[str, tuple] = {}
    for line in sys.stdin:
        cmd = json.loads(line)
        if cmd.get("quit"):
            break
        key = cmd["algo"] + ":" + cmd.get("variant", "")
        if key not in built:
            built[key] = _build(side, cmd["algo"], cmd.get("variant", ""))
        memory, agent, memory_name = built[key]
        res = _measure(memory, agent, cmd["mode"], cmd["seconds"])
        res["memory"] = memory_name
        print(RESULT + json.dumps(res), flush=True)


# --- driver --------------------------------------------------------------------------------------


class _Worker:
    def __init__(self, side: str, python: str, env: dict[str, str], cwd: str, threads: int | None) -> None:
        args = [python, str(Path(__file__).resolve()), "--worker", side]
        if threads:
            args += ["--threads", str(threads)]
        self.side = side
        self.proc = subprocess.Popen(
            args,
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            stderr=subprocess.DEVNULL,
            text=True,
            env=env,
            cwd=cwd,
        )

    def run(self, algo: str, mode: str, seconds: float, variant: str = "") -> dict[str, Any]:
        assert self.proc.stdin and self.proc.stdout
        cmd = {"algo": algo, "mode": mode, "seconds": seconds, "variant": variant}
        self.proc.stdin.write(json.dumps(cmd) + "\n")
        self.proc.stdin.flush()
        for line in self.proc.stdout:
            if line.startswith(RESULT):
                return json.loads(line[len(RESULT) :])
        raise RuntimeError(f"{self.side} worker exited (code {self.proc.wait()})")

    def close(self) -> None:
        if self.proc.poll() is None and self.proc.stdin:
            self.proc.stdin.write(json.dumps({"quit": True}) + "\n")
            self.proc.stdin.flush()
            self.proc.wait(timeout=30)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--worker", choices=["ours", "tmrl"], help=argparse.SUPPRESS)
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--seconds", type=float, default=4.0, help="per measurement")
    parser.add_argument(
        "--threads", type=int, default=None, help="torch threads on both sides (default: torch's)"
    )
    parser.add_argument("--algos", default="sac,redq")
    parser.add_argument("--anchor-python", default="/tmp/tmrl-anchor/venv/bin/python")
    parser.add_argument("--anchor-home", default="/tmp/tmrl-anchor/home")
    parser.add_argument("--no-anchor", action="store_true", help="measure ours only")
    parser.add_argument("--bf16", action="store_true", help="also measure ours with critic_dtype='bfloat16'")
    parser.add_argument(
        "--loop",
        action="store_true",
        help="also measure ours with a Python loop over separate critics (before)",
    )
    args = parser.parse_args()
    if args.worker:
        worker_main(args.worker, args.threads)
        return

    repo = Path(__file__).resolve().parent.parent
    env_ours = dict(os.environ, PYTHONPATH=str(repo))
    env_tmrl = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "TMRL_DATA")}
    env_tmrl["HOME"] = args.anchor_home
    sides = {"ours": _Worker("ours", sys.executable, env_ours, str(repo), args.threads)}
    if not args.no_anchor:
        if not Path(args.anchor_python).exists():
            sys.exit(
                f"no tmrl 0.7.1 at {args.anchor_python}: run shared/anchors/setup-tmrl-0.7.1.sh or pass --no-anchor"
            )
        # Outside the repository, so that `import tmrl` finds the installed 0.7.1.
        sides["tmrl"] = _Worker("tmrl", args.anchor_python, env_tmrl, "/tmp", args.threads)

    algos = args.algos.split(",")
    # (label, worker, variant): "ours-bf16" runs in the same worker process as "ours".
    runs = [("ours", "ours", "")] + ([("tmrl", "tmrl", "")] if "tmrl" in sides else [])
    if args.bf16:
        runs.append(("ours-bf16", "ours", "bf16"))
    if args.loop:
        runs.append(("ours-loop", "ours", "loop"))
    results: dict[tuple[str, str, str], list[dict[str, Any]]] = {}
    print(
        f"batch {BATCH}, MLP 256x256, {N_SAMPLES} Pendulum-shaped samples in memory; "
        f"{args.rounds} rounds of {args.seconds:.0f} s per measurement, interleaved"
    )
    try:
        for rnd in range(args.rounds):
            print(f"round {rnd + 1}: load average {os.getloadavg()[0]:.2f}", flush=True)
            for algo in algos:
                for mode in ("full", "agent"):
                    order = runs if rnd % 2 == 0 else runs[::-1]
                    for side, worker, variant in order:
                        res = sides[worker].run(algo, mode, args.seconds, variant)
                        results.setdefault((side, algo, mode), []).append(res)
                        share = f", sampling {100 * res['sample_share']:.1f}%" if mode == "full" else ""
                        print(
                            f"  {side:9s} {algo:5s} {mode:6s} {res['updates_per_s']:7.1f} updates/s"
                            f" ({res['cpu_per_update_ms']:.1f} ms CPU/update, {res['threads']} threads{share})",
                            flush=True,
                        )
    finally:
        for w in sides.values():
            w.close()

    print(f"\nsummary (median over rounds; best in brackets), load average now {os.getloadavg()[0]:.2f}")
    for algo in algos:
        for mode in ("full", "agent"):
            line = f"  {algo:5s} {mode:6s}"
            med, cpu = {}, {}
            for side, _, _ in runs:
                rates = [r["updates_per_s"] for r in results[(side, algo, mode)]]
                med[side] = statistics.median(rates)
                cpu[side] = statistics.median(r["cpu_per_update_ms"] for r in results[(side, algo, mode)])
                line += f"  {side}: {med[side]:7.1f} [{max(rates):7.1f}]"
                if mode == "full":
                    shares = [r["sample_share"] for r in results[(side, algo, mode)]]
                    line += f" sampling {100 * statistics.median(shares):4.1f}%"
            if "tmrl" in med:
                line += f"  ratio {med['ours'] / med['tmrl']:.2f}x"
                for other in ("ours-bf16", "ours-loop"):
                    if other in med:
                        line += f" ({other[5:]} {med[other] / med['tmrl']:.2f}x)"
            print(line)
            if "tmrl" in cpu:
                parts = ", ".join(f"{side} {ms:.1f}" for side, ms in cpu.items())
                ratio = cpu["tmrl"] / cpu["ours"]
                print(f"  {'':12s} CPU ms per update: {parts}  (tmrl/ours {ratio:.2f}x)")
    print(f"  memories: ours = {results[('ours', algos[0], 'full')][0]['memory']}")


if __name__ == "__main__":
    main()
