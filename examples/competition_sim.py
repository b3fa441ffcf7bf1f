"""A competition-style entry on the built-in simulator: your own actor module, trained by tmrl's SAC,
with everything else taken from the pipeline that ``python -m tmrl --trainer`` / ``--worker`` build.

In a TrackMania competition everybody shares the environment, the replay memory, the networking
and ``config.json``; an entry is a policy (an actor module the workers run) and, optionally, the
way it is trained. This file is such an entry for the simulator's lidar interfaces:

- ``LidarFeatures`` reads the lidar history with a 1-D convolution over the 19 beams (the history
  is the channels) instead of tmrl's flat MLP input;
- ``ConvLidarActor`` is the policy the workers run: a squashed Gaussian, so that SAC trains it;
- ``ConvLidarActorCritic`` holds it and two critics: what ``SACAgent(model_cls=...)`` trains.

The environment class, the observation preprocessor, the sample compressor, the replay memory,
SAC's settings and the training loop's settings are the configuration's objects
(``tmrl.config.config_objects``), exactly as the command line builds them. Why SAC rather than
the TD3 agent of examples/custom_agent.py: SAC is what the configuration's ``ALG`` section sets
up (its learning rates, entropy coefficient...), so the entry changes the model and nothing
else, and a stochastic policy explores by itself on the track.

The configuration is the data folder's ``config.json`` (``$TMRL_DATA``, default ``~/TmrlData``),
which must be a lidar simulator one (``python -m tmrl --install --env simlidar``); when there is
none, this script creates it so. It overrides two keys, for every role it starts: ``RUN_NAME``
(``competition_sim``: weights, checkpoint and metrics files of their own) and, with ``--port``,
``PORT``.

    python examples/competition_sim.py                   # the three roles in this process, 5 minutes
    python examples/competition_sim.py --minutes 10 --port 7000
    python examples/competition_sim.py --server          # or in three terminals (or machines)
    python examples/competition_sim.py --trainer --minutes 10
    python examples/competition_sim.py --worker

The trainer prints one line per round (environment steps, updates, the latest training return);
the worker counts laps. The trainer resumes from its checkpoint (``checkpoints/competition_sim_t.tcpt``)
when there is one, as ``--trainer`` does; delete it to start again.
"""

from __future__ import annotations

import argparse
import logging
import math
import sys
import threading
import time
from typing import Any

import gymnasium
import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from tmrl.actor import TorchActorModule
from tmrl.driving.models import lidar_obs_scales
from tmrl.models import mlp, space_dim
from tmrl.training_offline import TrainingCallback

RUN_NAME = "competition_sim"
LIDAR_INTERFACES = ("SIMLIDAR", "SIMLIDARPROGRESS", "TM20LIDAR", "TM20LIDARPROGRESS")
BEAMS = 19  # TrackMania's lidar, and the simulator's copy of it, has 19 beams

# --8<-- [start:model]
# --- the entry: an actor module of our own and the actor-critic that holds it ---------------------


class LidarFeatures(nn.Module):
    """One lidar observation as features: the lidar history through a 1-D convolution over the
    beams, then the other elements (speed, progress, the action buffer) as they are.

    Observations keep the environment's units: speed in km/h and lidar distances in pixels (up to
    about 400) are multiplied by tmrl's ``lidar_obs_scales`` (0.01) to be of order one.

    Args:
        observation_space: the environment's observation space (a Tuple: speed first, the lidar
            history, flat or not, then the rest).
        channels: output channels of the convolution.
        kernel: its width, in beams (odd: the padding keeps the 19 beams).
    """

    def __init__(self, observation_space: Any, channels: int = 8, kernel: int = 5) -> None:
        super().__init__()
        dims = [space_dim(s) for s in observation_space.spaces]
        self.scales = lidar_obs_scales(observation_space)
        self.lidar = next(i for i, d in enumerate(dims) if i > 0 and d >= BEAMS and d % BEAMS == 0)
        self.hist = dims[self.lidar] // BEAMS
        self.conv = nn.Sequential(nn.Conv1d(self.hist, channels, kernel, padding=kernel // 2), nn.ReLU(),
                                  nn.Flatten())
        self.out_dim = channels * BEAMS + sum(dims) - dims[self.lidar]

    def forward(self, obs: Any) -> torch.Tensor:
        b = obs[0].shape[0]
        parts = [o.reshape(b, -1).float() * s for o, s in zip(obs, self.scales)]
        lidar = parts.pop(self.lidar).reshape(b, self.hist, BEAMS)  # (batch, history, beams)
        return torch.cat([self.conv(lidar), *parts], dim=-1)


class ConvLidarActor(TorchActorModule):
    """The policy the workers run: a squashed Gaussian on top of ``LidarFeatures``.

    ``forward`` is what SAC calls (a batch, ``(action, log-density)``); ``act`` is what a worker
    calls through ``act_`` (a batch of one, no gradient), and returns a NumPy action. ``save`` and
    ``load`` are TorchActorModule's: the state dict as safetensors, data only.

    Args:
        observation_space: the environment's observation space.
        action_space: a bounded Box (``[gas, brake, steer]`` in [-1, 1]).
        hidden_sizes: widths of the hidden layers after the features.
        device: where ``act_`` puts the observations (TorchActorModule's).
    """

    def __init__(self, observation_space: Any, action_space: Any, hidden_sizes: tuple[int, ...] = (256, 256),
                 device: Any = "cpu") -> None:
        super().__init__(observation_space, action_space, device=device)
        self.features = LidarFeatures(observation_space)
        self.net = mlp([self.features.out_dim, *hidden_sizes], nn.ReLU, nn.ReLU)
        act_dim = space_dim(action_space)
        self.mu = nn.Linear(hidden_sizes[-1], act_dim)
        self.log_std = nn.Linear(hidden_sizes[-1], act_dim)
        low = torch.as_tensor(action_space.low, dtype=torch.float32).reshape(-1)
        high = torch.as_tensor(action_space.high, dtype=torch.float32).reshape(-1)
        # Not persistent: the bounds come from the action space, the weights file holds only
        # what is learned.
        self.register_buffer("act_scale", (high - low) / 2, persistent=False)
        self.register_buffer("act_offset", (high + low) / 2, persistent=False)

    def forward(self, obs: Any, test: bool = False, with_logprob: bool = True) -> tuple[torch.Tensor, Any]:
        h = self.net(self.features(obs))
        mu = self.mu(h)
        std = self.log_std(h).clamp(-20.0, 2.0).exp()
        u = mu if test else mu + std * torch.randn_like(mu)  # reparameterised: gradients flow
        logp = None
        if with_logprob:  # log-density of tanh(u): the Gaussian's, corrected for the squashing
            logp = torch.distributions.Normal(mu, std).log_prob(u).sum(-1)
            logp = logp - (2.0 * (math.log(2.0) - u - F.softplus(-2.0 * u))).sum(-1)
        return torch.tanh(u) * self.act_scale + self.act_offset, logp

    def act(self, obs: Any, test: bool = False) -> np.ndarray:
        action, _ = self.forward(obs, test=test, with_logprob=False)
        return action[0].cpu().numpy()


class ConvLidarQ(nn.Module):
    """A critic ``Q(obs, act)``, shape ``(B,)``, with features of its own.

    Args:
        observation_space: the environment's observation space.
        action_space: the action space.
        hidden_sizes: widths of the hidden layers.
    """

    def __init__(self, observation_space: Any, action_space: Any, hidden_sizes: tuple[int, ...] = (256, 256)) -> None:
        super().__init__()
        self.features = LidarFeatures(observation_space)
        self.net = mlp([self.features.out_dim + space_dim(action_space), *hidden_sizes, 1], nn.ReLU)

    def forward(self, obs: Any, act: torch.Tensor) -> torch.Tensor:
        return self.net(torch.cat([self.features(obs), act.float()], dim=-1)).squeeze(-1)


class ConvLidarActorCritic(nn.Module):
    """What ``SACAgent(model_cls=...)`` trains: ``actor`` and two critics ``q1``, ``q2``.

    Args:
        observation_space: the environment's observation space.
        action_space: the action space.
    """

    def __init__(self, observation_space: Any, action_space: Any) -> None:
        super().__init__()
        self.actor = ConvLidarActor(observation_space, action_space)
        self.q1 = ConvLidarQ(observation_space, action_space)
        self.q2 = ConvLidarQ(observation_space, action_space)
# --8<-- [end:model]


# --- the pipeline of `python -m tmrl --trainer / --worker`, with the entry plugged in --------------

# --8<-- [start:config]
def load_pipeline(port: int | None) -> tuple[Any, Any, Any]:
    """The command line's configuration objects: ``(config_constants, config_objects, settings)``.

    Both modules are built from config.json when first imported, so the overrides go first, into
    ``$TMRL_CONFIG_OVERRIDE``, where the roles started from this process read them too.
    """
    from tmrl.config.loader import config_path, install, set_override_env

    if not config_path().is_file():
        install(env="simlidar")  # the simulator's config.json, with a fresh random PASSWORD
    set_override_env({"RUN_NAME": RUN_NAME, **({"PORT": port} if port else {})})
    from tmrl.config import config_constants as cc
    from tmrl.config import config_objects as co
    from tmrl.config.settings import NetSettings

    if cc.RTGYM_INTERFACE not in LIDAR_INTERFACES:
        sys.exit(f"config.json is set up for {cc.RTGYM_INTERFACE}; this entry reads lidar observations: "
                 "run `python -m tmrl --install --env simlidar` (your other edits are kept)")
    return cc, co, NetSettings.from_config(cc.TMRL_CONFIG)
# --8<-- [end:config]


# --8<-- [start:plug]
def make_trainer(co: Any, settings: Any) -> Any:
    """The Trainer of ``--trainer``, training our model with the configured SAC."""
    from tmrl.networking import Trainer
    from tmrl.util import partial

    # config_objects.TRAINER is the training loop the CLI runs, AGENT the configured SAC: the
    # same partials with one keyword changed (functools.partial merges them).
    agent = partial(co.AGENT, model_cls=ConvLidarActorCritic)
    return Trainer(training_cls=partial(co.TRAINER, training_agent_cls=agent), settings=settings,
                   obs_preprocessor=co.OBS_PREPROCESSOR, sample_compressor=co.SAMPLE_COMPRESSOR)


def make_worker(co: Any, settings: Any, verbose: bool = False) -> Any:
    """The RolloutWorker of ``--worker``, running our actor (``worker.env`` counts the laps)."""
    from tmrl.networking import RolloutWorker

    return RolloutWorker(env_cls=lambda: DrivingStats(co.ENV_CLS(), verbose), actor_module_cls=ConvLidarActor,
                         sample_compressor=co.SAMPLE_COMPRESSOR, obs_preprocessor=co.OBS_PREPROCESSOR,
                         max_samples_per_episode=settings.max_samples_per_episode, settings=settings)
# --8<-- [end:plug]


# --- progress: laps on the worker's side, rounds on the trainer's ---------------------------------


class DrivingStats(gymnasium.Wrapper):
    """Watches the worker's episodes (it changes nothing): laps, lap times, progress along the track.

    Args:
        env: the environment.
        verbose: print one line per episode.
    """

    def __init__(self, env: Any, verbose: bool = False) -> None:
        super().__init__(env)
        self.verbose = verbose
        self.episodes = self.laps = 0
        self.best_lap = math.inf
        self.best_progress = 0.0
        self._return = 0.0

    def reset(self, **kwargs: Any) -> Any:
        self._return = 0.0
        return self.env.reset(**kwargs)

    def step(self, action: Any) -> Any:
        obs, rew, terminated, truncated, info = self.env.step(action)
        self._return += float(rew)
        if terminated or truncated:
            self.episodes += 1
            race = getattr(self.env.unwrapped, "race", None)  # the simulator's; TrackMania has none
            progress = float(race.progress) if race is not None else math.nan
            self.best_progress = max(self.best_progress, progress)
            lap = info.get("lap_time") if info.get("lap_completed") else None
            if lap is not None:
                self.laps += 1
                self.best_lap = min(self.best_lap, lap)
            if self.verbose:
                print(f"episode {self.episodes}: return {self._return:.1f}, progress {100 * progress:.0f}%"
                      + (f", LAP {lap:.2f} s" if lap is not None else ""), flush=True)
        return obs, rew, terminated, truncated, info

    def summary(self) -> str:
        best = f", best lap {self.best_lap:.2f} s" if self.laps else ""
        return f"{self.episodes} episodes, {self.laps} laps{best}, best progress {100 * self.best_progress:.0f}%"


class RoundLine(TrainingCallback):
    """Prints one line per round and ends training after ``minutes``.

    Args:
        minutes: the training budget.
        stats: the worker's statistics, when the worker runs in this process.
    """

    def __init__(self, minutes: float, stats: DrivingStats | None = None) -> None:
        self.t0 = time.monotonic()
        self.deadline = self.t0 + 60.0 * minutes
        self.stats = stats
        self.best = -math.inf
        self.first_lap_said = False

    def on_round_end(self, training: Any, m: Any) -> bool | None:
        elapsed = time.monotonic() - self.t0
        ret = m.return_train if m.episode_length_train > 0 else math.nan  # no episode ended yet: nan
        self.best = max(self.best, ret) if math.isfinite(ret) else self.best
        worker = f" | {self.stats.summary()}" if self.stats is not None else ""
        print(f"round {m.epoch}.{m.round}: {m.total_samples} env steps, {m.total_updates} updates "
              f"({m.updates_per_second:.0f}/s), return train {ret:.1f} (best {self.best:.1f}), "
              f"{elapsed:.0f} s{worker}", flush=True)
        if self.stats is not None and self.stats.laps and not self.first_lap_said:
            self.first_lap_said = True
            print(f"first lap completed after {elapsed:.0f} s, {m.total_samples} env steps, "
                  f"{m.total_updates} updates", flush=True)
        if time.monotonic() >= self.deadline:
            training.epochs = training.epoch  # Trainer.run stops once epoch reaches epochs
            return False  # end this epoch now; Trainer.run then writes the checkpoint
        return None


# --- the roles -------------------------------------------------------------------------------------


def run_trainer(co: Any, cc: Any, settings: Any, minutes: float, stats: DrivingStats | None = None) -> None:
    from tmrl.metrics import MetricsLogger

    trainer = make_trainer(co, settings)
    # as --trainer: the console line, and <data folder>/logs/competition_sim/metrics.csv
    trainer.metrics_logger = MetricsLogger(run_name=cc.RUN_NAME, folder=cc.TMRL_FOLDER)
    trainer.add_callback(RoundLine(minutes, stats))
    trainer.run()
    print(f"trainer done: {trainer.run_instance.total_updates} updates; the actor's weights are in "
          f"{settings.model_path_trainer}", flush=True)


def run_worker(co: Any, settings: Any) -> None:
    worker = make_worker(co, settings, verbose=True)
    try:
        worker.run()  # until Ctrl-C, as --worker
    except KeyboardInterrupt:
        pass
    finally:
        worker.close(5.0)
    print(f"worker stopped: {worker.env.summary()}, weights version {worker.weights_version}", flush=True)


def run_all(co: Any, cc: Any, settings: Any, minutes: float) -> None:
    """Server, trainer and worker in this process: the worker in a thread, the trainer here."""
    from tmrl.networking import Server

    server = Server(settings=settings)
    worker = make_worker(co, settings)
    stats = worker.env
    threading.Thread(target=worker.run, daemon=True).start()
    try:
        run_trainer(co, cc, settings, minutes, stats)
    finally:
        worker.close(5.0)
        server.stop(5.0)
    print(f"worker: {stats.summary()}, weights version {worker.weights_version}", flush=True)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    role = ap.add_mutually_exclusive_group()
    for name in ("server", "trainer", "worker"):
        role.add_argument(f"--{name}", dest="role", action="store_const", const=name,
                          help=f"run the {name} only (default: all three in this process)")
    ap.add_argument("--minutes", type=float, default=5.0, help="training time budget (default 5)")
    ap.add_argument("--port", type=int, default=None, help="the server's port (default: PORT of config.json)")
    args = ap.parse_args()
    logging.basicConfig(level=logging.WARNING, format="%(asctime)s %(name)s: %(message)s", datefmt="%H:%M:%S")
    torch.set_num_threads(1)  # as the demo: one thread per role leaves the other core to the rest
    cc, co, settings = load_pipeline(args.port)
    if args.role == "server":
        from tmrl.roles import run_server

        sys.exit(run_server())  # the command line's server, until Ctrl-C
    elif args.role == "trainer":
        run_trainer(co, cc, settings, args.minutes)
    elif args.role == "worker":
        run_worker(co, settings)
    else:
        run_all(co, cc, settings, args.minutes)


if __name__ == "__main__":
    main()
