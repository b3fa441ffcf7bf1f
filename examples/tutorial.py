"""tmrl as a library, from zero to a distributed pipeline on your own real-time device.

The device is tmrl's simulated remote-controlled drone (``tmrl.realtime.DummyRCDrone``); the script
writes its own real-time interface around it, checks it, and trains SAC on it through tmrl's three
parts: a Server, a Trainer and a RolloutWorker. docs/tutorial.md walks through it section by section.

    python examples/tutorial.py                      # all three parts in one process, a few minutes
    python examples/tutorial.py --minutes 1          # a shorter run
    python examples/tutorial.py --server             # or one part per terminal (or per machine):
    python examples/tutorial.py --trainer
    python examples/tutorial.py --worker
    python examples/tutorial.py --check              # only check the interface

The trainer resumes from its checkpoint (in the data folder: ``$TMRL_DATA`` or ``~/TmrlData``);
``--fresh`` deletes it first. Stop any part with Ctrl-C (exit code 130; the run in one process
still prints its summary and draws its plot).
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import os
import shutil
import sys
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch
from gymnasium import spaces
from torch import nn

from tmrl.actor import TorchActorModule, WeightsError
from tmrl.algorithms.sac import SACAgent
from tmrl.config.loader import data_folder
from tmrl.envs import GenericGymEnv
from tmrl.memory import TorchMemory
from tmrl.metrics import MetricsLogger
from tmrl.models import EnsembleQFunction, flatten_obs, mlp, space_dim
from tmrl.networking import RolloutWorker, Server, Trainer
from tmrl.realtime import DEFAULT_CONFIG_DICT, DummyRCDrone, RealTimeGymInterface, check_realtime_interface
from tmrl.realtime.timeouts import summarised_timeouts
from tmrl.training_offline import TorchTrainingOffline, TrainingCallback
from tmrl.util import partial

# --8<-- [start:settings]
# Where the three parts meet. On one machine: plain TCP on 127.0.0.1. Across machines, every part
# gets the server's address, the same port and password, and security="TLS" (see main()).
SERVER_IP = "127.0.0.1"
PORT = 6677
PASSWORD = os.environ.get("TMRL_TUTORIAL_PASSWORD", "tutorial-password-change-me")
SECURITY = None  # plain TCP: tmrl allows it on 127.0.0.1 only

# Files, all under the data folder ($TMRL_DATA, else ~/TmrlData).
RUN_NAME = "tutorial_drone"
DATA = data_folder()
WORKER_WEIGHTS = DATA / "weights" / f"{RUN_NAME}_worker.json"
TRAINER_WEIGHTS = DATA / "weights" / f"{RUN_NAME}_trainer.json"
CHECKPOINT = DATA / "checkpoints" / f"{RUN_NAME}_t"

# Real time: one time step is 20 ms (50 actions per second); see the page for why.
TIME_STEP = 0.02
EPISODE_STEPS = 50  # 1 s per episode
ACT_BUF_LEN = 4  # the drone's link delays add up to about 5 time steps
# --8<-- [end:settings]


# --8<-- [start:interface]
class MyDroneInterface(RealTimeGymInterface):
    """Fly the drone to a target that moves at each episode.

    Observation: the drone's position and the target, two float32 arrays of shape (2,).
    Action: a velocity command in [-1, 1]², sent as [-2, 2]² units per second.
    Reward: minus the distance to the target; the episode ends within 5 cm of it.
    """

    def __init__(self, max_speed: float = 2.0, success_distance: float = 0.05, seed: int | None = None) -> None:
        # Nothing touches the device here: the trainer builds this object only to read the spaces.
        self.max_speed = max_speed
        self.success_distance = success_distance
        self.rng = np.random.default_rng(seed)
        self.drone: DummyRCDrone | None = None
        self.target = np.zeros(2, dtype=np.float32)

    def get_observation_space(self) -> spaces.Tuple:
        position = spaces.Box(-1.0, 1.0, shape=(2,), dtype=np.float32)
        target = spaces.Box(-0.5, 0.5, shape=(2,), dtype=np.float32)
        return spaces.Tuple((position, target))  # the environment appends the action buffer

    def get_action_space(self) -> spaces.Box:
        return spaces.Box(-1.0, 1.0, shape=(2,), dtype=np.float32)

    def get_default_action(self) -> np.ndarray:
        return np.zeros(2, dtype=np.float32)  # hover

    def send_control(self, control: Any) -> None:
        if control is not None and self.drone is not None:  # never blocks: the radio is asynchronous
            self.drone.send_control(self.max_speed * float(control[0]), self.max_speed * float(control[1]))

    def reset(self, seed: int | None = None, options: dict | None = None) -> tuple[list, dict]:
        if self.drone is None:  # connect on the first episode, on the thread that will use the drone
            self.drone = DummyRCDrone(max_vel=self.max_speed)
        if seed is not None:
            self.rng = np.random.default_rng(seed)
        # A real drone cannot be teleported: it stays where it is and the target moves.
        self.target = self.rng.uniform(-0.5, 0.5, size=2).astype(np.float32)
        return self._observation(), {}

    def get_obs_rew_terminated_info(self) -> tuple[list, float, bool, dict]:
        obs = self._observation()
        distance = float(np.linalg.norm(obs[0] - obs[1]))
        return obs, -distance, distance < self.success_distance, {}

    def _observation(self) -> list[np.ndarray]:
        assert self.drone is not None
        position = np.clip(np.array(self.drone.get_observation(), dtype=np.float32), -1.0, 1.0)
        return [position, self.target.copy()]

    def close(self) -> None:
        if self.drone is not None:
            self.drone.close()  # stops the drone's radio thread
            self.drone = None
# --8<-- [end:interface]


# --8<-- [start:config]
def make_config(time_step: float = TIME_STEP) -> dict[str, Any]:
    """The rtgym-style configuration of the real-time environment."""
    config = dict(DEFAULT_CONFIG_DICT)  # a copy: never edit the default itself
    config.update(
        interface=MyDroneInterface,
        interface_kwargs={},
        time_step_duration=time_step,  # the cadence of the actions
        start_obs_capture=time_step,  # capture the observation at the end of each time step
        time_step_timeout_factor=1.0,  # up to one time step late, the cadence is kept
        ep_max_length=EPISODE_STEPS,  # episodes are truncated after this many steps
        act_buf_len=ACT_BUF_LEN,  # the last actions, appended to each observation
        act_in_obs=True,
        reset_act_buf=True,
    )
    return config


def make_env_cls(time_step: float = TIME_STEP) -> partial:
    """What a worker calls to build its environment: GenericGymEnv around the real-time env."""
    return partial(GenericGymEnv, id="real-time-gym-v1", gym_kwargs={"config": make_config(time_step)})


def drone_spaces() -> tuple[spaces.Tuple, spaces.Box]:
    """The environment's spaces without building it (the trainer's machine has no drone):
    the interface's observation followed by the action buffer."""
    interface = MyDroneInterface()
    act = interface.get_action_space()
    obs = spaces.Tuple((*interface.get_observation_space().spaces, *([act] * ACT_BUF_LEN)))
    return obs, act
# --8<-- [end:config]


# --8<-- [start:check]
def check_interface(time_step: float = TIME_STEP) -> bool:
    """Run tmrl's real-time checker on the interface and its configuration."""
    problems = check_realtime_interface(make_config(time_step), n_steps=10)
    for problem in problems:
        print("interface check:", problem)
    print("interface check:", "passed" if not problems else f"{len(problems)} problem(s)")
    return not problems
# --8<-- [end:check]


# --8<-- [start:actor]
class DroneActor(TorchActorModule):
    """The policy: an MLP giving a squashed Gaussian over the velocity command.

    The worker calls act(); SAC calls forward() during training. Weights travel as JSON.
    """

    def __init__(self, observation_space: Any, action_space: Any, hidden: int = 64, device: Any = "cpu") -> None:
        super().__init__(observation_space, action_space, device=device)
        n_act = int(np.prod(action_space.shape))
        self.body = mlp([space_dim(observation_space), hidden, hidden], nn.ReLU, nn.ReLU)
        self.mean = nn.Linear(hidden, n_act)
        self.log_std = nn.Linear(hidden, n_act)

    def forward(self, obs: Any, test: bool = False, with_logprob: bool = True) -> tuple[torch.Tensor, Any]:
        h = self.body(flatten_obs(obs))  # the observation tuple as one (batch, features) tensor
        mean, log_std = self.mean(h), self.log_std(h).clamp(-20.0, 2.0)
        u = mean if test else mean + log_std.exp() * torch.randn_like(mean)
        logp = None
        if with_logprob:  # log-density of tanh(u), with the change of variables of the SAC paper
            logp = torch.distributions.Normal(mean, log_std.exp()).log_prob(u).sum(-1)
            logp = logp - (2.0 * (math.log(2.0) - u - nn.functional.softplus(-2.0 * u))).sum(-1)
        return torch.tanh(u), logp  # the action space is [-1, 1]

    def act(self, obs: Any, test: bool = False) -> np.ndarray:
        action, _ = self.forward(obs, test=test, with_logprob=False)
        return action[0].cpu().numpy()  # the worker hands one observation at a time

    def save(self, path: str | os.PathLike[str]) -> None:
        state = {name: t.detach().cpu().tolist() for name, t in self.state_dict().items()}
        Path(path).write_text(json.dumps(state), encoding="utf-8")

    def load(self, path: str | os.PathLike[str], device: Any) -> DroneActor:
        def refuse(constant: str) -> None:
            raise WeightsError(f"{path} holds {constant}: refused")

        state = json.loads(Path(path).read_text(encoding="utf-8"), parse_constant=refuse)
        self.load_state_dict({name: torch.tensor(values) for name, values in state.items()})
        return self.to_device(device)


class DroneActorCritic(nn.Module):
    """What SACAgent trains: the actor above (``.actor``) and two critics (``.qs``)."""

    def __init__(self, observation_space: Any, action_space: Any, hidden: int = 64) -> None:
        super().__init__()
        self.actor = DroneActor(observation_space, action_space, hidden)
        self.qs = EnsembleQFunction(observation_space, action_space, (hidden, hidden), n=2)
# --8<-- [end:actor]


# --8<-- [start:memory]
class TutorialMemory(TorchMemory):
    """A replay memory of whole samples in a list.

    A worker's sample is (action, new observation, reward, terminated, truncated, info); transition i
    goes from sample i to sample i + 1, when both belong to the same episode.
    """

    def append_buffer(self, buffer: Any) -> None:
        samples = list(buffer.memory)
        if not samples:
            return
        # the last sample of a buffer ends the chain: the next buffer may come from another worker
        last = samples[-1]
        samples[-1] = (*last[:4], True, last[5])  # mark it truncated for the memory's purposes
        self.data.extend(samples)
        del self.data[: max(0, len(self.data) - self.memory_size)]  # forget the oldest samples
        self.starts = [i for i in range(len(self.data) - 1) if not (self.data[i][3] or self.data[i][4])]

    def __len__(self) -> int:
        return len(getattr(self, "starts", ()))

    def get_transition(self, item: int) -> tuple:
        i = self.starts[item]
        _, prev_obs, _, _, _, _ = self.data[i]
        act, new_obs, rew, terminated, truncated, info = self.data[i + 1]
        return prev_obs, act, rew, new_obs, terminated, truncated, info
# --8<-- [end:memory]


# --8<-- [start:training]
training_cls = partial(
    TorchTrainingOffline,
    env_cls=drone_spaces(),  # (observation space, action space): the trainer needs no drone
    memory_cls=partial(TutorialMemory, memory_size=100_000, batch_size=128),
    training_agent_cls=partial(  # your own TrainingAgent subclass would go here instead
        SACAgent,
        model_cls=DroneActorCritic,
        gamma=0.95,  # short episodes: a short horizon
        lr_actor=1e-3,
        lr_critic=1e-3,
    ),
    epochs=10_000,  # the trainer stops earlier, on its time budget (see TimeBudget)
    rounds=5,  # one metrics line per round, a checkpoint per epoch
    steps=200,  # training steps per round
    update_buffer_interval=10,  # steps between two retrievals of the workers' samples
    update_model_interval=50,  # steps between two broadcasts of the actor's weights
    max_training_steps_per_env_step=2.0,  # the trainer waits for samples beyond this ratio
    start_training=500,  # samples before the first training step (10 s of flight)
    sleep_between_buffer_retrieval_attempts=0.05,
    device="cpu",
)
# --8<-- [end:training]


# --8<-- [start:budget]
class TimeBudget(TrainingCallback):
    """Ends training at the first end of epoch after ``minutes`` of wall-clock time."""

    def __init__(self, minutes: float) -> None:
        self.deadline = time.monotonic() + 60.0 * minutes

    def on_epoch_end(self, training: Any, rows: list) -> None:
        if time.monotonic() >= self.deadline:
            training.epochs = training.epoch  # Trainer.run() returns after this epoch's checkpoint
# --8<-- [end:budget]


# --8<-- [start:parts]
def make_server(net: dict) -> Server:
    return Server(port=net["server_port"], password=net["password"], security=net["security"])


def make_trainer(net: dict, minutes: float) -> Trainer:
    trainer = Trainer(
        training_cls=training_cls,
        model_path=str(TRAINER_WEIGHTS),
        checkpoint_path=str(CHECKPOINT),
        obs_preprocessor=None,  # what the workers use: the trainer checks samples against the spaces
        sample_compressor=None,
        **net,
    )
    trainer.metrics_logger = MetricsLogger(RUN_NAME, folder=DATA)  # console line + logs/<run>/metrics.csv
    trainer.add_callback(TimeBudget(minutes))
    return trainer


def make_worker(net: dict, time_step: float = TIME_STEP) -> RolloutWorker:
    return RolloutWorker(
        env_cls=make_env_cls(time_step),
        actor_module_cls=DroneActor,
        device="cpu",
        max_samples_per_episode=EPISODE_STEPS,
        model_path=str(WORKER_WEIGHTS),
        model_history=0,
        **net,
    )


def fly(worker: RolloutWorker, stop: threading.Event, returns: list[float]) -> None:
    """The worker's loop: one training episode, send its samples, take the newest weights."""
    while not stop.is_set():
        worker.collect_train_episode()
        ret, steps = worker.buffer.stat_train_return, worker.buffer.stat_train_steps
        worker.send_and_clear_buffer()
        worker.update_actor_weights(verbose=False)
        returns.append(ret)
        print(f"episode {len(returns)}: return {ret:7.2f} in {steps} steps (weights version {worker.weights_version})",
              flush=True)
# --8<-- [end:parts]


# --8<-- [start:all_in_one]
def all_in_one(net: dict, minutes: float, time_step: float) -> tuple[list[float], bool]:
    """The three parts in one process: the server's relay, the worker in a thread, the trainer here.
    Returns the episodes' returns and whether Ctrl-C ended the run (what ran is kept)."""
    torch.set_num_threads(1)  # the trainer and the worker share this process's cores
    returns: list[float] = []
    stop = threading.Event()
    interrupted = False
    with make_server(net), make_worker(net, time_step) as worker:
        flight = threading.Thread(target=fly, args=(worker, stop, returns), daemon=True)
        flight.start()
        try:
            make_trainer(net, minutes).run()  # returns when the time budget is spent
        except KeyboardInterrupt:
            interrupted = True  # Ctrl-C: the summary and the plot show what ran
        finally:
            stop.set()
            flight.join(timeout=10.0)
            worker.env.close()
    return returns, interrupted


def summary(returns: list[float]) -> str:
    if not returns:
        return "summary: no episode finished"
    k = max(1, min(20, len(returns) // 4))
    first, last = float(np.mean(returns[:k])), float(np.mean(returns[-k:]))
    return f"summary: {len(returns)} episodes; mean return of the first {k} {first:.2f}, of the last {k} {last:.2f}"
# --8<-- [end:all_in_one]


def require_matplotlib() -> None:
    """``--plot`` needs matplotlib: say so in one line before the run, not after it."""
    try:
        import matplotlib  # noqa: F401
    except ImportError:
        print("tutorial.py: --plot needs matplotlib, which is not installed: pip install matplotlib", file=sys.stderr)
        raise SystemExit(2) from None


def plot(returns: list[float], path: str) -> None:
    """Draw the returns of a run into a PNG (used for the page's figure)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 3.5))
    ax.plot(range(1, len(returns) + 1), returns, lw=0.8, alpha=0.5, label="episode return")
    k = 10
    if len(returns) >= k:
        smooth = np.convolve(returns, np.ones(k) / k, mode="valid")
        ax.plot(range(k, len(returns) + 1), smooth, lw=2, label=f"mean of {k}")
    ax.set_xlabel("episode (1 s of flight each)")
    ax.set_ylabel("return")
    ax.set_title("examples/tutorial.py: SAC on the simulated drone, all in one process")
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    print(f"plot written to {path}")


# --8<-- [start:main]
def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    role = ap.add_mutually_exclusive_group()
    for name in ("server", "trainer", "worker", "check"):
        role.add_argument(f"--{name}", action="store_const", const=name, dest="role")
    ap.add_argument("--minutes", type=float, default=4.0, help="the trainer's wall-clock budget")
    ap.add_argument("--server-ip", default=SERVER_IP, help="the server's address (from the trainer and workers)")
    ap.add_argument("--port", type=int, default=PORT)
    ap.add_argument("--password", default=PASSWORD)
    ap.add_argument("--tls", action="store_true", help="TLS, with the credentials of python -m tmrl --install")
    ap.add_argument("--time-step", type=float, default=TIME_STEP, help="seconds per time step")
    ap.add_argument("--fresh", action="store_true", help="delete the checkpoint and weights first")
    ap.add_argument("--plot", metavar="FILE", help="all in one: draw the returns into FILE (PNG)")
    args = ap.parse_args()
    if args.plot:
        require_matplotlib()
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s: %(message)s", datefmt="%H:%M:%S")
    net = {
        "server_ip": args.server_ip,
        "server_port": args.port,
        "password": args.password,
        "security": "TLS" if args.tls else SECURITY,
    }
    if args.fresh:
        shutil.rmtree(CHECKPOINT, ignore_errors=True)
        for path in (WORKER_WEIGHTS, TRAINER_WEIGHTS):
            path.unlink(missing_ok=True)
    # Under load, time steps run late: one line per 10 s says how many, instead of two per step.
    with summarised_timeouts(interval=10.0) as timeouts:
        try:
            if args.role == "check":
                return 0 if check_interface(args.time_step) else 1
            if args.role == "server":
                with make_server(net):
                    while True:  # relay until Ctrl-C (a sleep lets it in on Windows; an untimed wait does not)
                        time.sleep(1.0)
            elif args.role == "trainer":
                make_trainer(net, args.minutes).run()
                print(f"trainer done: weights in {TRAINER_WEIGHTS}, checkpoint in {CHECKPOINT}")
            elif args.role == "worker":
                with make_worker(net, args.time_step) as worker:
                    try:
                        fly(worker, threading.Event(), [])
                    finally:
                        worker.env.close()
            else:
                check_interface(args.time_step)
                returns, interrupted = all_in_one(net, args.minutes, args.time_step)
                timeouts.flush()  # the last late time steps, before the summary
                if interrupted:  # Ctrl-C during the run: its summary and plot all the same
                    print(f"stopped (Ctrl-C) after {len(returns)} episodes")
                print(summary(returns))
                if args.plot and returns:
                    plot(returns, args.plot)
                return 130 if interrupted else 0
        except KeyboardInterrupt:
            print("stopped (Ctrl-C)")
            return 130  # 128 + SIGINT, as python -m tmrl
    return 0
# --8<-- [end:main]


if __name__ == "__main__":
    sys.exit(main())
