"""Pendulum-v1 trained with tmrl's distributed pipeline, through the library API.

A tmrl run has three parts: a Server (the relay), a Trainer (learns from samples, broadcasts
weights) and one or more RolloutWorkers (collect samples with the latest weights). They usually
live on different machines; here they run on this one.

    python examples/pendulum_distributed.py                 # all three in one process
    python examples/pendulum_distributed.py --server        # or three terminals:
    python examples/pendulum_distributed.py --trainer
    python examples/pendulum_distributed.py --worker        # (start as many workers as you like)
    python examples/pendulum_distributed.py --test          # watch the trained policy (no server)

Settings are plain Python below; nothing here reads config.json except the data folder location
(``TmrlData`` in your home, or ``$TMRL_DATA``), where weights and the checkpoint are kept. The
trainer resumes from its checkpoint when restarted; delete it to start over.

Security: this example uses plain TCP on 127.0.0.1. Across machines, use ``security="TLS"`` with
the credentials made by ``python -m tmrl --install`` and a strong password (see docs/networking.md).
"""

from __future__ import annotations

import argparse
import logging
import os
import threading
import time
from pathlib import Path

import gymnasium

from tmrl.algorithms.sac import SACAgent
from tmrl.envs import GenericGymEnv
from tmrl.memory import GenericTorchMemory
from tmrl.models import MLPActorCritic, SquashedGaussianMLPActor
from tmrl.networking import RolloutWorker, Server, Trainer
from tmrl.training_offline import TorchTrainingOffline
from tmrl.util import partial

# --- where the parts meet -------------------------------------------------------------------------

SERVER_IP = "127.0.0.1"
SERVER_PORT = 6666
PASSWORD = os.environ.get("TMRL_EXAMPLE_PASSWORD", "change-me-on-a-real-network")
SECURITY = None  # plain TCP: fine on localhost; use "TLS" across machines

RUN_NAME = "pendulum_distributed"
DATA = Path(os.environ.get("TMRL_DATA", Path.home() / "TmrlData"))
WORKER_MODEL = DATA / "weights" / f"{RUN_NAME}_worker.tmod"
TRAINER_MODEL = DATA / "weights" / f"{RUN_NAME}_trainer.tmod"
CHECKPOINT = DATA / "checkpoints" / f"{RUN_NAME}_t"  # None: no checkpoint

# --- the environment ------------------------------------------------------------------------------

env_cls = partial(GenericGymEnv, id="Pendulum-v1")
_spaces_env = gymnasium.make("Pendulum-v1")
SPACES = (_spaces_env.observation_space, _spaces_env.action_space)  # the trainer needs only the spaces

# --- the trainer's training class -----------------------------------------------------------------

HIDDEN = (64, 64)  # small networks: Pendulum does not need more, and each update is 4x cheaper

training_cls = partial(
    TorchTrainingOffline,
    env_cls=SPACES,
    memory_cls=partial(GenericTorchMemory, memory_size=1_000_000, batch_size=256),
    training_agent_cls=partial(
        SACAgent,
        model_cls=partial(MLPActorCritic, hidden_sizes=HIDDEN),
        gamma=0.99,
        polyak=0.995,
        alpha=0.2,
        lr_actor=1e-3,
        lr_critic=1e-3,
        lr_entropy=1e-3,
        learn_entropy_coef=True,
        target_entropy=None,
    ),
    epochs=10,  # an epoch ends with a checkpoint
    rounds=10,  # statistics are logged after each round
    steps=500,  # training steps per round
    update_buffer_interval=20,  # training steps between two retrievals of the workers' samples
    update_model_interval=20,  # training steps between two broadcasts of the actor's weights
    max_training_steps_per_env_step=1.0,  # the trainer waits for samples above this ratio
    start_training=1000,  # samples in memory before the first training step
    sleep_between_buffer_retrieval_attempts=0.01,
    device="cpu",
)


def make_server() -> Server:
    return Server(port=SERVER_PORT, password=PASSWORD, security=SECURITY)


def make_trainer() -> Trainer:
    return Trainer(
        training_cls=training_cls,
        server_ip=SERVER_IP,
        server_port=SERVER_PORT,
        password=PASSWORD,
        security=SECURITY,
        model_path=str(TRAINER_MODEL),
        checkpoint_path=str(CHECKPOINT),
    )


def make_worker(standalone: bool = False, render: bool = False) -> RolloutWorker:
    cls = partial(GenericGymEnv, id="Pendulum-v1", gym_kwargs={"render_mode": "human"}) if render else env_cls
    return RolloutWorker(
        env_cls=cls,
        actor_module_cls=partial(SquashedGaussianMLPActor, hidden_sizes=HIDDEN),
        device="cpu",
        max_samples_per_episode=1000,
        model_path=str(TRAINER_MODEL if standalone else WORKER_MODEL),
        model_history=0,
        standalone=standalone,
        server_ip=SERVER_IP,
        server_port=SERVER_PORT,
        password=PASSWORD,
        security=SECURITY,
    )


def can_render() -> bool:
    """Pendulum's window needs pygame and a display; without them --test prints returns only."""
    import importlib.util
    import os
    import sys

    has_display = sys.platform in ("win32", "darwin") or bool(os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY"))
    if importlib.util.find_spec("pygame") is None or not has_display:
        print("no window: rendering Pendulum needs pygame (pip install pygame) and a display; printing returns")
        return False
    return True


def watch(episodes: int = 5) -> None:
    """Run the trained policy without a server and print each episode's return."""
    with make_worker(standalone=True, render=can_render()) as worker:
        for i in range(episodes):
            print(f"test episode {i}: return {worker.run_episode(200):.1f}")


def run_worker(worker: RolloutWorker) -> None:
    # Pendulum can be stepped as fast as we like, so the worker keeps pace with the trainer:
    # at most 40 environment steps per model received (the trainer sends one every 20 updates).
    worker.run_synchronous(initial_steps=1000, max_steps_per_update=40, end_episodes=False)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    role = ap.add_mutually_exclusive_group()
    for name in ("server", "trainer", "worker", "test"):
        role.add_argument(f"--{name}", action="store_const", const=name, dest="role")
    args = ap.parse_args()
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s: %(message)s", datefmt="%H:%M:%S")
    try:
        if args.role == "server":
            server = make_server()
            try:
                while True:  # until Ctrl-C (a sleep lets it in on Windows; an untimed wait does not)
                    time.sleep(1.0)
            finally:
                server.stop()
        elif args.role == "trainer":
            make_trainer().run()
        elif args.role == "worker":
            with make_worker() as worker:
                run_worker(worker)
        elif args.role == "test":
            watch()
        else:
            server = make_server()
            worker = make_worker()
            threading.Thread(target=run_worker, args=(worker,), daemon=True).start()
            make_trainer().run()  # returns after `epochs` epochs
            worker.close()
            server.stop()
            print(f"done: the trained weights are in {TRAINER_MODEL}; watch them with --test")
    except KeyboardInterrupt:
        print("stopped (Ctrl-C)")


if __name__ == "__main__":
    main()
