"""The weights' way from the trainer's agent to a worker's actor, at every broadcast (issue 41:
on the tutorial's settings, one broadcast per update, it took three quarters of the trainer's
time): what it still does at each broadcast, and what it no longer does.

Real parts: a relay on 127.0.0.1, the Trainer's interface, a RolloutWorker, the SAC agent and
the training loop.
"""

from __future__ import annotations

import os
import sys
import threading
import time
from pathlib import Path
from typing import Any

import gymnasium
import numpy as np
import process_support
import pytest
import torch

from tmrl.distributed.weights import WeightsInstaller, move_over, replace_file
from tmrl.networking import RolloutWorker
from tmrl.spaces import describe_spaces
from tmrl.transport import credentials
from tmrl.transport.credentials import TRAINER_PUBLIC_KEY_FILE, ensure_trainer_key
from tmrl.util import partial

sys.path.insert(0, str(Path(__file__).resolve().parent))
from test_networking import JsonActor
from test_security import PW, closing, make_trainer, relay, sac_training  # noqa: F401 (closing: a fixture)
from test_training_offline import FakeInterface, make_training

pytestmark = pytest.mark.timeout(120)


def _pendulum() -> Any:
    return gymnasium.make("Pendulum-v1")


def _actor_cls() -> Any:
    from tmrl.models import SquashedGaussianMLPActor

    return partial(SquashedGaussianMLPActor, hidden_sizes=(16, 16))


def _no_sync(monkeypatch: pytest.MonkeyPatch) -> list[int]:
    """Make any sync to disk in this process fail the test (the calls are also recorded)."""
    calls: list[int] = []

    def refuse(fd: int) -> None:
        calls.append(fd)
        raise AssertionError("synced to disk on the broadcast path")

    monkeypatch.setattr(os, "fsync", refuse)
    return calls


# --- 1. the trainer's side and the worker's side sync nothing -------------------------------------


def test_a_broadcast_and_its_install_never_sync_to_disk(tmp_path, port_factory, closing, monkeypatch):
    port = port_factory()
    closing.append(relay(port))
    env = _pendulum()
    trainer = make_trainer(tmp_path, port, sac_training(spaces=(env.observation_space, env.action_space)))
    closing.append(trainer.interface)
    run = trainer._load_or_create()  # announces the initial actor
    worker = RolloutWorker(env_cls=_pendulum, actor_module_cls=_actor_cls(), server_ip="127.0.0.1",
                           server_port=port, password=PW, security=None, header_size=10,
                           keys_dir=str(tmp_path / "credentials"), model_path=str(tmp_path / "w.tmod"),
                           model_history=0)
    closing.append(worker)
    assert worker.update_actor_weights(verbose=False, blocking=True) == 1
    _no_sync(monkeypatch)
    actor = run.agent.get_actor()
    with torch.no_grad():
        next(actor.parameters()).add_(0.5)  # new weights, as after an update
    trainer.interface.broadcast_model(actor)
    assert worker.update_actor_weights(verbose=False, blocking=True) == 1
    expected = actor.to_bytes()
    assert (tmp_path / "trainer.tmod").read_bytes() == expected  # the trainer's copy
    assert (tmp_path / "w.tmod").read_bytes() == expected  # the worker's copy
    for mine, theirs in zip(worker.actor.state_dict().values(), actor.state_dict().values()):
        assert torch.equal(mine, theirs)
    leftovers = [p.name for p in tmp_path.iterdir() if p.name.startswith(".")]
    assert leftovers == []  # no temporary file left behind


def test_the_trainer_broadcasts_the_bytes_that_save_writes(tmp_path, port_factory, closing):
    """In memory for a TorchActorModule that keeps its own save; through save's file for an actor
    with a save of its own (tmrl 0.7's scripts)."""
    port = port_factory()
    closing.append(relay(port))
    env = _pendulum()
    trainer = make_trainer(tmp_path, port, sac_training(spaces=(env.observation_space, env.action_space)))
    closing.append(trainer.interface)
    run = trainer._load_or_create()
    actor = run.agent.get_actor()
    actor.save(tmp_path / "saved.tmod")
    assert trainer.interface.flush_broadcasts(30)
    assert (tmp_path / "trainer.tmod").read_bytes() == (tmp_path / "saved.tmod").read_bytes()
    json_actor = JsonActor(env.observation_space, env.action_space)
    json_actor.bias = 0.25
    trainer.interface.broadcast_model(json_actor)
    assert trainer.interface.flush_broadcasts(30)
    assert (tmp_path / "trainer.tmod").read_text() == '{"bias": 0.25}'


def test_a_copy_replaces_the_old_one_atomically_and_waits_for_a_reader_that_holds_it(tmp_path, monkeypatch):
    """Windows refuses to replace a file that another process holds open (PermissionError): the
    copy is retried until the file is free, the old one is never removed first (a reader would find
    none), and a file held for good leaves the old copy and no temporary file, in one error."""
    from tmrl import platform

    monkeypatch.setattr(platform, "BUSY_DELAYS", (0.0,) * 4)
    target = tmp_path / "model.tmod"
    target.write_bytes(b"old")
    real_replace, real_unlink = os.replace, os.unlink
    held = {"left": 3, "calls": 0}

    def replace(src: Any, dst: Any) -> None:
        held["calls"] += 1
        if held["left"] > 0:
            held["left"] -= 1
            raise PermissionError(13, "held by another process (emulated)", str(dst))
        real_replace(src, dst)

    def unlink(path: Any, *args: Any, **kwargs: Any) -> None:
        assert os.fspath(path) != os.fspath(target), "the old copy was removed before the new one was in place"
        real_unlink(path, *args, **kwargs)

    monkeypatch.setattr(os, "replace", replace)
    monkeypatch.setattr(os, "unlink", unlink)
    replace_file(target, b"weights 1")
    assert target.read_bytes() == b"weights 1" and held["calls"] == 4
    (tmp_path / "incoming").write_bytes(b"new")
    held["left"] = 2
    move_over(tmp_path / "incoming", target)
    assert target.read_bytes() == b"new" and not (tmp_path / "incoming").exists()
    held["left"] = 100  # held for good
    with pytest.raises(platform.FileBusy, match="held by another process"):
        replace_file(target, b"weights 2")
    assert target.read_bytes() == b"new"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["model.tmod"]


# --- 2. the training thread never waits for the network ----------------------------------------


def _big_training(env: Any) -> Any:
    """A SAC training whose actor's file is about 1 MiB, the size of the link's pipe."""
    from tmrl.algorithms.sac import SACAgent
    from tmrl.models import MLPActorCritic

    return sac_training(spaces=(env.observation_space, env.action_space),
                        training_agent_cls=partial(SACAgent, model_cls=partial(MLPActorCritic, hidden_sizes=(512, 512))))


def test_broadcasts_never_wait_for_the_network_and_the_newest_gets_through(tmp_path, port_factory, closing):
    """The trainer's network process is stopped (a loaded machine, or a slow network): a
    broadcast goes on at once, a newer one replaces a waiting one, and once the network process
    runs again the workers get the newest, its version counting the ones replaced."""
    port = port_factory()
    closing.append(relay(port))
    env = _pendulum()
    trainer = make_trainer(tmp_path, port, _big_training(env))
    closing.append(trainer.interface)
    run = trainer._load_or_create()
    worker = RolloutWorker(env_cls=_pendulum, actor_module_cls=partial(_actor_cls().func, hidden_sizes=(512, 512)),
                           server_ip="127.0.0.1", server_port=port, password=PW, security=None, header_size=10,
                           keys_dir=str(tmp_path / "credentials"), model_path=str(tmp_path / "w.tmod"),
                           model_history=0)
    closing.append(worker)
    assert worker.update_actor_weights(verbose=False, blocking=True) == 1 and worker.weights_version == 1
    actor = run.agent.get_actor()
    assert len(actor.to_bytes()) > 1_000_000
    net = trainer.interface._link._proc.proc
    process_support.freeze(net.pid)
    try:
        def broadcast_ten() -> None:
            for _ in range(10):
                with torch.no_grad():
                    next(actor.parameters()).add_(0.01)
                trainer.interface.broadcast_model(actor)

        thread = threading.Thread(target=broadcast_ten, daemon=True)
        thread.start()
        thread.join(20)
        assert not thread.is_alive(), "a broadcast waited for the stopped network process"
    finally:
        process_support.thaw(net.pid)
    assert trainer.interface.flush_broadcasts(30)
    assert trainer.interface._publisher.replaced >= 5  # waiting ones were replaced, not queued
    newest = actor.to_bytes()
    deadline = time.monotonic() + 30
    while worker.weights_version < 11 and time.monotonic() < deadline:
        worker.update_actor_weights(verbose=False, blocking=True)
    assert worker.weights_version == 11  # the newest, and versions 2-10 count as received
    assert (tmp_path / "w.tmod").read_bytes() == newest == (tmp_path / "trainer.tmod").read_bytes()


def test_a_failed_send_is_raised_by_the_next_broadcast_and_close_sends_the_last(tmp_path, port_factory, closing):
    port = port_factory()
    closing.append(relay(port))
    env = _pendulum()
    trainer = make_trainer(tmp_path, port, sac_training(spaces=(env.observation_space, env.action_space)))
    closing.append(trainer.interface)
    run = trainer._load_or_create()
    actor = run.agent.get_actor()
    trainer.interface.broadcast_model(actor)
    trainer.interface.close(10)  # sends what waits, then disconnects
    late = RolloutWorker(env_cls=_pendulum, actor_module_cls=_actor_cls(), server_ip="127.0.0.1", server_port=port,
                         password=PW, security=None, header_size=10, keys_dir=str(tmp_path / "credentials"),
                         model_path=str(tmp_path / "late.tmod"), model_history=0)
    closing.append(late)
    assert late.update_actor_weights(verbose=False, blocking=True) == 1 and late.weights_version == 2
    other = make_trainer(tmp_path / "b", port, sac_training(spaces=(env.observation_space, env.action_space)))
    closing.append(other.interface)
    run = other._load_or_create()
    assert other.interface.flush_broadcasts(30)
    net = other.interface._link._proc.proc
    process_support.kill(net.pid)
    net.wait(10)
    other.interface.broadcast_model(run.agent.get_actor())  # handed over: fails on the publishing thread
    assert other.interface.flush_broadcasts(30)
    with pytest.raises(ConnectionError, match="network process is gone"):
        other.interface.broadcast_model(run.agent.get_actor())


# --- 3. the worker reads the pinned key again only when the file changed -------------------------


def test_the_pinned_key_is_read_again_only_when_its_file_changed(tmp_path, monkeypatch):
    env = _pendulum()
    keys = tmp_path / "credentials"
    keys.mkdir()
    installer = WeightsInstaller(describe_spaces(env.observation_space, env.action_space), "cpu",
                                 tmp_path / "w.tmod", str(tmp_path / "hist"), 0, keys)
    reads: list[Any] = []
    real = credentials.load_trainer_public_key

    def counting(directory: Any) -> Any:
        reads.append(directory)
        return real(directory)

    monkeypatch.setattr(credentials, "load_trainer_public_key", counting)
    assert installer.pinned_key() is None  # nothing pinned yet
    first = ensure_trainer_key(tmp_path / "k1").public_pem
    (keys / TRAINER_PUBLIC_KEY_FILE).write_bytes(first)  # pinned while the worker runs
    assert installer.pinned_key() == first
    n = len(reads)
    for _ in range(5):
        assert installer.pinned_key() == first
    assert len(reads) == n  # unchanged: not read again
    second = ensure_trainer_key(tmp_path / "k2").public_pem
    tmp = keys / "new.pem"
    tmp.write_bytes(second)
    os.replace(tmp, keys / TRAINER_PUBLIC_KEY_FILE)  # replaced: read again
    assert installer.pinned_key() == second
    (keys / TRAINER_PUBLIC_KEY_FILE).unlink()  # removed: no key
    assert installer.pinned_key() is None


# --- 4. the training loop checks the actor at every broadcast, the whole state less often ---------


class TwoPartAgent:
    """An actor and a critic with losses of their own: a NaN in one leaves the other finite."""

    def __init__(self, observation_space: Any, action_space: Any, device: Any) -> None:
        obs_dim = sum(int(np.prod(s.shape)) for s in observation_space)
        self.actor = torch.nn.Linear(obs_dim, action_space.shape[0])
        self.critic = torch.nn.Linear(obs_dim + action_space.shape[0], 1)
        self.optimizer = torch.optim.SGD([*self.actor.parameters(), *self.critic.parameters()], lr=1e-3)

    def train(self, batch: Any) -> dict[str, Any]:
        o, a, r, _, _, _ = batch
        obs = torch.cat(list(o), -1)
        loss_critic = ((self.critic(torch.cat([obs, a], -1)).squeeze(-1) - r) ** 2).mean()
        loss_actor = (self.actor(obs) ** 2).mean()
        self.optimizer.zero_grad()
        (loss_critic + loss_actor).backward()
        self.optimizer.step()
        return {}

    def get_actor(self) -> torch.nn.Module:
        return self.actor

    def state_dict(self) -> dict[str, Any]:
        return {"actor": self.actor.state_dict(), "critic": self.critic.state_dict()}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.actor.load_state_dict(state["actor"])
        self.critic.load_state_dict(state["critic"])


class Broadcasts(FakeInterface):
    """Records, at every broadcast, the update count and whether the actor sent was finite;
    ``poison`` (update count -> module name) puts a NaN into that module after that update."""

    def __init__(self, poison: dict[int, str]) -> None:
        super().__init__(endless=10)
        self.poison = poison
        self.sent: list[tuple[int, bool]] = []

    def broadcast_model(self, actor: Any) -> None:
        updates = self.training.total_updates
        self.sent.append((updates, all(bool(torch.isfinite(p).all()) for p in actor.parameters())))
        name = self.poison.get(updates)
        if name is not None:
            with torch.no_grad():
                getattr(self.training.agent, name).weight[0, 0] = float("nan")


def _run(poison: dict[int, str], monkeypatch: pytest.MonkeyPatch, interval: int = 10) -> tuple[Any, Broadcasts]:
    monkeypatch.setattr(type(make_training(training_agent_cls=TwoPartAgent)), "FULL_CHECK_INTERVAL", interval)
    training = make_training(training_agent_cls=TwoPartAgent, epochs=1, rounds=1, steps=50,
                             update_model_interval=1, update_buffer_interval=1, start_training=10)
    checks: list[int] = []
    real = training.ensure_finite

    def counted() -> bool:
        checks.append(training.total_updates)
        return real()

    training.ensure_finite = counted
    interface = Broadcasts(poison)
    interface.training = training
    training.run_epoch(interface)
    training.checks = checks
    return training, interface


def test_the_whole_state_is_checked_once_per_interval_not_at_every_broadcast(monkeypatch):
    training, interface = _run({}, monkeypatch)
    assert len(interface.sent) == 50  # a broadcast after every update
    assert training.checks == [1, 11, 21, 31, 41]


def test_an_actor_that_is_not_finite_is_restored_before_it_is_sent(monkeypatch):
    training, interface = _run({5: "actor"}, monkeypatch)
    assert all(finite for _, finite in interface.sent)
    assert training.restored_states == 1 and 6 in training.checks  # at once, not at update 11


def test_a_critic_that_is_not_finite_is_restored_at_the_next_full_check(monkeypatch):
    training, interface = _run({15: "critic"}, monkeypatch)
    assert training.restored_states == 1
    assert torch.isfinite(training.agent.critic.weight).all()
    assert training.checks == [1, 11, 21, 31, 41]  # the check after update 15 (at 21) restored it


# --- 5. a round's metrics are averaged in one pass per metric --------------------------------------


def test_the_round_means_of_scalar_tensors_are_those_of_each_value_and_cost_one_pass(monkeypatch):
    """The built-in agents return 0-dim tensors: they are stacked at once (a round of 1000 updates
    spent 0.2 to 0.5 s averaging them one by one), with the same means as value by value:
    non-finite values skipped, any dtype, other values and shapes as before."""
    import math

    from tmrl.training_offline import _mean_rows

    rows = [{"loss": torch.tensor(float(i)), "alpha": torch.tensor(i, dtype=torch.int64),
             "q": torch.tensor(0.1 * i, dtype=torch.float64), "bad": torch.tensor(math.nan if i % 2 else 1.0),
             "vec": torch.full((3,), float(i)) if i else torch.tensor(0.0), "plain": 0.5 * i} for i in range(1000)]
    one_by_one = {key: float(np.mean([float(r[key].float().mean()) if torch.is_tensor(r[key]) else r[key]
                                      for r in rows if not (torch.is_tensor(r[key]) and r[key].isnan().any())]))
                  for key in rows[0]}
    means = _mean_rows(rows)
    assert means.keys() == one_by_one.keys()
    for key, value in one_by_one.items():
        assert means[key] == pytest.approx(value, rel=1e-6), key
    calls: list[int] = []
    real_float = torch.Tensor.float

    def counting_float(self: torch.Tensor, *args: Any, **kwargs: Any) -> torch.Tensor:
        calls.append(1)
        return real_float(self, *args, **kwargs)

    monkeypatch.setattr(torch.Tensor, "float", counting_float)
    scalars = [{"loss": torch.tensor(float(i)), "q": torch.tensor(1.0)} for i in range(1000)]
    assert _mean_rows(scalars) == {"loss": 499.5, "q": 1.0}
    assert len(calls) <= 2  # once per metric, not once per value (2000)


# --- 6. the worker starts each episode with the newest weights it received --------------------------


def _json_setup(tmp_path: Path, port: int, closing: list, env_cls: Any = None, actor_cls: Any = None,
                **worker_kwargs: Any) -> tuple[Any, Any, Any]:
    """A relay, a trainer's interface and a connected-to-be worker (``CountingEnv`` and ``JsonActor``
    unless given), and an actor of ``actor_cls`` for the trainer to broadcast."""
    from test_networking import CountingEnv

    from tmrl.networking import TrainerInterface

    env_cls, actor_cls = env_cls or CountingEnv, actor_cls or JsonActor
    closing.append(relay(port))
    iface = TrainerInterface(server_ip="127.0.0.1", server_port=port, password=PW, security=None, header_size=10,
                             keys_dir=str(tmp_path / "credentials"), model_path=str(tmp_path / "t.json"))
    closing.append(iface)
    worker = RolloutWorker(env_cls=env_cls, actor_module_cls=actor_cls, server_ip="127.0.0.1",
                           server_port=port, password=PW, security=None, header_size=10,
                           keys_dir=str(tmp_path / "credentials"), model_path=str(tmp_path / "w.json"),
                           model_history=0, max_samples_per_episode=1000, **worker_kwargs)
    closing.append(worker)
    actor = actor_cls(CountingEnv().observation_space, CountingEnv().action_space)
    return iface, worker, actor


def _broadcast_until_held(iface: Any, worker: Any, actor: Any, biases: list[float]) -> None:
    """Broadcast one version per bias and wait until the worker's link holds the last one."""
    from tmrl.distributed.weights import unpack_weights

    for bias in biases:
        actor.bias = bias
        iface.broadcast_model(actor)
    assert iface.flush_broadcasts(30)
    link = worker._link
    deadline = time.monotonic() + 30
    while time.monotonic() < deadline:
        with link._weights_cv:
            held = link._weights
            if held is not None and unpack_weights(held)[0]["version"] == iface.weights_version:
                return
            link._weights_cv.wait(0.5)
    raise AssertionError("the worker's link never got the last broadcast")


@pytest.mark.parametrize("newest", [True, False])
def test_each_episode_starts_with_the_newest_weights_received(tmp_path, port_factory, closing, newest):
    """A worker ahead of its budget never has to wait for weights (here the budget is unbounded):
    tmrl 0.7 then acts with the weights it had; ours takes the newest at each episode's start."""
    iface, worker, actor = _json_setup(tmp_path, port_factory(), closing)
    assert worker.wait_connected(30)
    _broadcast_until_held(iface, worker, actor, [1.0, 2.0])
    worker.run_synchronous(nb_steps=50, initial_steps=1, newest_each_episode=newest)
    if newest:
        assert worker.weights_version == 2 and worker.actor.bias == 2.0
    else:
        assert worker.weights_version == 0 and worker.actor.bias == 0.0


def test_the_newest_weights_count_every_version_they_stand_for(tmp_path, port_factory, closing):
    """The pace is unchanged: weights taken at an episode's start count as the models received
    since the worker's current ones, as when it waits for them."""
    iface, worker, actor = _json_setup(tmp_path, port_factory(), closing)
    _broadcast_until_held(iface, worker, actor, [1.0])
    assert worker._take_newest(verbose=False) == 1 and worker.weights_version == 1
    _broadcast_until_held(iface, worker, actor, [2.0, 3.0, 4.0])
    assert worker._take_newest(verbose=False) == 3 and worker.actor.bias == 4.0
    assert worker._take_newest(verbose=False) == 0  # nothing newer


# --- 7. in real time the worker syncs inside an episode (sync_every) --------------------------------


def _received(iface: Any, want: int, timeout: float = 30.0) -> int:
    """Samples the trainer's interface has received, polled until ``want`` or the deadline."""
    got, deadline = 0, time.monotonic() + timeout
    while got < want and time.monotonic() < deadline:
        got += len(iface.retrieve_buffer())
        if got < want:
            time.sleep(0.02)
    return got


@pytest.mark.parametrize("sync_every", [5, 0])
def test_a_worker_that_syncs_every_few_steps_sends_and_takes_weights_inside_an_episode(
        tmp_path, port_factory, closing, sync_every):
    """One 20-step episode. At step 7 the trainer broadcasts new weights; at step 12 the trainer
    has received the samples of steps 1 to 10 and the worker acts with those weights from step 11,
    both before the episode ends. With ``sync_every=0`` (tmrl 0.7) neither happens until it ends."""
    from test_networking import CountingEnv

    seen: dict[str, Any] = {"actions": []}
    port = port_factory()

    class Env(CountingEnv):
        def step(self, action):
            seen["actions"].append(float(action[0]))
            out = super().step(action)
            if self.t == 7:
                _broadcast_until_held(iface, worker, actor, [5.0])
            if self.t == 12:
                seen["received_by_12"] = _received(iface, 10, timeout=10.0 if sync_every else 1.0)
            return out

    iface, worker, actor = _json_setup(tmp_path, port, closing, Env, sync_every=sync_every)
    assert worker.wait_connected(30)
    worker.collect_train_episode()
    actions = seen["actions"]
    assert len(actions) == 20 and actions[:10] == [0.0] * 10
    if sync_every:
        assert seen["received_by_12"] >= 10  # the reset and steps 1 to 10 were sent at step 10
        assert actions[10:] == [5.0] * 10 and worker.weights_version == 1
    else:
        assert seen["received_by_12"] == 0
        assert actions[10:] == [0.0] * 10 and worker.weights_version == 0


def test_sync_every_must_not_be_negative(tmp_path):
    from tmrl.errors import UserError

    with pytest.raises(UserError, match="sync_every"):
        RolloutWorker(env_cls=lambda: gymnasium.make("Pendulum-v1"), actor_module_cls=JsonActor, standalone=True,
                      model_path=str(tmp_path / "w.json"), sync_every=-1)


def test_worker_sync_steps_in_the_config_reaches_the_worker(tmp_path):
    from tmrl.config.loader import deep_merge, validate
    from tmrl.config.schema import defaults
    from tmrl.config.settings import NetSettings

    cfg = validate(deep_merge(defaults(), {"WORKER_SYNC_STEPS": 20}), source="a test")
    settings = NetSettings.from_config(cfg, tmp_path)
    make = {"env_cls": lambda: gymnasium.make("Pendulum-v1"), "actor_module_cls": JsonActor, "standalone": True,
            "model_path": str(tmp_path / "w.json"), "settings": settings}
    assert RolloutWorker(**make).sync_every == 20
    assert RolloutWorker(**make, sync_every=0).sync_every == 0  # an argument wins over the config


# --- 8. in real time a test episode can feed the trainer too (run's test_samples) --------------------


@pytest.mark.parametrize("test_samples", [True, False])
def test_test_episodes_send_their_samples_only_when_asked(tmp_path, port_factory, closing, test_samples):
    """Two train episodes with a test episode before the first (``test_episode_interval=2``). The
    actor drives +1 when testing and -1 when training, and the reward is the action. With
    ``test_samples`` the test episode's 21 samples reach the trainer before the first train
    episode starts and count as a test episode; without (tmrl 0.7) only the 42 train samples do."""
    from test_networking import CountingEnv

    rewards: list[float] = []

    def receive(want: int, timeout: float) -> None:
        deadline = time.monotonic() + timeout
        while len(rewards) < want and time.monotonic() < deadline:
            rewards.extend(float(s[2]) for s in iface.retrieve_buffer().memory)
            time.sleep(0.02)

    class TwoFaced(JsonActor):
        def act(self, obs: Any, test: bool = False) -> np.ndarray:
            return np.array([1.0 if test else -1.0], np.float32)

    class Env(CountingEnv):
        resets = 0

        def reset(self, **kwargs: Any) -> Any:
            Env.resets += 1
            if Env.resets == 2:  # the first train episode starts: what has the trainer got?
                receive(21, timeout=10.0 if test_samples else 0.5)
                seen["before_train"] = len(rewards)
            return super().reset(**kwargs)

    seen: dict[str, int] = {}
    iface, worker, actor = _json_setup(tmp_path, port_factory(), closing, Env, TwoFaced)
    assert worker.wait_connected(30)
    _broadcast_until_held(iface, worker, actor, [0.0])
    Env.resets = 0
    worker.run(test_episode_interval=2, nb_episodes=2, test_samples=test_samples)
    receive(63 if test_samples else 42, timeout=30.0)
    resets = [0.0]  # a reset sample's reward
    if test_samples:
        assert seen["before_train"] == 21
        assert rewards == resets + [1.0] * 20 + (resets + [-1.0] * 20) * 2
        assert worker.buffer.stat_test_return == 20.0 and worker.buffer.stat_test_steps == 20
    else:
        assert seen["before_train"] == 0
        assert rewards == (resets + [-1.0] * 20) * 2
    assert worker.buffer.stat_train_return == -20.0
