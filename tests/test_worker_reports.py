"""What a worker tells its user (issue 40).

- One count of samples: the number of samples a worker reports sent, episode by episode, adds up
  to what the trainer received and stored, even when the trainer's pace makes the worker send in
  the middle of its episodes (the simulator's fast mode does so all the time). A real server, a
  real trainer (SAC on Pendulum, paced at 2 samples per update) and a real worker in this process;
  the trainer goes on until the worker's four episodes have all arrived.
- A worker waiting for the trainer's first weights says, every so often, why nothing happens:
  no server to connect to, or a server but no trainer.
"""

from __future__ import annotations

import logging
import threading
import time
from typing import Any

import pytest

from tmrl.distributed import RolloutWorker, Server, Trainer
from tmrl.distributed._common import LOGGER_NAME  # the worker's log ("tmrl.networking", as in tmrl 0.7)
from tmrl.training_offline import TrainingCallback

pytestmark = pytest.mark.timeout(180)

PW = "sample-count-test"
EPISODES, STEPS = 4, 50  # each episode: its reset sample and 50 steps


def _paced_training(limit: float, start: int) -> Any:
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
        epochs=1, rounds=2, steps=20, update_model_interval=5, update_buffer_interval=1,
        max_training_steps_per_env_step=10.0, start_training=start, sleep_between_buffer_retrieval_attempts=0.01,
        device="cpu", max_env_steps_per_training_step=limit)


class UntilAllArrived(TrainingCallback):
    """Adds an epoch while the worker runs or the trainer has not yet received all it sent."""

    def __init__(self, worker: RolloutWorker, done: threading.Event, deadline: float) -> None:
        self.worker, self.done, self.deadline = worker, done, deadline

    def on_epoch_end(self, training: Any, rows: list) -> None:
        complete = self.done.is_set() and training.total_samples >= self.worker.samples_sent
        if not complete and time.monotonic() < self.deadline:
            training.epochs = training.epoch + 2  # one more epoch


def test_the_samples_a_worker_reports_sent_are_the_samples_the_trainer_stored(tmp_path, port_factory, caplog):
    from tmrl.envs import GenericGymEnv
    from tmrl.models import SquashedGaussianMLPActor
    from tmrl.util import partial

    caplog.set_level(logging.INFO, logger="tmrl.metrics")
    caplog.set_level(logging.DEBUG, logger=LOGGER_NAME)  # last: it sets the capture's level too
    port = port_factory()
    server = Server(port=port, password=PW, security=None)
    worker = None
    try:
        trainer = Trainer(training_cls=_paced_training(limit=2.0, start=20), server_ip="127.0.0.1", server_port=port,
                          password=PW, security=None, model_path=str(tmp_path / "t.tmod"), checkpoint_path=None,
                          obs_preprocessor=None, sample_compressor=None)
        worker = RolloutWorker(env_cls=partial(GenericGymEnv, id="Pendulum-v1"),
                               actor_module_cls=partial(SquashedGaussianMLPActor, hidden_sizes=(16, 16)),
                               server_ip="127.0.0.1", server_port=port, password=PW, security=None,
                               model_path=str(tmp_path / "w.tmod"), max_samples_per_episode=STEPS)
        done = threading.Event()
        failures: list[BaseException] = []

        def work() -> None:
            try:
                worker.run(nb_episodes=EPISODES)
            except BaseException as err:  # noqa: BLE001 (reported by the test)
                failures.append(err)
            finally:
                done.set()

        trainer.add_callback(UntilAllArrived(worker, done, time.monotonic() + 120))
        threading.Thread(target=work, daemon=True).start()
        trainer.run()
        assert done.wait(30) and not failures, failures
        run = trainer.run_instance
    finally:
        if worker is not None:
            worker.close()
        server.stop()

    sent = EPISODES * (STEPS + 1)
    assert worker.samples_sent == sent
    # The pace made the worker send in the middle of its episodes: more batches than episodes.
    assert worker._seq > EPISODES, "the scenario needs mid-episode sends"
    reported = [r.args[4] for r in caplog.records
                if r.name == LOGGER_NAME and r.levelno == logging.DEBUG
                and "samples sent" in r.msg and "episode" in r.msg]
    assert len(reported) == EPISODES
    assert reported == [STEPS + 1] * EPISODES, reported
    assert run.total_samples == sum(reported) == sent  # what the trainer received and stored
    assert trainer.interface.received_samples == sent
    # the trainer's round line says the same number
    rounds = [r.getMessage() for r in caplog.records if r.name == "tmrl.metrics" and " round " in r.getMessage()]
    assert rounds and f"| samples {sent} memory " in rounds[-1], rounds[-3:]


@pytest.mark.parametrize("server", [False, True], ids=["no server", "no trainer"])
def test_a_worker_waiting_for_its_first_weights_says_what_is_missing(server, tmp_path, port_factory, caplog,
                                                                      monkeypatch):
    from tmrl.distributed import worker as worker_module
    from tmrl.envs import GenericGymEnv
    from tmrl.models import SquashedGaussianMLPActor
    from tmrl.util import partial

    monkeypatch.setattr(worker_module, "WAITING_NOTE_INTERVAL", 0.5)
    caplog.set_level(logging.INFO, logger=LOGGER_NAME)
    port = port_factory()
    relay = Server(port=port, password=PW, security=None) if server else None
    worker = RolloutWorker(env_cls=partial(GenericGymEnv, id="Pendulum-v1"),
                           actor_module_cls=partial(SquashedGaussianMLPActor, hidden_sizes=(16, 16)),
                           server_ip="127.0.0.1", server_port=port, password=PW, security=None,
                           model_path=str(tmp_path / "w.tmod"), max_samples_per_episode=10)
    thread = threading.Thread(target=worker.run, kwargs={"nb_episodes": 2}, daemon=True)
    try:
        if server:
            assert worker.wait_connected(60)
        thread.start()
        expected = "connected to the server, no trainer yet" if server else "no connection to the server at 127.0.0.1"
        deadline = time.monotonic() + 60
        while not any(expected in r.getMessage() for r in caplog.records):
            assert time.monotonic() < deadline, [r.getMessage() for r in caplog.records]
            time.sleep(0.05)
        notes = [r for r in caplog.records if "still waiting for the trainer's first weights" in r.getMessage()]
        assert notes and all(r.levelno == logging.WARNING for r in notes)
        assert ("python -m tmrl --trainer" if server else "python -m tmrl --server") in notes[-1].getMessage()
    finally:
        worker.close()
        thread.join(10)
        if relay is not None:
            relay.stop()
    assert not thread.is_alive()
