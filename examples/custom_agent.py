"""A training agent of your own: TD3, written from scratch against ``tmrl.training.TrainingAgent``.

tmrl's trainer does not care which algorithm it runs. ``TorchTrainingOffline`` builds the agent
with ``training_agent_cls(observation_space=..., action_space=..., device=...)``, then calls

- ``agent.train(batch)`` once per training step, with a ``tmrl.batch.Batch`` of tensors
  (``obs, act, rew, next_obs, terminated, truncated``) sampled from the replay memory; it returns
  a dict of metrics (numbers or 0-dim tensors, averaged per round);
- ``agent.get_actor()`` whenever it sends weights to the workers: a ``TorchActorModule`` whose
  ``save``/``load`` write data-only safetensors. The workers build the same actor class
  themselves (``RolloutWorker(actor_module_cls=...)``) and load those weights into it;
- ``agent.state_dict()`` / ``load_state_dict()`` for checkpoints: the base class collects every
  module, optimizer and tensor attribute, so this agent needs no code for it.

This file plugs a TD3 agent (twin critics, delayed policy updates, target policy smoothing;
Fujimoto et al. 2018) exactly where tmrl's SACAgent goes, and trains it on Pendulum-v1 through the
library's Server, Trainer and RolloutWorker, all in this process:

    python examples/custom_agent.py                  # 3 minutes, port 6688
    python examples/custom_agent.py --minutes 1 --port 7000

Each round prints the environment steps, updates, and the worker's latest train and test returns
(Pendulum's return is between about -1600 and 0; a policy that swings up and holds the pendulum
gets above -200), and a line the first time the test return exceeds -400, then -200. The
figures measured on a 2-core CPU are on docs/competition.md.

The trained actor's weights are written to ``<data folder>/weights/custom_agent_td3.tmod``
(``$TMRL_DATA``, default ``~/TmrlData``).
"""

from __future__ import annotations

import argparse
import copy
import logging
import math
import secrets
import threading
import time
from typing import Any

import numpy as np
import torch
from torch import nn

from tmrl.actor import TorchActorModule
from tmrl.batch import Batch
from tmrl.config.loader import data_folder
from tmrl.models import flatten_obs, mlp, space_dim
from tmrl.training import TrainingAgent
from tmrl.training_offline import TrainingCallback

# --8<-- [start:model]
# --- the networks ---------------------------------------------------------------------------------
# TD3's actor is deterministic; exploration noise is added by the *worker*, in act(), because the
# worker is the one that explores. The trainer only ever calls forward(). tmrl.models gives the
# small helpers: flatten_obs (a batched observation, tensor or tuple of tensors, as one (B, n)
# float tensor), mlp (Linear layers with an activation between them) and space_dim (the number of
# values in a Box or a Tuple of Boxes).


class DeterministicActor(TorchActorModule):
    """``a = tanh(mlp(obs))`` rescaled to the action bounds. What the workers run.

    Args:
        observation_space: the observation space (a Box or a Tuple of Boxes).
        action_space: a bounded Box.
        hidden_sizes: widths of the hidden layers.
        exploration_noise: std of the Gaussian noise added in training episodes, as a fraction
            of the action range's half-width.
    """

    def __init__(self, observation_space: Any, action_space: Any, hidden_sizes: tuple[int, ...] = (64, 64),
                 exploration_noise: float = 0.1) -> None:
        super().__init__(observation_space, action_space)
        self.net = mlp([space_dim(observation_space), *hidden_sizes, space_dim(action_space)], nn.ReLU)
        low = torch.as_tensor(action_space.low, dtype=torch.float32).reshape(-1)
        high = torch.as_tensor(action_space.high, dtype=torch.float32).reshape(-1)
        # Buffers move with .to(device); persistent=False keeps them out of the weights file,
        # which then holds the learned parameters only.
        self.register_buffer("act_scale", (high - low) / 2, persistent=False)
        self.register_buffer("act_offset", (high + low) / 2, persistent=False)
        self.exploration_noise = float(exploration_noise)

    def forward(self, obs: Any) -> torch.Tensor:
        return torch.tanh(self.net(flatten_obs(obs))) * self.act_scale + self.act_offset

    def act(self, obs: Any, test: bool = False) -> np.ndarray:
        # Called by the worker with a batch of one (TorchActorModule.act_ collates it, no grad).
        a = self.forward(obs)
        if not test:  # training episodes explore around the deterministic action
            a = a + self.exploration_noise * self.act_scale * torch.randn_like(a)
            a = torch.max(torch.min(a, self.act_offset + self.act_scale), self.act_offset - self.act_scale)
        return a[0].cpu().numpy()


class Critic(nn.Module):
    """``Q(obs, act)``, shape ``(B,)``.

    Args:
        observation_space: the observation space.
        action_space: the action space.
        hidden_sizes: widths of the hidden layers.
    """

    def __init__(self, observation_space: Any, action_space: Any, hidden_sizes: tuple[int, ...] = (64, 64)) -> None:
        super().__init__()
        self.net = mlp([space_dim(observation_space) + space_dim(action_space), *hidden_sizes, 1], nn.ReLU)

    def forward(self, obs: Any, act: torch.Tensor) -> torch.Tensor:
        return self.net(torch.cat((flatten_obs(obs), act.float()), dim=-1)).squeeze(-1)


class TD3Model(nn.Module):
    """What ``TD3Agent`` trains: ``actor``, ``q1`` and ``q2``. Any module with these three
    attributes will do (``model_cls`` of ``TD3Agent``): ``actor`` a ``TorchActorModule`` whose
    forward returns actions within the bounds, ``q1`` and ``q2`` called as ``q(obs, act)``.

    Args:
        observation_space: the observation space.
        action_space: a bounded Box.
        hidden_sizes: widths of the hidden layers of the actor and of each critic.
    """

    def __init__(self, observation_space: Any, action_space: Any, hidden_sizes: tuple[int, ...] = (64, 64)) -> None:
        super().__init__()
        self.actor = DeterministicActor(observation_space, action_space, hidden_sizes)
        self.q1 = Critic(observation_space, action_space, hidden_sizes)
        self.q2 = Critic(observation_space, action_space, hidden_sizes)
# --8<-- [end:model]


# --8<-- [start:agent]
# --- the training agent ---------------------------------------------------------------------------


class TD3Agent(TrainingAgent):
    """TD3 as a tmrl training agent.

    Args:
        observation_space: given by the training loop.
        action_space: given by the training loop (a bounded Box).
        device: given by the training loop.
        model_cls: builds the module holding ``actor``, ``q1`` and ``q2`` from the two spaces.
        gamma: discount factor.
        polyak: target networks move by ``1 - polyak`` towards the online ones at each policy update.
        lr_actor: Adam learning rate of the actor.
        lr_critic: Adam learning rate of the critics.
        policy_delay: the actor and the targets are updated once every ``policy_delay`` critic updates.
        target_noise: std of the noise added to the target action (fraction of the half-range).
        noise_clip: that noise is clipped to +/- this (same unit).
    """

    def __init__(self, observation_space: Any, action_space: Any, device: Any, model_cls: Any = TD3Model,
                 gamma: float = 0.99, polyak: float = 0.995, lr_actor: float = 1e-3, lr_critic: float = 1e-3,
                 policy_delay: int = 2, target_noise: float = 0.2, noise_clip: float = 0.5) -> None:
        super().__init__(observation_space, action_space, device)
        self.gamma, self.polyak = float(gamma), float(polyak)
        self.policy_delay = int(policy_delay)
        self.target_noise, self.noise_clip = float(target_noise), float(noise_clip)
        self.model = model_cls(observation_space, action_space).to(device)
        # The target networks: a frozen copy, moved towards the online networks by Polyak averaging.
        self.model_target = copy.deepcopy(self.model).requires_grad_(False)
        self.actor_optimizer = torch.optim.Adam(self.model.actor.parameters(), lr=lr_actor)
        self.critic_params = [*self.model.q1.parameters(), *self.model.q2.parameters()]
        self.critic_optimizer = torch.optim.Adam(self.critic_params, lr=lr_critic)
        # A tensor, not an int: the base class's state_dict() saves tensors (and modules and
        # optimizers), so a resumed run keeps the rhythm of its delayed updates.
        self.updates = torch.zeros((), dtype=torch.long)
        self.last_loss_actor = torch.zeros((), device=device)
        low = torch.as_tensor(action_space.low, dtype=torch.float32, device=device).reshape(-1)
        high = torch.as_tensor(action_space.high, dtype=torch.float32, device=device).reshape(-1)
        self.act_low, self.act_high = low, high

    def get_actor(self) -> TorchActorModule:
        # The live actor: the trainer saves its weights at once (the training thread calls this
        # between two updates), so no copy is needed.
        return self.model.actor

    @torch.no_grad()
    def target_value(self, b: Batch) -> torch.Tensor:
        """``r + gamma (1 - terminated) min(Q1', Q2')(o', a')``, ``a'`` the target actor's action
        plus clipped noise. An episode cut short (``truncated``) still bootstraps: only
        ``terminated`` means there is no future."""
        a2 = self.model_target.actor(b.next_obs)
        half_range = (self.act_high - self.act_low) / 2
        noise = (torch.randn_like(a2) * self.target_noise).clamp(-self.noise_clip, self.noise_clip)
        a2 = torch.max(torch.min(a2 + noise * half_range, self.act_high), self.act_low)
        q_next = torch.min(self.model_target.q1(b.next_obs, a2), self.model_target.q2(b.next_obs, a2))
        return b.rew.reshape(-1) + self.gamma * (1.0 - b.terminated.reshape(-1).float()) * q_next

    def train(self, batch: tuple) -> dict[str, Any]:
        b = Batch(*batch)  # a 6-tuple works too (tmrl 0.7's memories return one)
        # 1. the critics regress on the target value
        y = self.target_value(b)
        q1, q2 = self.model.q1(b.obs, b.act), self.model.q2(b.obs, b.act)
        loss_critic = (q1 - y).square().mean() + (q2 - y).square().mean()
        self.critic_optimizer.zero_grad(set_to_none=True)
        loss_critic.backward()
        self.critic_optimizer.step()
        self.updates += 1
        # 2. every policy_delay updates: the actor climbs Q1, and the targets follow
        if int(self.updates) % self.policy_delay == 0:
            for p in self.critic_params:  # the actor's loss must not move the critics
                p.requires_grad_(False)
            loss_actor = -self.model.q1(b.obs, self.model.actor(b.obs)).mean()
            self.actor_optimizer.zero_grad(set_to_none=True)
            loss_actor.backward()
            self.actor_optimizer.step()
            for p in self.critic_params:
                p.requires_grad_(True)
            with torch.no_grad():
                for p_targ, p in zip(self.model_target.parameters(), self.model.parameters()):
                    p_targ.lerp_(p, 1.0 - self.polyak)  # p_targ <- polyak p_targ + (1 - polyak) p
            self.last_loss_actor = loss_actor.detach()
        # 0-dim tensors: the training loop averages them over the round and reads them once
        return {"loss_critic": loss_critic.detach(), "loss_actor": self.last_loss_actor,
                "debug_q": q1.detach().mean()}
# --8<-- [end:agent]


# --- the three roles in one process ---------------------------------------------------------------

RUN_NAME = "custom_agent_td3"
HIDDEN = (64, 64)


# --8<-- [start:plug]
def training_cls() -> Any:
    """The trainer's training loop, with TD3Agent where the SAC examples put SACAgent."""
    from tmrl.envs import GenericGymEnv
    from tmrl.memory import GenericTorchMemory
    from tmrl.training_offline import TorchTrainingOffline
    from tmrl.util import partial

    return partial(
        TorchTrainingOffline,
        env_cls=partial(GenericGymEnv, id="Pendulum-v1"),  # built once, for its spaces
        memory_cls=partial(GenericTorchMemory, memory_size=100_000, batch_size=256),
        training_agent_cls=partial(TD3Agent, model_cls=partial(TD3Model, hidden_sizes=HIDDEN)),
        epochs=1_000_000,  # the --minutes budget ends the run (see Progress)
        rounds=10,
        steps=250,  # training steps per round: one printed line each
        update_buffer_interval=25,
        update_model_interval=25,
        # One update per environment step at most on the trainer's side, and (sent to the worker
        # with every weights broadcast) one environment step per update at most on the worker's:
        # Pendulum runs far faster than real time and would otherwise outrun the trainer.
        max_training_steps_per_env_step=1.0,
        max_env_steps_per_training_step=1.0,
        start_training=1000,
        sleep_between_buffer_retrieval_attempts=0.01,
        device="cpu",
    )


def worker_actor_cls() -> Any:
    """The workers' actor: the class TD3Model puts in ``actor``, with the same sizes."""
    from tmrl.util import partial

    return partial(DeterministicActor, hidden_sizes=HIDDEN)
# --8<-- [end:plug]


class Progress(TrainingCallback):
    """A training callback: prints one line per round, says when the test return first exceeds
    each of ``targets``, and stops the run at the deadline."""

    def __init__(self, minutes: float, targets: tuple[float, ...] = (-400.0, -200.0)) -> None:
        self.t0 = time.monotonic()
        self.deadline = self.t0 + 60.0 * minutes
        self.targets = list(targets)
        self.best = -math.inf

    def on_round_end(self, training: Any, m: Any) -> bool | None:
        elapsed = time.monotonic() - self.t0
        # The worker reports an episode's return once it has ended (a length of 0: none yet).
        train = m.return_train if m.episode_length_train > 0 else math.nan
        test = m.return_test if m.episode_length_test > 0 else math.nan
        if math.isfinite(test):
            self.best = max(self.best, test)
        print(f"round {m.epoch}.{m.round}: {m.total_samples} env steps, {m.total_updates} updates, "
              f"return train {train:.1f} test {test:.1f} (best test {self.best:.1f}), "
              f"loss critic {m.agent.get('loss_critic', math.nan):.3f}, {elapsed:.0f} s", flush=True)
        for target in [t for t in self.targets if test > t]:
            self.targets.remove(target)
            print(f"test return above {target:g} after {m.total_samples} env steps, "
                  f"{m.total_updates} updates, {elapsed:.0f} s", flush=True)
        if time.monotonic() >= self.deadline:
            # Trainer.run ends once `epoch` reaches `epochs`; returning False ends this epoch now
            # (without counting it), so the run ends here (this example keeps no checkpoint:
            # checkpoint_path=None below).
            training.epochs = training.epoch
            return False
        return None


def run(minutes: float, port: int) -> None:
    from tmrl.envs import GenericGymEnv
    from tmrl.networking import RolloutWorker, Server, Trainer
    from tmrl.util import partial

    torch.set_num_threads(1)  # trainer and worker share this process (and a small CPU)
    weights = data_folder() / "weights"
    # plain TCP on 127.0.0.1 with a fresh password: nothing leaves this machine
    net = {"server_ip": "127.0.0.1", "server_port": port, "password": secrets.token_hex(16), "security": None}
    server = Server(port=port, password=net["password"], security=None)
    # obs_preprocessor and sample_compressor: the worker's (none here), so that the trainer checks
    # the shapes of incoming samples against the spaces
    trainer = Trainer(training_cls=training_cls(), model_path=str(weights / f"{RUN_NAME}.tmod"),
                      checkpoint_path=None, obs_preprocessor=None, sample_compressor=None, **net)
    trainer.add_callback(progress := Progress(minutes))
    worker = RolloutWorker(env_cls=partial(GenericGymEnv, id="Pendulum-v1"), actor_module_cls=worker_actor_cls(),
                           max_samples_per_episode=200, model_history=0,
                           model_path=str(weights / f"{RUN_NAME}_worker.tmod"), **net)
    # The worker's loop, as `python -m tmrl --worker` runs it: training episodes (sent as they
    # end), a test episode (no exploration noise) before every 5th one, new weights between
    # episodes; the trainer's pace (max_env_steps_per_training_step) pauses it when it is ahead.
    threading.Thread(target=worker.run, kwargs={"test_episode_interval": 5}, daemon=True).start()
    try:
        trainer.run()
    finally:
        worker.close(5.0)
        server.stop(5.0)
    print(f"done: best test return {progress.best:.1f}; the actor's weights are in "
          f"{weights / f'{RUN_NAME}.tmod'}", flush=True)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--minutes", type=float, default=3.0, help="training time budget (default 3)")
    ap.add_argument("--port", type=int, default=6688, help="the server's port on 127.0.0.1 (default 6688)")
    args = ap.parse_args()
    logging.basicConfig(level=logging.WARNING, format="%(asctime)s %(name)s: %(message)s", datefmt="%H:%M:%S")
    run(args.minutes, args.port)


if __name__ == "__main__":
    main()
