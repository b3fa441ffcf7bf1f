"""tmrl.networking over real tlspyo on 127.0.0.1: a trainer and two workers exchange samples and
weights; a worker built for other spaces gets a clear error; killing (SIGKILL) and restarting the
worker, the server or the trainer loses no sample held by a live process; TLS with fresh
credentials; Ctrl-C on ``python -m tmrl --server`` exits cleanly and frees the port.

Samples are counted by id: the counting environment puts a sequence number in ``info["seq"]``.
Roles killed with SIGKILL run in subprocesses (this file run as a script, see ``_child``).
"""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import gymnasium
import numpy as np
import process_support
import pytest

from tmrl.networking import RolloutWorker, Server, Trainer, TrainerInterface

sys.path.insert(0, str(Path(__file__).resolve().parent))
from test_networking import CountingEnv, JsonActor, RecordingTraining, read_log, received_seqs

pytestmark = pytest.mark.timeout(60)

PW = "test-password"
HERE = Path(__file__).resolve()


# ------------------------------------------------------------------------------------------------
# helpers


@pytest.fixture(autouse=True)
def _credentials_of_this_test(_isolated_data_folder, monkeypatch):
    """The credentials folder (the trainer's signing key) of this test's data folder, as the
    subprocesses read it: the config module of this process was loaded by an earlier test."""
    from tmrl.config import config_constants

    monkeypatch.setattr(config_constants, "CREDENTIALS_DIRECTORY", _isolated_data_folder / "credentials")


def wait_for(cond: Callable[[], Any], timeout: float = 15.0, what: str = "condition") -> Any:
    """Poll ``cond`` until it returns something truthy (events in other processes)."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        value = cond()
        if value:
            return value
        time.sleep(0.02)
    raise AssertionError(f"timed out waiting for {what}")


def relay_connections(port: int) -> list[str]:
    """States of the TCP sockets whose local port is ``port`` (the relay's side, in this process
    or its network process), excluding the listening socket: lets a test wait until the relay has
    closed a killed peer's connection."""
    return process_support.tcp_states(port)


def worker(tmp_path: Path, port: int, name: str, obs_dim: int = 3, **kwargs: Any) -> RolloutWorker:
    return RolloutWorker(
        env_cls=lambda: CountingEnv(obs_dim),
        actor_module_cls=JsonActor,
        server_ip="127.0.0.1",
        server_port=port,
        password=PW,
        security=None,
        model_path=str(tmp_path / f"{name}.json"),
        model_history=0,
        max_samples_per_episode=10,
        **kwargs,
    )


def wait_until_acting_with(w: RolloutWorker, trained: dict[str, Any]) -> None:
    """Load broadcasts until ``w``'s actor has the weights ``trained`` (a trainer's actor's state
    dict); an epoch that broadcasts more than once may deliver an earlier one first."""
    loaded = []

    def acts_with_trained() -> bool:
        loaded.append(w.update_actor_weights(verbose=False))
        return all(np.array_equal(v.numpy(), trained[k].numpy()) for k, v in w.actor.state_dict().items())

    wait_for(acts_with_trained, timeout=30, what="the worker to act with the trained weights")
    assert sum(loaded) >= 1


def interface(tmp_path: Path, port: int, **kwargs: Any) -> TrainerInterface:
    return TrainerInterface(
        server_ip="127.0.0.1",
        server_port=port,
        password=PW,
        security=None,
        model_path=str(tmp_path / "trainer_model.json"),
        **kwargs,
    )


def drain(
    iface: TrainerInterface, expected: int, timeout: float = 15.0, source: int | None = None
) -> list[tuple]:
    """Retrieve until ``expected`` samples (from ``source`` when given) arrived; returns
    (source, seq, act) of each sample from that source (or of every sample)."""
    got: list[tuple] = []

    def more() -> bool:
        buf = iface.retrieve_buffer()
        for sample, src in zip(buf.memory, buf.sources):
            if source is None or src == source:
                act = None if sample[0] is None else float(sample[0][0])
                got.append((src, sample[5]["seq"], act))
        return len(got) >= expected

    wait_for(more, timeout, f"{expected} samples at the trainer")
    return got


class Child:
    """A role in a process of its own, killed at once (with its network processes)."""

    def __init__(self, tmp_path: Path, role: str, **args: Any):
        self.log = open(tmp_path / f"{role}-{time.monotonic_ns()}.log", "wb")
        self.proc = subprocess.Popen(
            [sys.executable, str(HERE), role, json.dumps(args)],
            stdout=subprocess.PIPE,
            stderr=self.log,
            cwd=str(tmp_path),
        )

    def line(self, timeout: float = 20.0) -> dict:
        """Next JSON line the child prints (a readiness or progress event)."""
        result: list[bytes] = []
        t = threading.Thread(target=lambda: result.append(self.proc.stdout.readline()), daemon=True)
        t.start()
        t.join(timeout)
        if not result or not result[0]:
            raise AssertionError(f"child gave no line in {timeout} s (log: {self.log.name})")
        return json.loads(result[0])

    def kill(self) -> None:
        process_support.kill_tree(self.proc.pid)
        self.proc.wait()
        self.log.close()


@pytest.fixture
def children():
    started: list[Child] = []
    yield started
    for c in started:
        c.kill()


@pytest.fixture
def closing():
    objs: list[Any] = []
    yield objs
    for o in reversed(objs):
        (o.stop if hasattr(o, "stop") else o.close)()


# ------------------------------------------------------------------------------------------------
# tests


def test_trainer_and_two_workers_exchange_samples_and_weights(tmp_path, port_factory, closing):
    port = port_factory()
    closing.append(Server(port=port, password=PW, security=None))
    log = tmp_path / "log.jsonl"
    trainer = Trainer(
        training_cls=lambda: RecordingTraining(str(log), epochs=2, samples_per_epoch=44),
        server_ip="127.0.0.1",
        server_port=port,
        password=PW,
        security=None,
        model_path=str(tmp_path / "trainer.json"),
        checkpoint_path=None,
    )
    thread = threading.Thread(target=trainer.run, daemon=True)
    thread.start()
    workers = [worker(tmp_path, port, f"w{i}") for i in range(2)]
    closing.extend(workers)
    for round_ in (1, 2):
        for w in workers:
            for _ in range(2):  # 2 episodes of 11 samples (reset + 10 steps)
                w.collect_train_episode()
                w.buffer.stat_train_return = -100.0 * (workers.index(w) + 1)
                w.send_and_clear_buffer()
        for w in workers:
            assert w.update_actor_weights(verbose=False, blocking=True) == 1
            assert w.actor.bias == round_  # the trainer's epoch-th actor reached every worker
    thread.join(20)
    assert not thread.is_alive()
    seqs = received_seqs(log)
    assert set(seqs) == {str(w.source_id) for w in workers}
    for w in workers:
        assert sorted(seqs[str(w.source_id)]) == list(range(44))  # every sample, exactly once
    # the trainer saw each worker's own statistics, not the last one merged
    assert read_log(log)[-1]["ret"] == pytest.approx(-150.0)


def test_run_synchronous_keeps_pace_with_the_trainer(tmp_path, port_factory, closing):
    port = port_factory()
    closing.append(Server(port=port, password=PW, security=None))
    log = tmp_path / "log.jsonl"
    trainer = Trainer(
        training_cls=lambda: RecordingTraining(str(log), epochs=100, samples_per_epoch=11),
        server_ip="127.0.0.1",
        server_port=port,
        password=PW,
        security=None,
        model_path=str(tmp_path / "trainer.json"),
        checkpoint_path=None,
    )
    thread = threading.Thread(target=trainer.run, daemon=True)
    thread.start()
    w = worker(tmp_path, port, "sync")
    closing.append(w)
    # one model per 11 samples at the trainer; the worker may run at most 15 steps per model
    w.run_synchronous(initial_steps=5, nb_steps=40, max_steps_per_update=15, end_episodes=True)
    # 1 initial episode + 4 episodes of 11 samples, all received
    wait_for(
        lambda: len(received_seqs(log).get(str(w.source_id), [])) == 55, what="55 samples at the trainer"
    )
    assert sorted(received_seqs(log)[str(w.source_id)]) == list(range(55))
    assert w.weights_version >= 2  # it had to wait for models to go on (ratio 23/1 > 15)
    trainer.run_instance.stop = True
    thread.join(20)
    assert not thread.is_alive()


def test_worker_with_other_spaces_keeps_its_actor_and_says_why(tmp_path, port_factory, closing, caplog):
    port = port_factory()
    closing.append(Server(port=port, password=PW, security=None))
    iface = interface(tmp_path, port)
    closing.append(iface)
    w = worker(tmp_path, port, "w4", obs_dim=4)
    closing.append(w)
    box3 = gymnasium.spaces.Box(-np.inf, np.inf, (3,), np.float32)
    actor = JsonActor(box3, gymnasium.spaces.Box(-1.0, 1.0, (1,), np.float32))
    actor.bias = 7.0
    iface.broadcast_model(actor)
    # a mismatch (a mistake, or a fake trainer) never stops the worker: it keeps its actor
    assert w.update_actor_weights(verbose=False, blocking=True) == 0
    assert w.actor.bias == 0.0 and not (tmp_path / "w4.json").exists() and w.rejected_weights == 1
    lines = [r.getMessage() for r in caplog.records if r.levelname == "ERROR"]
    assert len(lines) == 1
    assert "(3,)" in lines[0] and "(4,)" in lines[0] and "same environment" in lines[0]


def test_worker_killed_and_restarted_gets_latest_weights_and_samples_flow(
    tmp_path, port_factory, closing, children
):
    port = port_factory()
    closing.append(Server(port=port, password=PW, security=None))
    iface = interface(tmp_path, port)
    closing.append(iface)
    first = Child(tmp_path, "worker", port=port, episodes=5, model=str(tmp_path / "w1.json"))
    children.append(first)
    src1 = first.line()["source"]
    drain(iface, 11)
    actor = JsonActor(CountingEnv().observation_space, CountingEnv().action_space)
    actor.bias = 0.5
    iface.broadcast_model(actor)
    first.kill()
    # a new worker, started after the broadcast, gets it from the server and acts with it
    second = Child(
        tmp_path, "worker", port=port, episodes=3, wait_weights=True, model=str(tmp_path / "w2.json")
    )
    children.append(second)
    src2 = second.line()["source"]
    assert second.line()["bias"] == 0.5
    mine = drain(iface, 33, timeout=20, source=src2)
    assert sorted(g[1] for g in mine) == list(range(33))
    assert all(g[2] == 0.5 for g in mine if g[2] is not None)
    assert src1 != src2


def test_server_killed_and_restarted_keeps_samples_of_live_worker(tmp_path, port_factory, closing, children):
    port = port_factory()
    server = Child(tmp_path, "server", port=port)
    children.append(server)
    server.line()
    iface = interface(tmp_path, port)
    w = worker(tmp_path, port, "w")
    closing.extend([iface, w])
    assert w.wait_connected(15) and iface.wait_connected(15)
    w.collect_train_episode()
    w.send_and_clear_buffer()
    assert sorted(g[1] for g in drain(iface, 11)) == list(range(11))
    actor = JsonActor(CountingEnv().observation_space, CountingEnv().action_space)
    actor.bias = 0.25
    iface.broadcast_model(actor)
    assert w.update_actor_weights(verbose=False, blocking=True) == 1

    server.kill()
    wait_for(lambda: not w.connected and not iface.connected, what="both links to see the server gone")
    for _ in range(2):  # samples produced while the server is down stay with the worker
        w.collect_train_episode()
        w.send_and_clear_buffer()
    restarted = Child(tmp_path, "server", port=port)
    children.append(restarted)
    restarted.line()
    got = drain(iface, 22, timeout=30)
    assert sorted(g[1] for g in got) == list(range(11, 33))
    # the restarted server has no weights; the trainer sends its latest again on reconnection
    assert w.update_actor_weights(verbose=False, blocking=True) == 1 and w.actor.bias == 0.25


def test_weights_are_broadcast_again_on_a_reconnection_only(tmp_path, port_factory, closing, children):
    """Weights broadcast before the trainer's first connection reach the server once (the link keeps
    them until it connects); after a server restart they are sent again. A second copy after the
    first connection would reach a worker as if it were the next weights (it failed a test over NATS)."""
    port = port_factory()
    iface = interface(tmp_path, port)  # no server yet
    closing.append(iface)
    sent: list[bytes] = []
    send = iface._link.broadcast_weights

    def counted(data: bytes) -> None:
        sent.append(bytes(data))
        send(data)

    iface._link.broadcast_weights = counted
    actor = JsonActor(CountingEnv().observation_space, CountingEnv().action_space)
    actor.bias = 0.5
    iface.broadcast_model(actor)
    server = Child(tmp_path, "server", port=port)
    children.append(server)
    server.line()
    w = worker(tmp_path, port, "w")
    closing.append(w)
    assert w.update_actor_weights(verbose=False, blocking=True) == 1 and w.actor.bias == 0.5
    wait_for(lambda: iface.connections == 1, what="the trainer to see its first connection")
    assert len(sent) == 1

    server.kill()
    wait_for(lambda: not iface.connected, what="the trainer to see the server gone")
    restarted = Child(tmp_path, "server", port=port)
    children.append(restarted)
    restarted.line()
    wait_for(lambda: iface.connections == 2, timeout=30, what="the trainer to see its second connection")
    assert len(sent) == 2 and sent[1] == sent[0]  # the restarted server has no weights: the same again
    assert w.update_actor_weights(verbose=False, blocking=True) == 1 and w.actor.bias == 0.5


def test_trainer_killed_and_restarted_resumes_from_checkpoint_without_losing_samples(
    tmp_path, port_factory, closing, children
):
    port = port_factory()
    closing.append(Server(port=port, password=PW, security=None))
    w = worker(tmp_path, port, "w")
    closing.append(w)
    log, ckpt = tmp_path / "log.jsonl", tmp_path / "ckpt.json"
    args = dict(port=port, log=str(log), checkpoint=str(ckpt), model=str(tmp_path / "t.json"))
    first = Child(tmp_path, "trainer", **args)
    children.append(first)
    first.line()
    w.collect_train_episode()
    w.send_and_clear_buffer()
    assert w.update_actor_weights(verbose=False, blocking=True) == 1 and w.actor.bias == 1.0  # epoch 1 done
    wait_for(
        lambda: ckpt.exists() and json.loads(ckpt.read_text())["epoch"] == 1, what="the epoch-1 checkpoint"
    )
    first.kill()
    wait_for(
        lambda: (
            relay_connections(port).count("ESTABLISHED") == 1 and "CLOSE_WAIT" not in relay_connections(port)
        ),
        what="the server to close the killed trainer's connection",
    )
    w.collect_train_episode()  # sent while no trainer is connected: the server keeps it
    w.send_and_clear_buffer()
    second = Child(tmp_path, "trainer", **args)
    children.append(second)
    assert second.line()["epoch"] == 1  # resumed, not restarted from scratch
    # the resumed trainer re-broadcasts its weights, then finishes epoch 2 with the kept samples
    biases = set()
    wait_for(
        lambda: (w.update_actor_weights(verbose=False) and biases.add(w.actor.bias)) or 2.0 in biases,
        timeout=20,
        what="the resumed trainer's epoch-2 weights",
    )
    entries = read_log(log)
    assert sorted(s for e in entries if e["epoch"] == 1 for s in e["seqs"][str(w.source_id)]) == list(
        range(11, 22)
    )
    assert sorted(s for e in entries for s in e["seqs"][str(w.source_id)]) == list(range(22))


def test_tls_with_fresh_credentials(tmp_path, port_factory, closing):
    from tmrl.transport import ensure_credentials

    keys = tmp_path / "credentials"
    ensure_credentials(keys)
    port = port_factory()
    closing.append(Server(port=port, password=PW, security="TLS", keys_dir=str(keys)))
    iface = TrainerInterface(
        server_ip="127.0.0.1",
        server_port=port,
        password=PW,
        security="TLS",
        keys_dir=str(keys),
        model_path=str(tmp_path / "t.json"),
    )
    w = RolloutWorker(
        env_cls=CountingEnv,
        actor_module_cls=JsonActor,
        server_ip="127.0.0.1",
        server_port=port,
        password=PW,
        security="TLS",
        keys_dir=str(keys),
        model_path=str(tmp_path / "w.json"),
        model_history=0,
        max_samples_per_episode=4,
    )
    closing.extend([iface, w])
    w.collect_train_episode()
    w.send_and_clear_buffer()
    assert sorted(g[1] for g in drain(iface, 5)) == list(range(5))
    actor = JsonActor(CountingEnv().observation_space, CountingEnv().action_space)
    actor.bias = 0.125
    iface.broadcast_model(actor)
    assert w.update_actor_weights(verbose=False, blocking=True) == 1 and w.actor.bias == 0.125


def test_real_sac_stack_trains_broadcasts_safetensors_and_resumes_from_checkpoint(
    tmp_path, port_factory, closing
):
    from tmrl.algorithms.sac import SACAgent
    from tmrl.envs import GenericGymEnv
    from tmrl.memory import GenericTorchMemory
    from tmrl.models import MLPActorCritic, SquashedGaussianMLPActor
    from tmrl.training_offline import TorchTrainingOffline
    from tmrl.util import partial

    port = port_factory()
    closing.append(Server(port=port, password=PW, security=None))
    env = gymnasium.make("Pendulum-v1")

    def training(epochs: int):
        return partial(
            TorchTrainingOffline,
            env_cls=(env.observation_space, env.action_space),
            memory_cls=partial(GenericTorchMemory, memory_size=1000, batch_size=16),
            training_agent_cls=partial(SACAgent, model_cls=partial(MLPActorCritic, hidden_sizes=(16, 16))),
            epochs=epochs,
            rounds=1,
            steps=10,
            update_buffer_interval=5,
            update_model_interval=5,
            max_training_steps_per_env_step=10.0,
            start_training=50,
            sleep_between_buffer_retrieval_attempts=0.01,
            device="cpu",
        )

    w = RolloutWorker(
        env_cls=partial(GenericGymEnv, id="Pendulum-v1"),
        actor_module_cls=partial(SquashedGaussianMLPActor, hidden_sizes=(16, 16)),
        server_ip="127.0.0.1",
        server_port=port,
        password=PW,
        security=None,
        model_path=str(tmp_path / "worker.tmod"),
        model_history=0,
        max_samples_per_episode=60,
    )
    closing.append(w)
    w.collect_train_episode()
    w.send_and_clear_buffer()
    ckpt = tmp_path / "checkpoint"
    trainer = Trainer(
        training_cls=training(1),
        server_ip="127.0.0.1",
        server_port=port,
        password=PW,
        security=None,
        model_path=str(tmp_path / "trainer.tmod"),
        checkpoint_path=str(ckpt),
    )
    rounds: list[tuple[int, int]] = []
    trainer.add_callback(lambda m: rounds.append((m.epoch, m.total_updates)))  # a library script's hook
    trainer.run()
    assert trainer.run_instance.epoch == 1 and trainer.checkpoint_exists()
    assert rounds and rounds[-1] == (0, trainer.run_instance.total_updates)
    wait_until_acting_with(w, trainer.run_instance.agent.get_actor().state_dict())
    resumed = Trainer(
        training_cls=training(2),
        server_ip="127.0.0.1",
        server_port=port,
        password=PW,
        security=None,
        model_path=str(tmp_path / "trainer.tmod"),
        checkpoint_path=str(ckpt),
    )
    resumed.add_callback(lambda m: rounds.append((m.epoch, m.total_updates)))
    resumed.run()
    assert resumed.run_instance.epoch == 2
    assert rounds[-1] == (1, 20)  # the callback reached the training loop resumed from the checkpoint
    assert resumed.run_instance.total_samples == 61  # the memory came back with the checkpoint
    assert resumed.run_instance.total_updates == 20


def test_run_with_wandb_without_wandb_names_the_extra(tmp_path, port_factory, monkeypatch):
    from tmrl.errors import UserError

    monkeypatch.setitem(sys.modules, "wandb", None)  # as if it were not installed
    trainer = Trainer(
        training_cls=lambda: None,
        server_ip="127.0.0.1",
        server_port=port_factory(),
        password=PW,
        security=None,
        model_path=str(tmp_path / "t.json"),
        checkpoint_path=None,
    )
    try:
        with pytest.raises(UserError, match=r"pip install \"\.\[wandb\]\""):
            trainer.run_with_wandb(entity="e", project="p", run_id="r")
    finally:
        trainer.interface.close()


@pytest.mark.posix  # Ctrl-C as SIGINT, and SIGTERM as a clean stop (Windows ends the process at once)
@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM])
def test_cli_server_exits_cleanly_on_ctrl_c_and_frees_port(
    tmp_path, port_factory, _isolated_data_folder, sig
):
    port = port_factory()
    env = dict(os.environ, TMRL_CONFIG_OVERRIDE=json.dumps({"PORT": port, "TLS": False, "PASSWORD": PW}))
    proc = subprocess.Popen(
        [sys.executable, "-m", "tmrl", "--server"],
        env=env,
        stderr=subprocess.PIPE,
        stdout=subprocess.DEVNULL,
        cwd=str(tmp_path),
    )
    lines: list[str] = []
    reader = threading.Thread(
        target=lambda: lines.extend(ln.decode().rstrip() for ln in proc.stderr), daemon=True
    )
    reader.start()
    try:
        wait_for(
            lambda: proc.poll() is not None or any("server running on port" in ln for ln in lines),
            timeout=30,
            what="the server to run",
        )
        assert proc.poll() is None
        proc.send_signal(sig)
        proc.wait(20)
        reader.join(10)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    name, code = ("Ctrl-C", 130) if sig == signal.SIGINT else ("SIGTERM", 143)
    assert proc.returncode == code
    # exactly one line about the stop, naming the signal (the relay may still log its own shutdown)
    assert [ln for ln in lines if "stopped" in ln or "interrupted" in ln] == [f"tmrl: server stopped ({name})"]
    assert not any("Traceback" in ln for ln in lines)
    with socket.socket() as s:  # no child kept the port
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        s.bind(("127.0.0.1", port))


def relay_listening(port: int) -> bool:
    try:
        with socket.create_connection(("127.0.0.1", port), timeout=0.5):
            return True
    except OSError:
        return False


# ------------------------------------------------------------------------------------------------
# subprocess roles: python tests/test_networking_e2e.py ROLE JSON_ARGS


def _say(obj: dict) -> None:
    print(json.dumps(obj), flush=True)


def _child(role: str, args: dict) -> None:
    port = args["port"]
    if role == "server":
        server = Server(port=port, password=PW, security=None)
        _say({"ready": True})
        while server.running:
            time.sleep(0.5)
    elif role == "worker":
        w = RolloutWorker(
            env_cls=CountingEnv,
            actor_module_cls=JsonActor,
            server_ip="127.0.0.1",
            server_port=port,
            password=PW,
            security=None,
            model_path=args["model"],
            model_history=0,
            max_samples_per_episode=10,
        )
        _say({"source": w.source_id})
        if args.get("wait_weights"):
            w.update_actor_weights(verbose=False, blocking=True)
            _say({"bias": w.actor.bias})
        w.run(test_episode_interval=0, nb_episodes=args["episodes"], verbose=False)
        w.close()
        while True:
            time.sleep(1)
    elif role == "trainer":
        trainer = Trainer(
            training_cls=lambda: RecordingTraining(args["log"], epochs=1000, samples_per_epoch=11),
            server_ip="127.0.0.1",
            server_port=port,
            password=PW,
            security=None,
            model_path=args["model"],
            checkpoint_path=args["checkpoint"],
            dump_run_instance_fn=RecordingTraining.dump,
            load_run_instance_fn=RecordingTraining.load,
        )
        run = trainer._load_or_create()
        _say({"epoch": run.epoch})
        while run.epoch < run.epochs:
            run.run_epoch(interface=trainer.interface)
            trainer.dump_run_instance_fn(run, trainer.checkpoint_path)


if __name__ == "__main__":
    _child(sys.argv[1], json.loads(sys.argv[2]))


# ------------------------------------------------------------------------------------------------
# pacing: workers of a fast environment keep to the trainer's budget of samples


def _paced_training(limit: float, start: int = 50) -> Any:
    from tmrl.algorithms.sac import SACAgent
    from tmrl.envs import GenericGymEnv
    from tmrl.memory import GenericTorchMemory
    from tmrl.models import MLPActorCritic
    from tmrl.training_offline import TorchTrainingOffline
    from tmrl.util import partial

    return partial(
        TorchTrainingOffline, env_cls=partial(GenericGymEnv, id="Pendulum-v1"),
        memory_cls=partial(GenericTorchMemory, memory_size=10_000, batch_size=16),
        training_agent_cls=partial(SACAgent, model_cls=partial(MLPActorCritic, hidden_sizes=(16, 16))),
        epochs=1, rounds=3, steps=40, update_model_interval=5, update_buffer_interval=1,
        max_training_steps_per_env_step=1.0, start_training=start, sleep_between_buffer_retrieval_attempts=0.01,
        device="cpu", max_env_steps_per_training_step=limit)


def test_a_fast_worker_keeps_to_the_trainers_budget_of_samples(tmp_path, port_factory, closing):
    from tmrl.envs import GenericGymEnv
    from tmrl.models import SquashedGaussianMLPActor
    from tmrl.util import partial

    port = port_factory()
    closing.append(Server(port=port, password=PW, security=None))
    trainer = Trainer(training_cls=_paced_training(limit=2.0), server_ip="127.0.0.1", server_port=port, password=PW,
                      security=None, model_path=str(tmp_path / "t.tmod"), checkpoint_path=None,
                      obs_preprocessor=None, sample_compressor=None)
    w = RolloutWorker(env_cls=partial(GenericGymEnv, id="Pendulum-v1"),
                      actor_module_cls=partial(SquashedGaussianMLPActor, hidden_sizes=(16, 16)),
                      server_ip="127.0.0.1", server_port=port, password=PW, security=None,
                      model_path=str(tmp_path / "w.tmod"), max_samples_per_episode=200)
    closing.append(w)
    threading.Thread(target=w.run, daemon=True).start()
    trainer.run()  # 120 updates; returns: the worker and the trainer never waited for each other forever
    run = trainer.run_instance
    assert run.total_updates == 120
    # Unpaced, Pendulum runs thousands of steps a second; here the trainer holds at most what its
    # last budget allowed: 2 samples per update plus the 50 it starts with (and one reset sample).
    assert run.total_samples <= 2 * run.total_updates + 50 + 2, run.total_samples
    assert w.pace.active and w.pace.limit == 2.0


def test_a_real_time_worker_pauses_for_the_budget_only_between_episodes(tmp_path, port_factory, closing):
    """A real-time environment's clock must not stop mid-episode: with the budget used up, the
    worker finishes its episode before it waits for new weights."""
    import gymnasium
    from gymnasium.envs.classic_control.pendulum import PendulumEnv

    from tmrl.envs import GenericGymEnv
    from tmrl.models import SquashedGaussianMLPActor
    from tmrl.util import partial

    class RealTimePendulum(PendulumEnv):
        """Pendulum that looks like an rtgym environment (it has benchmarks()) and counts steps."""

        steps = 0

        def reset(self, **kw):
            RealTimePendulum.steps = 0
            return super().reset(**kw)

        def step(self, action):
            RealTimePendulum.steps += 1
            return super().step(action)

        def benchmarks(self):
            return {}

    env_id = "TmrlTest/RealTimePendulum-v0"
    if env_id not in gymnasium.registry:
        gymnasium.register(env_id, entry_point=RealTimePendulum, max_episode_steps=50)
    port = port_factory()
    closing.append(Server(port=port, password=PW, security=None))
    trainer = Trainer(training_cls=_paced_training(limit=2.0), server_ip="127.0.0.1", server_port=port, password=PW,
                      security=None, model_path=str(tmp_path / "t.tmod"), checkpoint_path=None,
                      obs_preprocessor=None, sample_compressor=None)
    w = RolloutWorker(env_cls=partial(GenericGymEnv, id=env_id),
                      actor_module_cls=partial(SquashedGaussianMLPActor, hidden_sizes=(16, 16)),
                      server_ip="127.0.0.1", server_port=port, password=PW, security=None,
                      model_path=str(tmp_path / "w.tmod"), max_samples_per_episode=50)
    closing.append(w)
    waits_at: list[int] = []
    update = w.update_actor_weights

    def recording_update(verbose=True, blocking=False):
        if blocking:
            waits_at.append(RealTimePendulum.steps)
        return update(verbose=verbose, blocking=blocking)

    w.update_actor_weights = recording_update
    threading.Thread(target=w.run, daemon=True).start()
    trainer.run()
    assert w.pace.active
    # 120 updates at 2 samples each from 50 samples: the worker ran ahead of its budget, so it
    # waited, and only ever at the end of an episode (step 50 of 50)
    assert len(waits_at) > 1 and set(waits_at) == {50}, waits_at


def test_a_worker_closed_from_another_thread_stops_its_run(tmp_path, port_factory, closing):
    from tmrl.envs import GenericGymEnv
    from tmrl.models import SquashedGaussianMLPActor
    from tmrl.util import partial

    import gymnasium

    env_id = "TmrlTest/LongPendulum-v0"
    if env_id not in gymnasium.registry:
        gymnasium.register(env_id, entry_point="gymnasium.envs.classic_control.pendulum:PendulumEnv",
                           max_episode_steps=100_000)
    port = port_factory()
    closing.append(Server(port=port, password=PW, security=None))
    w = RolloutWorker(env_cls=partial(GenericGymEnv, id=env_id),
                      actor_module_cls=partial(SquashedGaussianMLPActor, hidden_sizes=(16, 16)),
                      server_ip="127.0.0.1", server_port=port, password=PW, security=None,
                      model_path=str(tmp_path / "w.tmod"), max_samples_per_episode=100_000)
    failures: list[BaseException] = []

    def run():
        try:
            w.run()
        except BaseException as e:  # noqa: BLE001 - the test reports it
            failures.append(e)

    thread = threading.Thread(target=run, daemon=True)
    thread.start()
    deadline = time.monotonic() + 30
    while len(w.buffer) < 500 and time.monotonic() < deadline:
        time.sleep(0.01)  # polling the worker's own counter: mid-episode, nothing to await
    assert len(w.buffer) >= 500, "the worker never got going"
    w.close()  # mid-episode (episodes of 100,000 steps)
    thread.join(10)
    assert not thread.is_alive() and not failures, failures


def test_pace_takes_the_trainers_fields_and_turns_off_without_them():
    from tmrl.networking import Pace

    pace = Pace()
    assert not pace.active and not pace.exhausted()
    pace.update({"pace_limit": 3.0, "pace_budget": 1060, "pace_received": 1000})
    assert pace.active and pace.allowance == 60
    pace.count(59)
    assert not pace.exhausted()
    pace.count(1)
    assert pace.exhausted()
    pace.update({"pace_limit": 3.0, "pace_budget": 1120, "pace_received": 1060})  # new weights: a new budget
    assert pace.collected == 0 and not pace.exhausted()
    for bad in ({}, {"pace_limit": float("nan"), "pace_budget": 1, "pace_received": 0},
                {"pace_limit": 3.0, "pace_budget": -1, "pace_received": 0}, {"pace_limit": "x"}):
        pace.update(bad)  # a trainer without pacing, or a malformed header: no pacing
        assert not pace.active and not pace.exhausted()


def test_the_trainer_budget_and_its_broadcast_when_it_waits():
    run = _paced_training(limit=3.0, start=40)()
    assert run.pace() == {"pace_limit": 3.0, "pace_budget": 40, "pace_received": 0}
    run.total_updates, run.total_samples = 20, 90
    assert run.pace() == {"pace_limit": 3.0, "pace_budget": 100, "pace_received": 90}
    sent = []

    class Waiting:
        def retrieve_buffer(self):
            from tmrl.networking import Buffer

            run.stop()  # nothing arrives: stop after the first wait
            return Buffer()

        def broadcast_model(self, actor):
            sent.append(run.total_updates)

    run.total_samples = 10  # 20 updates > 10 samples: the trainer must wait
    assert run.check_ratio(Waiting()) is False and sent == [20]  # workers get the current count first
    assert _paced_training(limit=0.0)().pace() is None
