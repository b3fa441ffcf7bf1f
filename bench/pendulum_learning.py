"""Learning check: SAC in a plain synchronous loop (one environment step, one update) on
Pendulum-v1 or on the built-in simulator, with the two update orders side by side, and the other
agents beside it in environment steps.

    python -m bench pendulum_learning                        # Pendulum, both orders, 5 seeds each
    python -m bench pendulum_learning --env simlidar --steps 20000
    python -m bench pendulum_learning --orders simultaneous --agents SAC,REDQSAC,DROQ,TQC --updates-per-step 1
    python -m bench pendulum_learning --device cuda          # memory, agent and the workers' actors on the GPU

``simultaneous`` (our default: the actor loss reads the critics before their step, one backward
pass) against ``sequential`` (the original tmrl SAC: after it), ``ALG.UPDATE_ORDER``. Each run is
a fresh process; seeds alternate the order of the two. Printed per order: medians and spread of
the environment steps until the mean test return exceeds the threshold (Pendulum: -200), the best
and last test returns, the updates per second inside ``train()`` and the wall time. ``--agents``
adds REDQ-SAC, DroQ and TQC (on Pendulum, with their MLP models) with their own class default
settings, labelled by name; ``--updates-per-step`` (the update-to-data ratio) applies to all.

The loop: ``--start-steps`` uniformly random actions, then the policy; samples go through a
standalone :class:`tmrl.networking.RolloutWorker` (the simulator's preprocessor and compressor
included) into the trainer's replay memory every ``--append-every`` steps; one update per step
once the memory holds a batch; ``--eval-episodes`` deterministic test episodes every
``--eval-every`` steps. ``--device`` (default ``cpu``, the published figures'; ``cuda``,
``cuda:N`` or ``auto``) puts the memory's batches, the agent and the actors the loop acts with
on that device; the first printed line and the record's settings name it.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from typing import Any

from bench import harness

ORDERS = ("simultaneous", "sequential")
ENVS = ("pendulum", "simlidar")
THRESHOLDS = {"pendulum": -200.0, "simlidar": None}


# --- one run (child process) ----------------------------------------------------------------------


class _UniformActor:
    """Uniformly random actions (the first ``--start-steps``)."""

    def __init__(self, action_space: Any) -> None:
        self.action_space = action_space

    def act_(self, obs: Any, test: bool = False) -> Any:
        return self.action_space.sample()


def _parts(env_name: str, batch_size: int, memory_size: int, track: str = "classic",
           device: str = "cpu") -> dict[str, Any]:
    """Environment factory, memory (its batches collated on ``device``), agent class and worker
    extras of ``env_name`` (``"simlidar"``: on ``track``)."""
    from tmrl.memory import GenericTorchMemory
    from tmrl.models import MLPActorCritic, SquashedGaussianMLPActor
    from tmrl.util import partial

    if env_name == "pendulum":
        from tmrl.envs import GenericGymEnv

        return {"env_cls": partial(GenericGymEnv, id="Pendulum-v1"), "model_cls": MLPActorCritic,
                "actor_cls": SquashedGaussianMLPActor,
                "memory": GenericTorchMemory(device=device, nb_steps=1, memory_size=memory_size, batch_size=batch_size),
                "worker": {}, "max_samples": 200}
    from tmrl.sim.demo import DEMO_SETTINGS, _demo_config
    from tmrl.sim.interfaces import fast_env, pipeline_parts

    parts = pipeline_parts("SIMLIDAR")
    cfg = _demo_config("SIMLIDAR", track)
    memory = parts["memory_cls"](hist_len=DEMO_SETTINGS["img_hist_len"], act_buf_len=DEMO_SETTINGS["act_buf_len"],
                                 device=device, nb_steps=1, memory_size=memory_size, batch_size=batch_size)
    return {"env_cls": partial(fast_env, cfg), "model_cls": parts["model_cls"], "actor_cls": parts["actor_cls"],
            "memory": memory,
            "worker": {"obs_preprocessor": parts["obs_preprocessor"], "sample_compressor": parts["sample_compressor"]},
            "max_samples": DEMO_SETTINGS["ep_max_length"]}


AGENTS = ("SAC", "REDQSAC", "DROQ", "TQC")


def _agent(name: str, order: str, env_name: str, spaces: tuple[Any, Any], model_cls: Any,
           device: str = "cpu") -> Any:
    """The agent ``name`` (an ``ALG.ALGORITHM`` value) on ``device`` with its class defaults (and
    its own MLP model, the class default, except SAC, which trains the environment's model)."""
    from tmrl.algorithms import agent_class

    if name == "SAC":
        return agent_class(name)(*spaces, device, model_cls=model_cls, update_order=order)
    if env_name != "pendulum":
        raise SystemExit(f"{name} is measured on Pendulum only (its MLP models do not read the simulator's lidar)")
    return agent_class(name)(*spaces, device)


def _feed_and_train(worker: Any, memory: Any, agent: Any, append_every: int, n_updates: int,
                    batch_size: int) -> tuple[int, float]:
    """One step's bookkeeping of a synchronous learning loop: the worker's buffer goes into the
    memory once it holds ``append_every`` samples, then ``n_updates`` updates once the memory holds
    a batch. Returns (updates done, seconds spent in them)."""
    from tmrl.networking import Buffer

    if len(worker.buffer) >= append_every:
        memory.append(worker.buffer)
        worker.buffer = Buffer()
    if n_updates <= 0 or len(memory) < batch_size:
        return 0, 0.0
    t0 = time.perf_counter()
    for _ in range(n_updates):
        agent.train(memory.sample())
    return n_updates, time.perf_counter() - t0


def run(env_name: str, order: str, seed: int, steps: int, start_steps: int, eval_every: int, eval_episodes: int,
        batch_size: int, append_every: int, threads: int, agent_name: str = "SAC",
        updates_per_step: int = 1, device: str = "cpu") -> dict[str, Any]:
    """One learning run on ``device``; returns its test curve and timings."""
    import numpy as np
    import torch

    from tmrl.networking import RolloutWorker

    torch.set_num_threads(threads)
    torch.manual_seed(seed)
    np.random.seed(seed)
    p = _parts(env_name, batch_size, 100_000, device=device)
    memory = p["memory"]
    # The workers' own actors are replaced below (uniform, then the trained one).
    worker_kwargs = dict(env_cls=p["env_cls"], actor_module_cls=p["actor_cls"], standalone=True, model_history=0,
                         max_samples_per_episode=p["max_samples"], model_path=os.devnull + "_none", **p["worker"])
    worker, tester = RolloutWorker(**worker_kwargs), RolloutWorker(**worker_kwargs)
    agent = _agent(agent_name, order, env_name, (worker.env.observation_space, worker.env.action_space),
                   p["model_cls"], device)
    worker.env.action_space.seed(seed)
    worker.actor, tester.actor = _UniformActor(worker.env.action_space), agent.get_actor()
    curve, updates, t_update = [], 0, 0.0
    start = time.perf_counter()
    obs, _ = worker.reset(collect_samples=True)
    episode_step = 0
    for step in range(1, steps + 1):
        if step == start_steps + 1:
            worker.actor = agent.get_actor()
        episode_step += 1
        obs, _, terminated, truncated, _ = worker.step(obs, test=False, collect_samples=True,
                                                       last_step=episode_step == p["max_samples"])
        if terminated or truncated:
            obs, _ = worker.reset(collect_samples=True)
            episode_step = 0
        done, seconds = _feed_and_train(worker, memory, agent, append_every,
                                        updates_per_step if step > start_steps else 0, batch_size)
        updates, t_update = updates + done, t_update + seconds
        if step % eval_every == 0:
            ret = float(np.mean([tester.run_episode() for _ in range(eval_episodes)]))
            curve.append((step, ret))
            print(f"    [{env_name} {agent_name} {order} seed {seed}] step {step:6d} test return {ret:8.1f} "
                  f"({time.perf_counter() - start:.0f} s)", file=sys.stderr, flush=True)
    return {"curve": curve, "wall_s": time.perf_counter() - start, "updates": updates,
            "updates_per_s": updates / max(t_update, 1e-9)}


def child_main(argv: list[str]) -> None:
    """``--run JSON``: one run with those keyword arguments; prints its result as JSON."""
    ap = argparse.ArgumentParser()
    ap.add_argument("--run", required=True)
    harness.print_json(run(**json.loads(ap.parse_args(argv).run)))


# --- driver ---------------------------------------------------------------------------------------


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(prog="python -m bench pendulum_learning", description=__doc__.split("\n\n")[0])
    ap.add_argument("--env", choices=ENVS, default="pendulum")
    ap.add_argument("--orders", default=",".join(ORDERS), help="comma-separated among " + ", ".join(ORDERS))
    ap.add_argument("--seeds", type=int, default=5, help="runs per order")
    ap.add_argument("--steps", type=int, default=15_000)
    ap.add_argument("--start-steps", type=int, default=1_000, help="uniformly random actions first")
    ap.add_argument("--eval-every", type=int, default=1_000)
    ap.add_argument("--eval-episodes", type=int, default=5)
    ap.add_argument("--batch-size", type=int, default=256)
    ap.add_argument("--append-every", type=int, default=10, help="env steps between memory appends")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--threshold", type=float, default=None, help="test return to reach (Pendulum: -200)")
    ap.add_argument("--agents", default="SAC", help="comma-separated ALG.ALGORITHM values: SAC (in each --orders), "
                    "REDQSAC, DROQ, TQC (their own class defaults; Pendulum only)")
    ap.add_argument("--updates-per-step", type=int, default=1, help="updates per environment step, every agent")
    harness.add_device_argument(ap, "cpu")
    args = ap.parse_args(argv)
    device = harness.resolve_device(ap, args.device)
    orders = [o for o in args.orders.split(",") if o]
    if set(orders) - set(ORDERS):
        ap.error(f"unknown order(s) {sorted(set(orders) - set(ORDERS))}: use {', '.join(ORDERS)}")
    agents = [a.strip().upper() for a in args.agents.split(",") if a.strip()]
    if set(agents) - set(AGENTS):
        ap.error(f"unknown agent(s) {sorted(set(agents) - set(AGENTS))}: use {', '.join(AGENTS)}")
    if args.updates_per_step < 1:
        ap.error("--updates-per-step must be at least 1")
    # a variant is (label, agent, order): SAC once per order (labelled by the order), the others once
    variants = {o: ("SAC", o) for o in orders} if "SAC" in agents else {}
    variants.update({a: (a, "simultaneous") for a in agents if a != "SAC"})
    threshold = args.threshold if args.threshold is not None else THRESHOLDS[args.env]
    settings = {k: v for k, v in vars(args).items() if k not in ("orders", "seeds")}
    settings.update(harness.device_settings(device))
    settings.update(threshold=threshold, algorithm="each agent's class defaults (SAC: MLP 256x256, lr 1e-3, "
                    "gamma 0.99, alpha 0.2 learned)")
    rec = harness.Recorder("pendulum_learning", settings)
    side = harness.ours_side()
    for seed, label in harness.alternate(list(variants), args.seeds):
        agent_name, order = variants[label]
        kwargs = dict(env_name=args.env, order=order, seed=seed, steps=args.steps, start_steps=args.start_steps,
                      eval_every=args.eval_every, eval_episodes=args.eval_episodes, batch_size=args.batch_size,
                      append_every=args.append_every, threads=args.threads, agent_name=agent_name,
                      updates_per_step=args.updates_per_step, device=device)
        # A fresh process per run; its progress lines go to stderr, its result to stdout.
        out = subprocess.run(side.command("pendulum_learning", "--run", json.dumps(kwargs)), env=side.env,
                             cwd=side.cwd, stdout=subprocess.PIPE, text=True, check=False)
        if out.returncode != 0:
            raise SystemExit(f"the {label} run of seed {seed} failed (exit code {out.returncode})")
        res = json.loads(out.stdout.strip().splitlines()[-1])
        case = args.env
        returns = [r for _, r in res["curve"]]
        reached = next((s for s, r in res["curve"] if threshold is not None and r > threshold), None)
        if threshold is not None:
            rec.add(case, f"steps_to_{threshold:g}", label, reached, round=seed, higher_is_better=False,
                    unit="steps", curve=res["curve"])
        rec.add(case, "best_test_return", label, max(returns), round=seed)
        rec.add(case, "last_test_return", label, returns[-1], round=seed)
        rec.add(case, "updates_per_s_in_train", label, res["updates_per_s"], round=seed, unit="1/s")
        rec.add(case, "wall_s", label, res["wall_s"], round=seed, higher_is_better=False, unit="s")
    pairs = [("simultaneous", "sequential")] if {"simultaneous", "sequential"} <= set(variants) else []
    rec.print_table(ratios=pairs + [(a, "simultaneous") for a in variants if a not in ORDERS and "simultaneous" in variants])
    rec.close()
