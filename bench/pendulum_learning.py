"""Learning speed: SAC on Pendulum-v1, a plain synchronous loop (one environment step, one update).

Prints the test curve (mean return of deterministic test episodes every ``--eval-every`` steps)
and the wall time; the goal is a mean test return above -200 within 15k environment steps.
Samples go through ``tmrl.memory.GenericTorchMemory`` (the trainer's memory) when it is
available, else through a small local ring buffer.

Usage::

    /work/venv/bin/python bench/pendulum_learning.py [--steps 15000] [--seed 0] [--threads 1]
"""

from __future__ import annotations

import argparse
import os
import time
from typing import Any

import gymnasium
import numpy as np
import torch

from tmrl.algorithms import SACAgent
from tmrl.models import MLPActorCritic
from tmrl.util import partial


class _RingBuffer:
    """Fallback replay memory with the same ``append`` / ``sample`` surface as tmrl's."""

    def __init__(self, size: int, batch_size: int, obs_dim: int, act_dim: int) -> None:
        self.o = np.zeros((size, obs_dim), np.float32)
        self.a = np.zeros((size, act_dim), np.float32)
        self.r = np.zeros(size, np.float32)
        self.o2 = np.zeros((size, obs_dim), np.float32)
        self.d = np.zeros(size, np.float32)
        self.n = 0
        self.i = 0
        self.size = size
        self.batch_size = batch_size
        self.rng = np.random.default_rng(0)
        self.last_obs: np.ndarray | None = None

    def append(self, buffer: Any) -> None:
        for act, obs, rew, terminated, truncated, _ in buffer.memory:
            if act is not None and self.last_obs is not None:
                j = self.i
                self.o[j], self.a[j], self.r[j], self.o2[j], self.d[j] = (
                    self.last_obs,
                    act,
                    rew,
                    obs[0],
                    terminated,
                )
                self.i = (self.i + 1) % self.size
                self.n = min(self.n + 1, self.size)
            self.last_obs = None if (terminated or truncated) else obs[0]

    def __len__(self) -> int:
        return self.n

    def sample(self) -> tuple:
        idx = self.rng.integers(0, self.n, self.batch_size)
        t = torch.from_numpy
        return (
            (t(self.o[idx]),),
            t(self.a[idx]),
            t(self.r[idx]),
            (t(self.o2[idx]),),
            t(self.d[idx]),
            torch.zeros(len(idx)),
        )


class _Samples:
    def __init__(self) -> None:
        self.memory: list = []
        self.sources = None
        self.stat_train_return = 0.0
        self.stat_test_return = 0.0
        self.stat_train_steps = 0
        self.stat_test_steps = 0

    def __len__(self) -> int:
        return len(self.memory)


def _memory(batch_size: int, env: gymnasium.Env) -> tuple[Any, str]:
    try:
        from tmrl.memory import GenericTorchMemory
    except ImportError:
        dims = int(np.prod(env.observation_space.shape)), int(np.prod(env.action_space.shape))
        return _RingBuffer(100_000, batch_size, *dims), "local ring buffer"
    return GenericTorchMemory(
        device="cpu", nb_steps=1, memory_size=100_000, batch_size=batch_size
    ), "tmrl.memory.GenericTorchMemory"


def evaluate(actor: Any, episodes: int, seed: int) -> float:
    env = gymnasium.make("Pendulum-v1")
    returns = []
    for k in range(episodes):
        obs, _ = env.reset(seed=seed + k)
        total, done = 0.0, False
        while not done:
            obs, rew, terminated, truncated, _ = env.step(actor.act_((obs,), test=True))
            total += float(rew)
            done = terminated or truncated
        returns.append(total)
    env.close()
    return float(np.mean(returns))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--steps", type=int, default=15_000)
    parser.add_argument("--start-steps", type=int, default=1_000, help="uniform random actions first")
    parser.add_argument("--eval-every", type=int, default=1_000)
    parser.add_argument("--eval-episodes", type=int, default=10)
    parser.add_argument("--batch-size", type=int, default=256)
    parser.add_argument("--append-every", type=int, default=10, help="env steps between memory appends")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--critic-dtype", default=None, help="None (float32) or bfloat16")
    args = parser.parse_args()

    torch.set_num_threads(args.threads)
    torch.manual_seed(args.seed)
    env = gymnasium.make("Pendulum-v1")
    obs_space = gymnasium.spaces.Tuple((env.observation_space,))
    # The original's defaults: lr 1e-3, gamma 0.99, polyak 0.995, alpha 0.2 learned.
    model = partial(MLPActorCritic, critic_dtype=args.critic_dtype)
    agent = SACAgent(obs_space, env.action_space, "cpu", model_cls=model)
    actor = agent.get_actor()
    memory, memory_name = _memory(args.batch_size, env)
    print(
        f"SAC on Pendulum-v1, {memory_name}, batch {args.batch_size}, MLP 256x256, "
        f"critics in {args.critic_dtype or 'float32'}, "
        f"{torch.get_num_threads()} torch thread(s), load average {os.getloadavg()[0]:.2f}"
    )

    rng = np.random.default_rng(args.seed)
    env.action_space.seed(args.seed)
    pending = _Samples()
    obs, _ = env.reset(seed=args.seed)
    pending.memory.append((None, (obs,), 0.0, False, False, {}))
    curve: list[tuple[int, float]] = []
    updates = 0
    t_update = 0.0
    start = time.perf_counter()
    for step in range(1, args.steps + 1):
        if step <= args.start_steps:
            act = env.action_space.sample()
        else:
            act = actor.act_((obs,), test=False)
        obs, rew, terminated, truncated, _ = env.step(act)
        pending.memory.append(
            (np.asarray(act, np.float32), (obs,), float(rew), bool(terminated), bool(truncated), {})
        )
        if terminated or truncated:
            obs, _ = env.reset(seed=int(rng.integers(1 << 30)))
            pending.memory.append((None, (obs,), 0.0, False, False, {}))
        if len(pending.memory) >= args.append_every:
            memory.append(pending)
            pending = _Samples()
        if step > args.start_steps and len(memory) >= args.batch_size:
            t0 = time.perf_counter()
            agent.train(memory.sample())
            t_update += time.perf_counter() - t0
            updates += 1
        if step % args.eval_every == 0:
            ret = evaluate(actor, args.eval_episodes, seed=10_000 + step)
            curve.append((step, ret))
            print(
                f"  step {step:6d}  test return {ret:8.1f}  updates {updates:6d}  "
                f"wall {time.perf_counter() - start:6.1f} s",
                flush=True,
            )
    wall = time.perf_counter() - start
    first = next((s for s, r in curve if r > -200), None)
    print(
        f"wall time {wall:.1f} s ({updates} updates, {updates / max(t_update, 1e-9):.0f} updates/s in train(); "
        f"load average {os.getloadavg()[0]:.2f})"
    )
    print(f"first test return above -200 at step {first}" if first else "never above -200")
    print(f"best test return {max(r for _, r in curve):.1f}, final {curve[-1][1]:.1f}")


if __name__ == "__main__":
    main()
