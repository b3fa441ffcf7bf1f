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

TrackMania cases (``--cases tmfull,tmlidar``), SAC only, the original's config values (ALG of
its TM20FULL config: lr, betas, gamma, alpha...):

- ``tmfull``: TM20FULL-shaped data, speed/gear/rpm and a history of 4 grayscale 64x64 images
  plus 2 actions, CNN actor-critic (ours: the ``TM20FULL`` parts of
  :func:`tmrl.sim.interfaces.pipeline_parts`, i.e. ``ImageMemory`` and ``CNNActorCritic``;
  theirs: ``MemoryTMFull`` and ``VanillaCNNActorCritic`` with ``SpinupSacAgent``);
- ``tmlidar``: TM20LIDAR-shaped data, speed and a history of 4 lidars of 19 beams plus 2
  actions, MLP 256x256 (ours: ``LidarMemory``, ``LidarActorCritic``; theirs: ``MemoryTMLidar``,
  ``MLPActorCritic``).

Both sides store the same synthetic episodes (random frames or lidars, episodes of 1000, 400,
700 and 250 steps, the last truncated or terminated), each side compressed by its own sample
compressor (ours ``compress_full_sample``/``compress_lidar_sample``; theirs
``get_local_buffer_sample_tm20_imgs``/``get_local_buffer_sample_lidar``) from the same
preprocessed observations. ``--memory-bytes`` also prints the bytes each side's memory holds per
stored sample (tracemalloc, ``--memory-bytes-samples`` samples, memory sized to fit them).

Allocator: our worker calls :func:`tmrl.util.reuse_freed_memory`, as our trainer does when its
``TorchTrainingOffline`` is built (glibc keeps freed blocks for the next update instead of
page-faulting them in again; it matters for the CNN, whose activations are tens of MiB).
``--malloc-both`` gives tmrl 0.7.1 the same settings, to separate that gain from the rest.

Usage::

    /work/venv/bin/python bench/trainer_speed.py [--rounds 3] [--seconds 4] [--threads N]
        [--cases pendulum,tmfull,tmlidar] [--memory-bytes] [--malloc-both]
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
import tracemalloc
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


# --- TrackMania-shaped cases ---------------------------------------------------------------------

TM_SAMPLES = {"tmfull": 50_000, "tmlidar": 100_000}
TM_EPISODES = (1000, 400, 700, 250)  # steps; 1000 = ep_max_length, so truncated, else terminated
TM_HIST = 4
TM_ACT_BUF = 2
TM_IMG = 64
TM_BEAMS = 19
# The ALG values of tmrl 0.7.1's default TM20FULL config, on both sides.
TM_ALG: dict[str, Any] = {
    "lr_actor": 1e-5, "lr_critic": 5e-5, "lr_entropy": 3e-4, "gamma": 0.995, "polyak": 0.995,
    "learn_entropy_coef": False, "target_entropy": -0.5, "alpha": 0.01, "optimizer_actor": "adam",
    "optimizer_critic": "adam", "betas_actor": (0.997, 0.997), "betas_critic": (0.997, 0.997),
    "l2_actor": 0.0, "l2_critic": 0.0,
}


def _tm_spaces(case: str):
    """Preprocessed observation space (what the models see) and action space."""
    import numpy as np
    from gymnasium import spaces

    act = spaces.Box(-1.0, 1.0, (3,), np.float32)
    one = spaces.Box(-np.inf, np.inf, (1,), np.float32)
    if case == "tmfull":
        imgs = spaces.Box(0.0, 1.0, (TM_HIST, TM_IMG, TM_IMG), np.float32)
        obs = spaces.Tuple((one, one, one, imgs, act, act))
    else:
        lidars = spaces.Box(0.0, np.inf, (TM_HIST * TM_BEAMS,), np.float32)
        obs = spaces.Tuple((one, lidars, act, act))
    return obs, act


def _tm_samples(case: str, n: int, compressor, seed: int = 0) -> list:
    """``n`` samples as a worker sends them: the preprocessed observation of each step (history
    and action buffer built as the interfaces and rtgym do), then ``compressor``."""
    from collections import deque

    import numpy as np

    rng = np.random.default_rng(seed)
    out: list = []
    ep = 0
    while len(out) < n:
        length = TM_EPISODES[ep % len(TM_EPISODES)]
        ep += 1
        if case == "tmfull":
            frames = rng.integers(0, 256, (length, TM_IMG, TM_IMG), dtype=np.uint8)
        else:
            frames = rng.uniform(0.0, 400.0, (length, TM_BEAMS)).astype(np.float32)
        hist: deque = deque([frames[0]] * TM_HIST, maxlen=TM_HIST)
        default = np.zeros(3, np.float32)
        acts: deque = deque([default] * TM_ACT_BUF, maxlen=TM_ACT_BUF)
        for t in range(length):
            if len(out) >= n:
                break
            if t == 0:
                act, rew = default, 0.0
            else:
                act = rng.uniform(-1.0, 1.0, 3).astype(np.float32)
                rew = float(rng.uniform(-0.1, 1.0))
                hist.append(frames[t])
                acts.append(act)
            speed = np.array([rng.uniform(0.0, 300.0)], np.float32)
            if case == "tmfull":
                gear = np.array([float(rng.integers(0, 6))], np.float32)
                rpm = np.array([rng.uniform(0.0, 11000.0)], np.float32)
                imgs = np.stack(hist).astype(np.float32) / 256.0
                obs = (speed / 1000.0, gear / 10.0, rpm / 10000.0, imgs, *acts)
            else:
                obs = (speed, np.stack(hist).reshape(-1), *acts)
            last = t == length - 1
            terminated = last and length < 1000
            truncated = last and length >= 1000
            out.append(compressor(act, obs, rew, terminated, truncated, {}))
    return out


def _tm_memory(side: str, case: str, memory_size: int):
    """Each side's memory for ``case``, built as its pipeline builds it, and its compressor."""
    if side == "tmrl":
        from tmrl.custom import custom_memories as cm

        cls, compressor = (
            (cm.MemoryTMFull, cm.get_local_buffer_sample_tm20_imgs)
            if case == "tmfull"
            else (cm.MemoryTMLidar, cm.get_local_buffer_sample_lidar)
        )
        memory = cls(memory_size=memory_size, batch_size=BATCH, dataset_path="", imgs_obs=TM_HIST,
                     act_buf_len=TM_ACT_BUF, nb_steps=1, sample_preprocessor=None, crc_debug=False, device="cpu")
        return memory, compressor, f"tmrl 0.7.1 {cls.__name__}"
    from tmrl.sim.interfaces import pipeline_parts

    parts = pipeline_parts("TM20FULL" if case == "tmfull" else "TM20LIDAR")
    memory = parts["memory_cls"](hist_len=TM_HIST, act_buf_len=TM_ACT_BUF, memory_size=memory_size,
                                 batch_size=BATCH, device="cpu", nb_steps=1)
    return memory, parts["sample_compressor"], f"tmrl.driving.memories.{type(memory).__name__}"


def _conv_bf16_cnn(observation_space, action_space, **kwargs):
    """Experimental, not in the library: our CNN actor-critic whose convolutions run under
    bfloat16 autocast (weights, optimizer state, the MLPs and every loss stay float32). Fast on
    CPUs with native bfloat16 (AVX512-BF16, AMX), slow where it is emulated."""
    import torch

    from tmrl.driving.models import CNNActorCritic, ImageEncoder

    class BF16Encoder(ImageEncoder):
        def forward(self, imgs):
            with torch.autocast("cpu", dtype=torch.bfloat16):
                x = self.convs(imgs)
            return x.flatten(1).float()

    model = CNNActorCritic(observation_space, action_space, **kwargs)
    for module in model.modules():
        if type(module) is ImageEncoder:
            module.__class__ = BF16Encoder
    return model


def _build_tm(side: str, case: str, variant: str = ""):
    obs_space, act_space = _tm_spaces(case)
    memory, compressor, memory_name = _tm_memory(side, case, 1_000_000)
    if side == "tmrl":
        from tmrl.custom.custom_algorithms import SpinupSacAgent
        from tmrl.custom.custom_models import MLPActorCritic, VanillaCNNActorCritic

        model = VanillaCNNActorCritic if case == "tmfull" else MLPActorCritic
        agent = SpinupSacAgent(observation_space=obs_space, action_space=act_space, device="cpu",
                               model_cls=model, **TM_ALG)
    else:
        from tmrl.algorithms.sac import SACAgent
        from tmrl.sim.interfaces import pipeline_parts

        parts = pipeline_parts("TM20FULL" if case == "tmfull" else "TM20LIDAR")
        model_cls = _conv_bf16_cnn if variant == "convbf16" else parts["model_cls"]
        agent = SACAgent(observation_space=obs_space, action_space=act_space, device="cpu",
                         model_cls=model_cls, **TM_ALG)
    memory.append(_PlainBuffer(_tm_samples(case, TM_SAMPLES[case], compressor)))
    return memory, agent, memory_name


def _tm_memory_bytes(side: str, case: str, n: int) -> dict[str, Any]:
    """Bytes the memory holds per stored sample: everything tracemalloc sees still allocated
    once the memory holds ``n`` samples (memory sized ``n``) and a batch was drawn, the samples'
    list itself released."""
    import gc

    _tm_memory(side, case, 16)  # imports happen outside the measurement
    _tm_samples(case, 8, lambda *sample: sample)
    gc.collect()
    tracemalloc.start()
    base = tracemalloc.get_traced_memory()[0]
    memory, compressor, name = _tm_memory(side, case, n)
    samples = _tm_samples(case, n, compressor, seed=1)
    buf = _PlainBuffer(samples)
    memory.append(buf)
    del buf, samples
    memory.sample()  # caches built on first sampling count too
    gc.collect()
    held = tracemalloc.get_traced_memory()[0] - base
    tracemalloc.stop()
    del memory
    gc.collect()
    return {"bytes_per_sample": held / n, "samples": n, "memory": name}


def _measure(memory, agent, mode: str, seconds: float, warmup: int = 3, min_updates: int = 5) -> dict[str, Any]:
    import torch

    batch = memory.sample()
    for _ in range(warmup):  # warm-up: allocator, optimizer state
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
        if elapsed >= seconds and n >= min_updates:
            break
    cpu = time.process_time() - cpu0
    return {
        "updates_per_s": n / elapsed,
        "sample_share": t_sample / elapsed,
        "cpu_per_update_ms": 1000 * cpu / n,
        "updates": n,
        "threads": torch.get_num_threads(),
    }


def _glibc_reuse_freed_memory() -> bool:
    """The mallopt settings of ``tmrl.util.reuse_freed_memory``, for the tmrl 0.7.1 side
    (``--malloc-both``), whose interpreter imports the original tmrl."""
    import ctypes

    mallopt = ctypes.CDLL(None).mallopt
    mallopt.argtypes = [ctypes.c_int, ctypes.c_int]
    return all(mallopt(p, v) == 1 for p, v in ((-3, 256 << 20), (-1, 1 << 30), (-2, 64 << 20)))


def worker_main(side: str, threads: int | None, malloc: bool = False) -> None:
    import torch

    if threads:
        torch.set_num_threads(threads)
    if side == "ours":
        # What our trainer does when TorchTrainingOffline is built (the agents are built directly
        # here): keep freed blocks for reuse instead of page-faulting them in at every update.
        from tmrl.util import reuse_freed_memory

        reuse_freed_memory()
    elif malloc:
        _glibc_reuse_freed_memory()
    torch.manual_seed(0)
    built: dict[str, tuple] = {}
    for line in sys.stdin:
        cmd = json.loads(line)
        if cmd.get("quit"):
            break
        case = cmd.get("case", "pendulum")
        if "memory_bytes" in cmd:
            print(RESULT + json.dumps(_tm_memory_bytes(side, case, int(cmd["memory_bytes"]))), flush=True)
            continue
        key = case + ":" + cmd["algo"] + ":" + cmd.get("variant", "")
        if key not in built:
            if case == "pendulum":
                built[key] = _build(side, cmd["algo"], cmd.get("variant", ""))
            else:
                built[key] = _build_tm(side, case, cmd.get("variant", ""))
        memory, agent, memory_name = built[key]
        # A CNN update takes seconds on a CPU: fewer warm-up and minimum updates.
        slow = case == "tmfull"
        res = _measure(memory, agent, cmd["mode"], cmd["seconds"], warmup=1 if slow else 3,
                       min_updates=3 if slow else 5)
        res["memory"] = memory_name
        print(RESULT + json.dumps(res), flush=True)


# --- driver --------------------------------------------------------------------------------------


class _Worker:
    def __init__(self, side: str, python: str, env: dict[str, str], cwd: str, threads: int | None,
                 malloc: bool = False) -> None:
        args = [python, str(Path(__file__).resolve()), "--worker", side]
        if threads:
            args += ["--threads", str(threads)]
        if malloc:
            args += ["--malloc-both"]
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

    def run(self, algo: str, mode: str, seconds: float, variant: str = "", case: str = "pendulum") -> dict[str, Any]:
        return self.ask({"algo": algo, "mode": mode, "seconds": seconds, "variant": variant, "case": case})

    def ask(self, cmd: dict[str, Any]) -> dict[str, Any]:
        assert self.proc.stdin and self.proc.stdout
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


CASES = ("pendulum", "tmfull", "tmlidar")
CASE_TITLES = {
    "pendulum": f"Pendulum-shaped, MLP 256x256, {N_SAMPLES} samples in memory",
    "tmfull": f"TM20FULL-shaped, CNN, history {TM_HIST} of {TM_IMG}x{TM_IMG}, {TM_SAMPLES['tmfull']} samples",
    "tmlidar": f"TM20LIDAR-shaped, MLP 256x256, history {TM_HIST} of {TM_BEAMS} beams, "
    f"{TM_SAMPLES['tmlidar']} samples",
}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--worker", choices=["ours", "tmrl"], help=argparse.SUPPRESS)
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--seconds", type=float, default=4.0, help="per measurement")
    parser.add_argument(
        "--threads", type=int, default=None, help="torch threads on both sides (default: torch's)"
    )
    parser.add_argument("--algos", default="sac,redq", help="algorithms of the pendulum case")
    parser.add_argument(
        "--cases", default="pendulum", help=f"comma-separated, among {', '.join(CASES)} (TM cases: SAC only)"
    )
    parser.add_argument("--modes", default="full,agent", help="full (sample + train) and/or agent (train only)")
    parser.add_argument(
        "--memory-bytes", action="store_true", help="also print each side's bytes per stored sample (TM cases)"
    )
    parser.add_argument("--memory-bytes-samples", type=int, default=20_000)
    parser.add_argument("--anchor-python", default="/tmp/tmrl-anchor/venv/bin/python")
    parser.add_argument("--anchor-home", default="/tmp/tmrl-anchor/home")
    parser.add_argument("--no-anchor", action="store_true", help="measure ours only")
    parser.add_argument("--bf16", action="store_true", help="also measure ours with critic_dtype='bfloat16' (pendulum)")
    parser.add_argument(
        "--conv-bf16",
        action="store_true",
        help="also measure ours (tmfull) with the convolutions under bfloat16 autocast (experimental, bench only)",
    )
    parser.add_argument(
        "--malloc-both",
        action="store_true",
        help="give tmrl 0.7.1 the allocator settings our trainer uses (tmrl.util.reuse_freed_memory)",
    )
    parser.add_argument(
        "--loop",
        action="store_true",
        help="also measure ours with a Python loop over separate critics (before; pendulum)",
    )
    args = parser.parse_args()
    if args.worker:
        worker_main(args.worker, args.threads, args.malloc_both)
        return
    cases = [c for c in args.cases.split(",") if c]
    unknown = sorted(set(cases) - set(CASES))
    if unknown:
        sys.exit(f"unknown case(s) {unknown}: use {', '.join(CASES)}")
    modes = [m for m in args.modes.split(",") if m]

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
        sides["tmrl"] = _Worker("tmrl", args.anchor_python, env_tmrl, "/tmp", args.threads, args.malloc_both)

    # (case, algo) jobs; per job the runs (label, worker, variant). "ours-bf16" and "ours-loop"
    # run in the same worker process as "ours".
    jobs: list[tuple[str, str]] = []
    for case in cases:
        jobs += [(case, a) for a in args.algos.split(",")] if case == "pendulum" else [(case, "sac")]
    base_runs = [("ours", "ours", "")] + ([("tmrl", "tmrl", "")] if "tmrl" in sides else [])
    pendulum_runs = list(base_runs)
    if args.bf16:
        pendulum_runs.append(("ours-bf16", "ours", "bf16"))
    if args.loop:
        pendulum_runs.append(("ours-loop", "ours", "loop"))

    tmfull_runs = base_runs + ([("ours-convbf16", "ours", "convbf16")] if args.conv_bf16 else [])

    def runs_of(case: str) -> list[tuple[str, str, str]]:
        return {"pendulum": pendulum_runs, "tmfull": tmfull_runs}.get(case, base_runs)

    results: dict[tuple[str, str, str, str], list[dict[str, Any]]] = {}
    print(f"batch {BATCH}; {args.rounds} rounds of {args.seconds:.0f} s per measurement, interleaved; cases:")
    print("  allocator: ours keeps freed memory for reuse (tmrl.util.reuse_freed_memory); tmrl 0.7.1 "
          + ("gets the same settings (--malloc-both)" if args.malloc_both else "runs with glibc's defaults"))
    for case in cases:
        print(f"  {case}: {CASE_TITLES[case]}")
    load_start = os.getloadavg()
    mem_bytes: dict[tuple[str, str], dict[str, Any]] = {}
    try:
        if args.memory_bytes:
            for case in (c for c in cases if c != "pendulum"):
                for side, w in sides.items():
                    mem_bytes[(side, case)] = w.ask({"case": case, "memory_bytes": args.memory_bytes_samples})
        for rnd in range(args.rounds):
            print(f"round {rnd + 1}: load average {os.getloadavg()[0]:.2f}", flush=True)
            for case, algo in jobs:
                for mode in modes:
                    runs = runs_of(case)
                    order = runs if rnd % 2 == 0 else runs[::-1]
                    for side, worker, variant in order:
                        res = sides[worker].run(algo, mode, args.seconds, variant, case)
                        results.setdefault((case, side, algo, mode), []).append(res)
                        share = f", sampling {100 * res['sample_share']:.1f}%" if mode == "full" else ""
                        label = algo if case == "pendulum" else case
                        print(
                            f"  {side:13s} {label:7s} {mode:6s} {res['updates_per_s']:8.2f} updates/s"
                            f" ({res['cpu_per_update_ms']:.1f} ms CPU/update, {res['threads']} threads{share})",
                            flush=True,
                        )
    finally:
        for w in sides.values():
            w.close()

    print(
        f"\nsummary (median over rounds; best in brackets), load average at start "
        f"{load_start[0]:.2f}/{load_start[1]:.2f}/{load_start[2]:.2f}, now {os.getloadavg()[0]:.2f}"
    )
    for case, algo in jobs if args.rounds > 0 else []:  # --rounds 0: memory bytes only
        runs = runs_of(case)
        label = algo if case == "pendulum" else case
        for mode in modes:
            line = f"  {label:7s} {mode:6s}"
            med, cpu = {}, {}
            for side, _, _ in runs:
                rs = results[(case, side, algo, mode)]
                rates = [r["updates_per_s"] for r in rs]
                med[side] = statistics.median(rates)
                cpu[side] = statistics.median(r["cpu_per_update_ms"] for r in rs)
                line += f"  {side}: {med[side]:7.2f} [{max(rates):7.2f}]"
                if mode == "full":
                    shares = [r["sample_share"] for r in rs]
                    line += f" sampling {100 * statistics.median(shares):4.1f}%"
            if "tmrl" in med:
                line += f"  ratio {med['ours'] / med['tmrl']:.2f}x"
                for other in ("ours-bf16", "ours-loop", "ours-convbf16"):
                    if other in med:
                        line += f" ({other[5:]} {med[other] / med['tmrl']:.2f}x)"
            print(line)
            if "tmrl" in cpu:
                parts = ", ".join(f"{side} {ms:.1f}" for side, ms in cpu.items())
                ratios = ", ".join(f"tmrl/{side} {cpu['tmrl'] / ms:.2f}x" for side, ms in cpu.items() if side != "tmrl")
                print(f"  {'':14s} CPU ms per update: {parts}  ({ratios})")
        first = results[(case, "ours", algo, modes[0])][0]["memory"]
        theirs = results.get((case, "tmrl", algo, modes[0]))
        print(f"  {'':14s} memories: ours = {first}" + (f", theirs = {theirs[0]['memory']}" if theirs else ""))
    if mem_bytes:
        frame = TM_IMG * TM_IMG
        print("\nreplay memory bytes per stored sample (tracemalloc)")
        for (side, case), res in mem_bytes.items():
            extra = f" ({res['bytes_per_sample'] / frame:.3f} x one {TM_IMG}x{TM_IMG} uint8 frame)" if case == "tmfull" else ""
            print(f"  {side:5s} {case:7s} {res['bytes_per_sample']:9.1f} B/sample over {res['samples']} samples{extra}"
                  f"  [{res['memory']}]")


if __name__ == "__main__":
    main()
