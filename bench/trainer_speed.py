"""Trainer speed: SAC and REDQ-SAC updates per second, ours beside tmrl 0.7.1, Stable-Baselines3
and the matrix-product floor of the same update.

    python -m bench trainer_speed                         # Pendulum-shaped SAC and REDQ-SAC
    python -m bench trainer_speed --cases tmlidar,tmfull  # TrackMania-shaped (SAC)
    python -m bench trainer_speed --device cuda           # every side on the GPU

Every side runs in its own process with the same torch thread count, on the same synthetic data
(Pendulum-shaped: observation ``(3,)`` in a Tuple, action ``(1,)``, episodes of 200 steps, 100k
samples in memory), MLP 256x256, batch 256, and the same allocator settings
(:func:`tmrl.util.reuse_freed_memory`, which our trainer applies; ``--glibc-defaults-for-tmrl``
adds a labelled line with tmrl 0.7.1 on glibc's defaults). Rounds alternate the order of the sides.

``--device`` (default ``cpu``, the published figures' device; ``cuda``, ``cuda:N`` or ``auto``)
puts every side's replay memory (where it collates its batches) and agent on that device: ours,
tmrl 0.7.1's (``device=`` of its memories and agents) and Stable-Baselines3's (``SAC(device=)``).
The first printed line and the record's settings name it, with the GPU's name and driver. On a
GPU each timing ends with ``torch.cuda.synchronize``, so the queued work is counted; a side that
fails on the device (tmrl 0.7.1's REDQ-SAC on CUDA) gets ``-`` and its error, and the others go on.

Figures, per side and algorithm:

- ``full``: ``batch = memory.sample(); agent.train(batch)`` in a loop (each side's own replay
  memory); for Stable-Baselines3, ``model.train(gradient_steps=N, batch_size=256)`` on a replay
  buffer filled with the same samples (SAC only: it has no REDQ);
- ``agent``: ``agent.train(batch)`` on one ready batch (ours and tmrl 0.7.1);
- ``floor``: the matrix products of one update (the same shapes: every linear layer's forward
  and backward products that the update computes), timed alone with torch on the same threads
  (on the GPU with ``--device cuda``), in milliseconds; ``floor / ours`` is the fraction of the floor our update reaches
  (1.0: the update costs no more than its products).

TrackMania cases (``--cases tmfull,tmlidar``), SAC only, with the ALG values of the original's
TM20FULL config on both sides: ``tmfull``, speed/gear/rpm and 4 grayscale 64x64 images plus 2
actions, CNN actor-critic (ours: ``ImageMemory`` and ``CNNActorCritic``; theirs: ``MemoryTMFull``
and ``VanillaCNNActorCritic``); ``tmlidar``, speed and 4 lidars of 19 beams plus 2 actions, MLP
256x256 (ours: ``LidarMemory``, ``LidarActorCritic``; theirs: ``MemoryTMLidar``,
``MLPActorCritic``). Both sides store the same synthetic episodes, each compressed by its own
sample compressor. ``--memory-bytes`` adds the bytes each side's memory holds per stored sample.

Where our batches are built: on a GPU our memories keep their rings there (``MEMORY_ON_DEVICE``
``"auto"``, :mod:`tmrl.memory.resident`) and gather each batch on the device; ``--host-memory``
adds ``ours hostmem``, the same memory with ``"off"`` (gathered on the host, then copied over), in
``full`` mode. The ``memory`` field of each figure says which (``(rings on cuda:0)``).
"""

from __future__ import annotations

import argparse
import time
import tracemalloc
from typing import Any

from bench import harness

OBS_HIGH = (1.0, 1.0, 8.0)
EPISODE = 200
N_SAMPLES = 100_000
BATCH = 256
HIDDEN = 256


# --- child side: tmrl 0.7.1 or ours (runs in either interpreter) ------------------------------------


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


def _build(side: str, algo: str, variant: str = "", device: str = "cpu"):
    obs_space, act_space = _spaces()
    if side == "tmrl":
        from tmrl.custom.custom_memories import GenericTorchMemory

        from tmrl.custom.custom_algorithms import REDQSACAgent, SpinupSacAgent

        memory = GenericTorchMemory(memory_size=1e6, batch_size=BATCH, nb_steps=1, device=device)
        cls = SpinupSacAgent if algo == "sac" else REDQSACAgent
        agent = cls(observation_space=obs_space, action_space=act_space, device=device)
        memory_name = "tmrl 0.7.1 GenericTorchMemory"
    else:
        from tmrl.algorithms import REDQSACAgent, SACAgent
        from tmrl.memory import GenericTorchMemory
        from tmrl.models import MLPActorCritic, REDQMLPActorCritic
        from tmrl.util import partial

        memory = GenericTorchMemory(device=device, nb_steps=1, memory_size=1_000_000, batch_size=BATCH,
                                    on_device="off" if variant == "hostmem" else "auto")
        cls = SACAgent if algo == "sac" else REDQSACAgent
        model = MLPActorCritic if algo == "sac" else REDQMLPActorCritic
        critic_dtype = "bfloat16" if variant == "bf16" else None
        agent = cls(
            observation_space=obs_space,
            action_space=act_space,
            device=device,
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


def _tm_memory(side: str, case: str, memory_size: int, device: str = "cpu", variant: str = ""):
    """Each side's memory for ``case``, built as its pipeline builds it (its batches collated on
    ``device``; ours with its rings on the host for the ``hostmem`` variant), and its compressor."""
    if side == "tmrl":
        from tmrl.custom import custom_memories as cm

        cls, compressor = (
            (cm.MemoryTMFull, cm.get_local_buffer_sample_tm20_imgs)
            if case == "tmfull"
            else (cm.MemoryTMLidar, cm.get_local_buffer_sample_lidar)
        )
        memory = cls(memory_size=memory_size, batch_size=BATCH, dataset_path="", imgs_obs=TM_HIST,
                     act_buf_len=TM_ACT_BUF, nb_steps=1, sample_preprocessor=None, crc_debug=False, device=device)
        return memory, compressor, f"tmrl 0.7.1 {cls.__name__}"
    from tmrl.sim.interfaces import pipeline_parts

    parts = pipeline_parts("TM20FULL" if case == "tmfull" else "TM20LIDAR")
    memory = parts["memory_cls"](hist_len=TM_HIST, act_buf_len=TM_ACT_BUF, memory_size=memory_size,
                                 batch_size=BATCH, device=device, nb_steps=1,
                                 on_device="off" if variant == "hostmem" else "auto")
    return memory, parts["sample_compressor"], f"tmrl.driving.memories.{type(memory).__name__}"


def _build_tm(side: str, case: str, device: str = "cpu", variant: str = ""):
    obs_space, act_space = _tm_spaces(case)
    memory, compressor, memory_name = _tm_memory(side, case, 1_000_000, device, variant)
    if side == "tmrl":
        from tmrl.custom.custom_algorithms import SpinupSacAgent
        from tmrl.custom.custom_models import MLPActorCritic, VanillaCNNActorCritic

        model = VanillaCNNActorCritic if case == "tmfull" else MLPActorCritic
        agent = SpinupSacAgent(observation_space=obs_space, action_space=act_space, device=device,
                               model_cls=model, **TM_ALG)
    else:
        from tmrl.algorithms.sac import SACAgent
        from tmrl.sim.interfaces import pipeline_parts

        parts = pipeline_parts("TM20FULL" if case == "tmfull" else "TM20LIDAR")
        agent = SACAgent(observation_space=obs_space, action_space=act_space, device=device,
                         model_cls=parts["model_cls"], **TM_ALG)
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


def synchronizer(device: str):
    """A function that waits for the work queued on ``device`` (``torch.cuda.synchronize`` on a
    GPU, nothing on the CPU, where every call returns once its work is done)."""
    if str(device).startswith("cuda"):
        import torch

        return lambda: torch.cuda.synchronize(device)
    return lambda: None


def _measure(step, seconds: float, warmup: int, min_updates: int, updates_per_step: int = 1,
             sample=None, device: str = "cpu") -> dict[str, Any]:
    """Call ``step()`` (``updates_per_step`` updates each) for ``seconds``; ``sample()``, when
    given, is timed apart before each step (its share of the time is reported: on a GPU, the
    host's time in it). On a GPU the clock starts and stops with the queued work done."""
    import torch

    sync = synchronizer(device)
    for _ in range(warmup):  # allocator, optimizer state
        step(sample() if sample else None)
    sync()
    n = 0
    t_sample = 0.0
    cpu0 = time.process_time()
    start = time.perf_counter()
    while True:
        batch = None
        if sample is not None:
            t0 = time.perf_counter()
            batch = sample()
            t_sample += time.perf_counter() - t0
        step(batch)
        n += updates_per_step
        elapsed = time.perf_counter() - start
        if elapsed >= seconds and n >= min_updates:
            break
    sync()
    elapsed = time.perf_counter() - start
    return {"updates_per_s": n / elapsed, "sample_share": t_sample / elapsed,
            "cpu_ms_per_update": 1000 * (time.process_time() - cpu0) / n, "threads": torch.get_num_threads()}


def _measure_agent(memory, agent, mode: str, seconds: float, slow: bool, device: str = "cpu") -> dict[str, Any]:
    fixed = memory.sample()
    if mode == "full":
        return _measure(agent.train, seconds, 1 if slow else 3, 3 if slow else 5, sample=memory.sample,
                        device=device)
    return _measure(lambda _: agent.train(fixed), seconds, 1 if slow else 3, 3 if slow else 5, device=device)


# --- Stable-Baselines3 ---------------------------------------------------------------------------


def _sb3_model(device: str = "cpu"):
    """SB3 SAC on Pendulum-v1 (MLP 256x256, batch 256) on ``device`` (its replay buffer samples
    there too), the buffer holding the same synthetic samples as the others' memories
    (transitions rebuilt from the sample stream)."""
    import gymnasium
    import numpy as np
    from stable_baselines3 import SAC
    from stable_baselines3.common.logger import configure

    env = gymnasium.make("Pendulum-v1")
    model = SAC("MlpPolicy", env, batch_size=BATCH, buffer_size=N_SAMPLES, learning_starts=0, device=device,
                policy_kwargs={"net_arch": [HIDDEN, HIDDEN]}, seed=0)
    model.set_logger(configure(None, []))  # train() records its losses in the logger
    prev = None
    for act, obs, rew, terminated, truncated, _ in _samples():
        if prev is not None:
            model.replay_buffer.add(prev[None], obs[0][None], (act / 2.0)[None], np.array([rew]),
                                    np.array([terminated]), [{"TimeLimit.truncated": truncated}])
        prev = None if terminated or truncated else obs[0]
    return model


def _measure_sb3(model, seconds: float, device: str = "cpu") -> dict[str, Any]:
    # 8 gradient steps per call: SB3's per-call overhead (learning-rate update, logging) is
    # spread as it is in its own training loop (gradient_steps=-1 or a train_freq > 1).
    return _measure(lambda _: model.train(gradient_steps=8, batch_size=BATCH), seconds, 1, 16,
                    updates_per_step=8, device=device)


# --- the floor: the matrix products of one update -----------------------------------------------


def update_products(obs_dim: int, act_dim: int, hidden: int, batch: int, n_critics: int,
                    n_targets: int) -> list[tuple[int, int, int, int]]:
    """The matrix products of one SAC / REDQ-SAC update of MLPs with two hidden layers of
    ``hidden`` units, as ``(count, m, k, n)``: ``count`` products ``(m, k) @ (k, n)`` that the
    update can batch (the same layer of every critic of an ensemble), in the update's order.

    Each linear layer ``k -> n`` on a batch ``B`` costs ``(B, k, n)`` forward; backward adds the
    weight gradient ``(k, B, n)`` and the input gradient ``(B, n, k)`` when the input needs one.
    The actor's head is two layers ``hidden -> act_dim`` (mean and log-std).
    """
    actor = [(obs_dim, hidden), (hidden, hidden), (hidden, act_dim), (hidden, act_dim)]
    critic = [(obs_dim + act_dim, hidden), (hidden, hidden), (hidden, 1)]
    b = batch

    def forward(layers, count=1):
        return [(count, b, k, n) for k, n in layers]

    def backward(layers, weights: bool, first_input: bool, count=1):
        out = []
        for i, (k, n) in enumerate(layers):
            if weights:
                out.append((count, k, b, n))
            if i > 0 or first_input:
                out.append((count, b, n, k))
        return out

    return (
        forward(actor) * 2  # pi on o, a2 on o'
        + forward(critic, n_targets)  # target critics on (o', a2)
        + forward(critic, n_critics) + backward(critic, True, False, n_critics)  # Q(o, a), critic loss
        + forward(critic, n_critics) + backward(critic, False, True, n_critics)  # Q(o, pi), actor loss
        + backward(actor, True, False)  # actor weights
    )


def floor_ms(products: list[tuple[int, int, int, int]], seconds: float, device: str = "cpu") -> float:
    """Milliseconds that ``products`` take back to back on ``device``, each group of the same
    shape as one ``torch.bmm`` (one ``torch.mm`` when alone), into preallocated outputs (no
    allocation, no autograd, no other work): the median of repeated timings of the whole list
    (on a GPU, from the first launch to the end of the last product)."""
    import statistics

    import torch

    gen = torch.Generator().manual_seed(0)
    sync = synchronizer(device)
    operands = []
    for count, m, k, n in products:
        shape = (count,) if count > 1 else ()
        operands.append((torch.bmm if count > 1 else torch.mm, torch.randn(*shape, m, k, generator=gen).to(device),
                         torch.randn(*shape, k, n, generator=gen).to(device),
                         torch.empty(*shape, m, n, device=device)))

    def once() -> float:
        sync()
        t0 = time.perf_counter()
        for product, a, b, out in operands:
            product(a, b, out=out)
        sync()
        return time.perf_counter() - t0

    for _ in range(20):
        once()
    times = []
    start = time.perf_counter()
    while time.perf_counter() - start < seconds or len(times) < 20:
        times.append(once())
    return 1000 * statistics.median(times)


def _floor_case(case: str, algo: str) -> dict[str, int] | None:
    """Shapes of the floor of ``case`` (None: no floor for a CNN)."""
    n_critics, n_targets = (10, 2) if algo == "redq" else (2, 2)
    if case == "pendulum":
        return {"obs_dim": 3, "act_dim": 1, "n_critics": n_critics, "n_targets": n_targets}
    if case == "tmlidar":
        return {"obs_dim": 1 + TM_HIST * TM_BEAMS + 3 * TM_ACT_BUF, "act_dim": 3, "n_critics": 2, "n_targets": 2}
    return None


# --- child entry --------------------------------------------------------------------------------


def child_main(argv: list[str]) -> None:
    """Serve measurement requests for one side (``--side ours|tmrl|sb3``)."""
    parser = argparse.ArgumentParser()
    parser.add_argument("--side", required=True)
    parser.add_argument("--threads", type=int, default=None)
    parser.add_argument("--glibc-defaults", action="store_true")
    parser.add_argument("--device", default="cpu", help="resolved by the parent: cpu, cuda or cuda:N")
    args = parser.parse_args(argv)
    import torch

    if args.threads:
        torch.set_num_threads(args.threads)
    if not args.glibc_defaults:
        # What our trainer does when TorchTrainingOffline is built, given to every side.
        _reuse_freed_memory()
    torch.manual_seed(0)
    device = args.device
    built: dict[str, Any] = {}
    failed: dict[str, str] = {}

    def measure(req: dict[str, Any], case: str, algo: str, key: str) -> dict[str, Any]:
        if args.side == "sb3":
            if key not in built:
                built[key] = _sb3_model(device)
            return _measure_sb3(built[key], req["seconds"], device)
        if key not in built:
            built[key] = (_build(args.side, algo, req.get("variant", ""), device) if case == "pendulum"
                          else _build_tm(args.side, case, device, req.get("variant", "")))
        memory, agent, memory_name = built[key]
        res = _measure_agent(memory, agent, req["mode"], req["seconds"], slow=case == "tmfull", device=device)
        ring = getattr(memory, "device_ring", None)
        res["memory"] = memory_name + (f" (rings on {ring.device})" if ring is not None else "")
        return res

    def handle(req: dict[str, Any]) -> dict[str, Any]:
        case, algo = req.get("case", "pendulum"), req.get("algo", "sac")
        if "memory_bytes" in req:
            return _tm_memory_bytes(args.side, case, int(req["memory_bytes"]))
        if "floor" in req:
            shapes = req["floor"]
            return {"floor_ms": floor_ms(update_products(hidden=HIDDEN, batch=BATCH, **shapes), req["seconds"],
                                         device)}
        key = f"{case}:{algo}:{req.get('variant', '')}"
        if key not in failed:
            try:
                return measure(req, case, algo, key)
            except Exception as e:  # noqa: BLE001 (a side that fails on this device is a figure: "-", and why)
                failed[key] = " ".join(f"{type(e).__name__}: {e}".split())[:300]
                built.pop(key, None)
        return {"error": failed[key]}

    harness.serve(handle)


def _reuse_freed_memory() -> bool:
    """glibc's settings of :func:`tmrl.util.reuse_freed_memory`, set here so that every side's
    interpreter (tmrl 0.7.1's and SB3's too) gets them: keep freed blocks for reuse instead of
    page-faulting them in again at every update."""
    import ctypes
    import sys

    if not sys.platform.startswith("linux"):
        return False
    mallopt = ctypes.CDLL(None).mallopt
    mallopt.argtypes = [ctypes.c_int, ctypes.c_int]
    # M_MMAP_THRESHOLD, M_TRIM_THRESHOLD, M_TOP_PAD
    return all(mallopt(p, v) == 1 for p, v in ((-3, 256 << 20), (-1, 1 << 30), (-2, 64 << 20)))


# --- driver ---------------------------------------------------------------------------------------

CASES = ("pendulum", "tmfull", "tmlidar")


def _jobs(cases: list[str], algos: list[str], modes: list[str]) -> list[tuple[str, str, str]]:
    jobs = []
    for case in cases:
        for algo in algos if case == "pendulum" else ["sac"]:
            jobs += [(case, algo, mode) for mode in modes]
    return jobs


def _workers(args: argparse.Namespace, device: str = "cpu") -> dict[str, harness.ChildWorker]:
    common = (["--threads", str(args.threads)] if args.threads else []) + ["--device", device]
    workers = {}
    for side in harness.sides_from_args(args):
        code = "ours" if side.name == "before" else side.name  # an earlier commit of ours runs our code path
        workers[side.name] = harness.ChildWorker(side, "trainer_speed", "--side", code, *common)
        if side.name == "tmrl" and args.glibc_defaults_for_tmrl:
            label = "tmrl (glibc defaults)"
            workers[label] = harness.ChildWorker(side, "trainer_speed", "--side", "tmrl", "--glibc-defaults", *common)
    return workers


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(prog="python -m bench trainer_speed", description=__doc__.split("\n")[0])
    parser.add_argument("--rounds", type=int, default=5, help="rounds (sides alternate their order)")
    parser.add_argument("--seconds", type=float, default=4.0, help="per measurement")
    parser.add_argument("--threads", type=int, default=None, help="torch threads on every side (default: torch's)")
    parser.add_argument("--cases", default="pendulum", help=f"comma-separated among {', '.join(CASES)}")
    parser.add_argument("--algos", default="sac,redq", help="algorithms of the pendulum case")
    parser.add_argument("--modes", default="full,agent", help="full (sample + train) and/or agent (train only)")
    parser.add_argument("--bf16", action="store_true", help="also ours with critic_dtype='bfloat16' (pendulum)")
    parser.add_argument("--host-memory", action="store_true",
                        help="also ours with MEMORY_ON_DEVICE \"off\" (batches built on the host and copied over, "
                        "as before the rings moved to the GPU); full mode; on a CPU both are the host path")
    parser.add_argument("--glibc-defaults-for-tmrl", action="store_true",
                        help="also tmrl 0.7.1 on glibc's allocator defaults (a labelled, one-sided line)")
    parser.add_argument("--memory-bytes", type=int, default=0, metavar="N",
                        help="also the bytes per stored sample of each side's memory, over N samples (TM cases)")
    harness.add_side_arguments(parser, tmrl=True, sb3=True)
    harness.add_device_argument(parser, "cpu")
    args = parser.parse_args(argv)
    device = harness.resolve_device(parser, args.device)
    cases = [c for c in args.cases.split(",") if c]
    if set(cases) - set(CASES):
        parser.error(f"unknown case(s) {sorted(set(cases) - set(CASES))}: use {', '.join(CASES)}")
    jobs = _jobs(cases, args.algos.split(","), [m for m in args.modes.split(",") if m])
    settings = {"batch": BATCH, "hidden": [HIDDEN, HIDDEN], "samples_in_memory": N_SAMPLES,
                "threads": args.threads or "torch default", "allocator": "reuse_freed_memory on every side",
                "seconds": args.seconds, "rounds": args.rounds, "tm_alg": TM_ALG, **harness.device_settings(device)}
    rec = harness.Recorder("trainer_speed", settings)
    workers = _workers(args, device)
    try:
        if args.memory_bytes:
            for case in (c for c in cases if c != "pendulum"):
                for name, w in workers.items():
                    if name in ("ours", "tmrl"):
                        res = w.ask({"case": case, "memory_bytes": args.memory_bytes})
                        rec.add(f"{case} memory", "bytes_per_sample", name, res["bytes_per_sample"],
                                higher_is_better=False, unit="B", memory=res["memory"])
        _run_rounds(args, jobs, workers, rec)
    finally:
        for w in workers.values():
            w.close()
    rows = rec.print_table(ratios=[("ours", "tmrl"), ("ours", "sb3"), ("ours", "tmrl (glibc defaults)"),
                                   ("ours bf16", "tmrl"), ("ours", "before"), ("ours", "ours hostmem")])
    _print_floor_fractions(rows)
    rec.close()


def _run_rounds(args: argparse.Namespace, jobs: list[tuple[str, str, str]],
                workers: dict[str, harness.ChildWorker], rec: harness.Recorder) -> None:
    names = list(workers)
    for rnd in range(args.rounds):
        print(f"round {rnd + 1}/{args.rounds}: load average {harness.load_average():.2f}", flush=True)
        for case, algo, mode in jobs:
            figure = f"{case}/{algo}" if case == "pendulum" else case
            runs = [(n, "") for n in names if n != "sb3" or (case, algo, mode) == ("pendulum", "sac", "full")]
            if args.bf16 and case == "pendulum":
                runs.append(("ours", "bf16"))
            if args.host_memory and mode == "full":
                runs.append(("ours", "hostmem"))
            for name, variant in runs if rnd % 2 == 0 else runs[::-1]:
                res = workers[name].ask({"case": case, "algo": algo, "mode": mode, "seconds": args.seconds,
                                         "variant": variant})
                label = f"{name} {variant}".strip()
                if "error" in res:  # this side fails on this device: no figure, and why
                    rec.add(f"{figure} {mode}", "updates_per_s", label, None, round=rnd, unit="1/s",
                            error=res["error"])
                    print(f"    {label} failed: {res['error']}", flush=True)
                    continue
                rec.add(f"{figure} {mode}", "updates_per_s", label, res["updates_per_s"],
                        round=rnd, unit="1/s", cpu_ms_per_update=res["cpu_ms_per_update"],
                        sample_share=res["sample_share"], threads=res["threads"], memory=res.get("memory"))
            shapes = _floor_case(case, algo)
            if shapes is not None and mode == jobs[-1][2]:  # once per figure and round
                res = workers["ours"].ask({"floor": shapes, "seconds": min(args.seconds, 2.0)})
                rec.add(figure, "floor_ms", "floor", res["floor_ms"], round=rnd, unit="ms", higher_is_better=False)


def _print_floor_fractions(rows: list[dict[str, Any]]) -> None:
    """``floor / ours``: the floor's milliseconds over our update's, per figure and mode (medians)."""
    med = {(r["case"], r["metric"], r["side"]): r["median"] for r in rows}
    for (case, metric, _), floor in med.items():
        if metric != "floor_ms" or not floor:
            continue
        for mode in ("agent", "full"):
            ours = med.get((f"{case} {mode}", "updates_per_s", "ours"))
            if ours:
                print(f"{case} {mode}: floor / ours = {floor:.2f} ms / {1000 / ours:.2f} ms = "
                      f"{floor * ours / 1000:.2f} of the matrix-product floor")
