"""The environment-specific parts of ``python -m bench chaos`` (:mod:`bench.chaos`): the workers'
paced environment and actor, the trainer's training class, and the evaluation of a ``.tmod`` file.

- ``pendulum``: Pendulum-v1 with the MLP SAC of :data:`bench.chaos.PROFILES` (unchanged).
- ``sim``: the built-in simulator (:mod:`tmrl.sim`) with lidar observations (``SIMLIDAR``) on the
  ``oval`` track, the easiest (docs/simulator.md), through the pipeline of
  :func:`tmrl.sim.interfaces.pipeline_parts` (lidar preprocessor and compressor, ``LidarMemory``,
  ``LidarActorCritic``), with the demo's fast-mode settings (:data:`tmrl.sim.demo.DEMO_SETTINGS`:
  SAC, learning rates 1e-3, entropy coefficient learned from 0.2, at most one update per sample).
  Workers step at 20 steps/s, the simulator's real-time rate (``time_step_duration`` 0.05 s), and
  send every 40 steps: three of them give the trainer 60 samples/s, about what it updates on with
  one core of the 2-core machine.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

ENVS = ("pendulum", "sim")

THRESHOLDS: dict[str, float | None] = {"pendulum": -200.0, "sim": None}
"""The test return the learning figure waits for (:meth:`bench.chaos.Chaos.learning`): Pendulum's
-200; None for the simulator, whose figure is how far the test return rose while the faults ran."""

SIM_PROFILES: dict[str, dict[str, Any]] = {
    # a CI-sized run: small networks, payloads of 25 steps, frequent checkpoints
    "test": {"track": "oval", "hidden_sizes": [32, 32], "batch_size": 64, "memory_size": 20_000, "rounds": 1,
             "steps": 100, "start_training": 100, "rate": 100.0, "chunk": 25},
    # the benchmark: the demo's networks and batch; a checkpoint every 200 updates (a few seconds); half the
    # demo's memory (28 minutes of 3 workers), so that a checkpoint's segments stay well inside disk_full's 64 MiB
    "bench": {"track": "oval", "hidden_sizes": [256, 256], "batch_size": 256, "memory_size": 100_000, "rounds": 1,
              "steps": 200, "start_training": 1000, "rate": 20.0, "chunk": 40},
}
"""The ``sim`` settings per :class:`bench.chaos.ChaosConfig` profile; :func:`profile` adds the
demo's (learning rates, entropy coefficient, intervals, history and action buffer lengths)."""


def check(env: str) -> str:
    """``env``, or ValueError when it is not one of :data:`ENVS`."""
    if env not in ENVS:
        raise ValueError(f"unknown chaos environment {env!r}: use one of {', '.join(ENVS)}")
    return env


def profile(env: str, name: str, base: dict[str, Any]) -> dict[str, Any]:
    """The roles' settings for ``env`` under profile ``name`` (``"test"`` or ``"bench"``):
    ``base`` (the Pendulum profile of :data:`bench.chaos.PROFILES`) itself for ``pendulum``; for
    ``sim``, :data:`SIM_PROFILES` with the demo's training settings. Written into the roles'
    config files, so that every role (and the run's record) sees the same numbers."""
    if check(env) == "pendulum":
        return base
    from tmrl.sim.demo import DEMO_SETTINGS as S
    from tmrl.sim.interfaces import DEFAULT_SIM_RTGYM_CONFIG

    return dict(
        interface="SIMLIDAR", img_hist_len=S["img_hist_len"], act_buf_len=S["act_buf_len"],
        ep_max_length=S["ep_max_length"], time_step_duration=DEFAULT_SIM_RTGYM_CONFIG["time_step_duration"],
        lr=S["lr"], gamma=S["gamma"], polyak=S["polyak"], alpha=S["alpha"], learn_entropy_coef=S["learn_entropy_coef"],
        update_model_interval=S["update_model_interval"], update_buffer_interval=S["update_buffer_interval"],
        max_training_steps_per_env_step=S["max_training_steps_per_env_step"], poll_wait=0.01,
        episode=S["ep_max_length"], **SIM_PROFILES[name],
    )


def paced(env: Any, rate: float) -> Any:
    """``env`` stepped at most ``rate`` times a second (a real-time game: it never waits for the
    trainer). Behind by more than a second (a frozen process), it starts again from now instead
    of catching up."""
    import gymnasium

    class Paced(gymnasium.Wrapper):
        period = 1.0 / rate
        next_step: float | None = None

        def step(self, action: Any) -> Any:
            now = time.monotonic()
            if self.next_step is None or now - self.next_step > 1.0:
                self.next_step = now
            elif self.next_step > now:
                time.sleep(self.next_step - now)
            self.next_step += self.period
            return self.env.step(action)

    return Paced(env)


# ================================================================================================
# the worker


def worker_parts(env: str, p: dict[str, Any]) -> dict[str, Any]:
    """Keyword arguments of the worker's :class:`tmrl.networking.RolloutWorker` for ``env``:
    ``env_cls`` (paced at ``p["rate"]`` steps/s), ``actor_module_cls``, ``obs_preprocessor``,
    ``sample_compressor``."""
    from tmrl.util import partial

    if check(env) == "pendulum":
        from tmrl.envs import GenericGymEnv
        from tmrl.models import SquashedGaussianMLPActor

        return {
            "env_cls": lambda: paced(GenericGymEnv(id="Pendulum-v1", gym_kwargs={"render_mode": None}), p["rate"]),
            "actor_module_cls": partial(SquashedGaussianMLPActor, hidden_sizes=tuple(p["hidden_sizes"])),
            "obs_preprocessor": None, "sample_compressor": None,
        }
    parts = _sim_pipeline(p)
    return {"env_cls": lambda: paced(sim_env(p), p["rate"]),
            "actor_module_cls": partial(parts["actor_cls"], hidden_sizes=tuple(p["hidden_sizes"])),
            "obs_preprocessor": parts["obs_preprocessor"], "sample_compressor": parts["sample_compressor"]}


def collector(env: str, p: dict[str, Any]) -> Callable[[Any], None]:
    """What the worker collects into its buffer before each send: for ``pendulum`` one training
    episode of ``p["episode"]`` steps; for ``sim`` the next ``p["chunk"]`` steps of the current
    episode (:class:`Chunks`: a lap takes 400 or more steps, 20 s and more at the real-time rate,
    too long between two sends for the recovery times to mean anything)."""
    if check(env) == "pendulum":
        return lambda worker: worker.collect_train_episode(p["episode"])
    return Chunks(p["chunk"])


class Chunks:
    """Collects the next ``chunk`` steps of a worker's current training episode at each call
    (fewer when the episode ends; the next call starts a new one), so that a worker sends its
    samples every ``chunk`` steps whatever the episodes' length. The replay memory links the
    chunks of an episode by the worker's source id (:mod:`tmrl.memory.episodes`)."""

    def __init__(self, chunk: int) -> None:
        self.chunk = int(chunk)
        self.obs: Any = None
        self.ret = 0.0
        self.steps = 0
        self.episodes = 0

    def __call__(self, worker: Any) -> None:
        """Step ``worker`` (a :class:`tmrl.networking.RolloutWorker`) into its buffer."""
        if self.obs is None:
            self.obs, _ = worker.reset(collect_samples=True)
            self.ret, self.steps = 0.0, 0
        for _ in range(self.chunk):
            # the environment truncates its episodes itself (ep_max_length)
            self.obs, rew, terminated, truncated, _ = worker.step(self.obs, test=False, collect_samples=True)
            self.ret += float(rew)
            self.steps += 1
            if terminated or truncated:
                worker.buffer.stat_train_return = self.ret
                worker.buffer.stat_train_steps = self.steps
                self.obs = None
                self.episodes += 1
                return


# ================================================================================================
# the trainer


def training_cls(env: str, p: dict[str, Any]) -> Any:
    """The trainer's ``training_cls`` (a :class:`tmrl.training_offline.TorchTrainingOffline`
    partial) for ``env``, on the CPU, for as many epochs as it runs (a checkpoint after each)."""
    from tmrl.algorithms.sac import SACAgent
    from tmrl.training_offline import TorchTrainingOffline
    from tmrl.util import partial

    common: dict[str, Any] = {
        "epochs": 10**9, "rounds": p["rounds"], "steps": p["steps"],
        "update_buffer_interval": p["update_buffer_interval"], "update_model_interval": p["update_model_interval"],
        "max_training_steps_per_env_step": p["max_training_steps_per_env_step"],
        "start_training": p["start_training"], "sleep_between_buffer_retrieval_attempts": p["poll_wait"],
        "device": "cpu",
    }
    if check(env) == "pendulum":
        import gymnasium

        from tmrl.memory import GenericTorchMemory
        from tmrl.models import MLPActorCritic

        spaces = gymnasium.make("Pendulum-v1")
        return partial(
            TorchTrainingOffline,
            env_cls=(spaces.observation_space, spaces.action_space),
            memory_cls=partial(GenericTorchMemory, memory_size=p["memory_size"], batch_size=p["batch_size"]),
            training_agent_cls=partial(
                SACAgent, model_cls=partial(MLPActorCritic, hidden_sizes=tuple(p["hidden_sizes"])),
                lr_actor=p["lr"], lr_critic=p["lr"], lr_entropy=p["lr"], learn_entropy_coef=True,
            ),
            **common,
        )
    parts = _sim_pipeline(p)
    spaces = sim_env(p)  # only its spaces are used
    return partial(
        TorchTrainingOffline,
        env_cls=(spaces.observation_space, spaces.action_space),
        memory_cls=partial(parts["memory_cls"], hist_len=p["img_hist_len"], act_buf_len=p["act_buf_len"],
                           memory_size=p["memory_size"], batch_size=p["batch_size"]),
        training_agent_cls=partial(
            SACAgent, model_cls=partial(parts["model_cls"], hidden_sizes=tuple(p["hidden_sizes"])),
            gamma=p["gamma"], polyak=p["polyak"], alpha=p["alpha"], lr_actor=p["lr"], lr_critic=p["lr"],
            lr_entropy=p["lr"], learn_entropy_coef=p["learn_entropy_coef"], target_entropy=None,
        ),
        **common,
    )


def trainer_parts(env: str, p: dict[str, Any]) -> dict[str, Any]:
    """The trainer's ``obs_preprocessor`` and ``sample_compressor`` (the workers'), from which it
    derives the schema every sample batch is checked against."""
    if check(env) == "pendulum":
        return {"obs_preprocessor": None, "sample_compressor": None}
    parts = _sim_pipeline(p)
    return {"obs_preprocessor": parts["obs_preprocessor"], "sample_compressor": parts["sample_compressor"]}


# ================================================================================================
# the evaluation


class Evaluation:
    """Mean test return of deterministic episodes of the actor in a ``.tmod`` file (the
    trainer's weights), on an environment that is not paced.

    Attributes:
        extra: figures of the last evaluation besides its return (``sim``: ``lap_time``, the
            lap's simulated seconds or None, and ``progress``, the share of the lap driven).
    """

    def __init__(self, env: str, p: dict[str, Any]) -> None:
        self.name = check(env)
        self.extra: dict[str, Any] = {}
        if env == "pendulum":
            import gymnasium

            from tmrl.models import SquashedGaussianMLPActor

            self.env = gymnasium.make("Pendulum-v1")
            self.actor = SquashedGaussianMLPActor(self.env.observation_space, self.env.action_space,
                                                  hidden_sizes=tuple(p["hidden_sizes"]))
            self.preprocess: Callable[[Any], Any] | None = None
        else:
            parts = _sim_pipeline(p)
            self.env = sim_env(p)
            self.actor = parts["actor_cls"](self.env.observation_space, self.env.action_space,
                                            hidden_sizes=tuple(p["hidden_sizes"]))
            self.preprocess = parts["obs_preprocessor"]

    def load(self, path: str | Path) -> None:
        """Load the actor's weights from ``path`` (raises what the actor's ``load`` raises)."""
        self.actor = self.actor.load(str(path), device="cpu")

    def test_return(self, episodes: int) -> float:
        """Mean return of ``episodes`` deterministic episodes. Pendulum's start from fixed seeds;
        the simulator's are all the same episode (the car starts at rest on the start line, the
        physics is deterministic, the seed is ignored), so one is driven for all."""
        import numpy as np
        import torch

        if self.name == "sim":
            episodes = min(episodes, 1)
        returns = []
        for i in range(episodes):
            obs, _ = self.env.reset(seed=10_000 + i)
            ret, done, info = 0.0, False, {}
            while not done:
                if self.preprocess is not None:
                    obs = self.preprocess(obs)
                with torch.no_grad():
                    act = self.actor.act_(obs if self.preprocess is not None else np.asarray(obs, np.float32),
                                          test=True)
                obs, rew, terminated, truncated, info = self.env.step(
                    np.asarray(act, np.float32).reshape(self.env.action_space.shape))
                ret += float(rew)
                done = terminated or truncated
            returns.append(ret)
            if self.name == "sim":
                self.extra = {"lap_time": info.get("lap_time") if info.get("lap_completed") else None,
                              "progress": float(self.env.race.progress)}
        return float(np.mean(returns))


# ================================================================================================
# the simulator


def sim_env(p: dict[str, Any]) -> Any:
    """The simulator in fast mode (one ``time_step_duration`` of simulated time per step; the
    workers pace it with :func:`paced`), with the demo's observations on ``p["track"]``."""
    from tmrl.sim.interfaces import SimEnv

    return SimEnv(p["interface"], time_step_duration=p["time_step_duration"], ep_max_length=p["ep_max_length"],
                  act_buf_len=p["act_buf_len"], track=p["track"], img_hist_len=p["img_hist_len"])


def _sim_pipeline(p: dict[str, Any]) -> dict[str, Any]:
    from tmrl.sim.interfaces import pipeline_parts

    return pipeline_parts(p["interface"])
