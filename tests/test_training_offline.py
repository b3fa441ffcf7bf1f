"""Tests of tmrl.training_offline: the loop's schedule, with an in-process interface and a tiny agent."""

from __future__ import annotations

import csv
import logging
import threading
from collections import deque

import gymnasium
import numpy as np
import pytest
import torch

from tmrl.errors import UserError
from tmrl.memory import GenericTorchMemory
from tmrl.metrics import MetricsLogger
from tmrl.training_offline import TorchTrainingOffline, TrainingOffline
from tmrl.util import partial

OBS_SPACE = gymnasium.spaces.Tuple((gymnasium.spaces.Box(-1, 1, (3,), np.float32),))
ACT_SPACE = gymnasium.spaces.Box(-1, 1, (2,), np.float32)


class Buf:
    def __init__(self, samples=()):
        self.memory = list(samples)
        self.sources = None
        self.stat_train_return = 1.5
        self.stat_test_return = 2.5
        self.stat_train_steps = 10
        self.stat_test_steps = 11

    def __len__(self):
        return len(self.memory)


def make_samples(n: int, start: int = 0, episode_len: int = 50) -> list[tuple]:
    out = []
    for i in range(start, start + n):
        t = i % episode_len
        act = None if t == 0 else np.full(2, t / episode_len, np.float32)
        out.append((act, (np.full(3, t / episode_len, np.float32),), float(t), t == episode_len - 1, False, {}))
    return out


class FakeInterface:
    """In-process stand-in for the networking trainer interface: hands out queued buffers."""

    def __init__(self, buffers=(), endless=0, on_retrieve=None):
        self.queue = deque(buffers)
        self.endless = endless  # samples per buffer once the queue is empty (0: empty buffers)
        self.produced = sum(len(b) for b in buffers)
        self.retrieves = 0
        self.broadcasts: list[int] = []
        self.on_retrieve = on_retrieve
        self.training = None

    def retrieve_buffer(self):
        self.retrieves += 1
        if self.on_retrieve is not None:
            self.on_retrieve(self)
        if self.queue:
            return self.queue.popleft()
        buf = Buf(make_samples(self.endless, start=self.produced))
        self.produced += self.endless
        return buf

    def broadcast_model(self, actor):
        assert isinstance(actor, torch.nn.Module)
        self.broadcasts.append(self.training.total_updates if self.training else -1)


class TinyAgent:
    """A one-layer regression 'agent' with an optimizer, recording the ratio it trained at."""

    training = None  # set by tests that check the ratio

    def __init__(self, observation_space, action_space, device):
        self.device = device
        obs_dim = sum(int(np.prod(s.shape)) for s in observation_space)
        self.model = torch.nn.Linear(obs_dim + action_space.shape[0], 1)
        self.optimizer = torch.optim.Adam(self.model.parameters(), lr=1e-2)
        self.seen: list[tuple[int, int]] = []

    def train(self, batch):
        o, a, r, o2, d, t = batch
        assert r.shape == d.shape == t.shape == (a.shape[0],)
        if TinyAgent.training is not None:
            self.seen.append((TinyAgent.training.total_updates, TinyAgent.training.total_samples))
        loss = ((self.model(torch.cat([*o, a], -1)).squeeze(-1) - r) ** 2).mean()
        self.optimizer.zero_grad()
        loss.backward()
        self.optimizer.step()
        return {"loss_critic": loss.detach(), "loss_actor": 0.5, "entropy_coef": None}

    def get_actor(self):
        return self.model

    def state_dict(self):
        return {"model": self.model.state_dict(), "optimizer": self.optimizer.state_dict()}

    def load_state_dict(self, state):
        self.model.load_state_dict(state["model"])
        self.optimizer.load_state_dict(state["optimizer"])


def make_training(**kwargs):
    defaults = dict(
        env_cls=(OBS_SPACE, ACT_SPACE),
        memory_cls=partial(GenericTorchMemory, memory_size=1000, batch_size=8),
        training_agent_cls=TinyAgent,
        epochs=3,
        rounds=2,
        steps=10,
        update_model_interval=4,
        update_buffer_interval=5,
        max_training_steps_per_env_step=1000.0,
        sleep_between_buffer_retrieval_attempts=0.0,
        start_training=20,
        device="cpu",
    )
    defaults.update(kwargs)
    return TorchTrainingOffline(**defaults)


@pytest.fixture(autouse=True)
def _reset_tiny_agent():
    TinyAgent.training = None
    yield
    TinyAgent.training = None


def test_run_epoch_schedule():
    training = make_training()
    interface = FakeInterface([Buf(make_samples(10, start=10 * i)) for i in range(20)])
    interface.training = training
    stats = training.run_epoch(interface)
    assert training.epoch == 1 and training.total_updates == 20
    # two pulls to reach start_training=20, then one every update_buffer_interval=5 steps
    assert interface.retrieves == 2 + 4
    assert training.total_samples == 60
    assert interface.broadcasts == [4, 8, 12, 16, 20]
    assert [row["round"] for row in stats] == [0, 1] and all(row["epoch"] == 0 for row in stats)
    row = stats[-1]
    assert row["total_updates"] == 20 and row["memory_len"] == len(training.memory)
    assert row["return_train"] == 1.5 and row["return_test"] == 2.5
    assert isinstance(row["loss_critic"], float) and row["loss_actor"] == 0.5
    assert "entropy_coef" not in row  # None values are skipped
    assert row["updates_per_second"] > 0 and row["samples_per_second"] >= 0


def test_training_waits_for_the_sample_ratio():
    training = make_training(max_training_steps_per_env_step=0.5, start_training=0, steps=25,
                             update_buffer_interval=1)
    TinyAgent.training = training
    interface = FakeInterface(endless=3)
    training.run_epoch(interface)
    seen = training.agent.seen
    assert len(seen) == 50
    assert all(updates <= 0.5 * samples for updates, samples in seen)


@pytest.mark.timeout(60)
def test_stop_interrupts_waiting():
    training = make_training(sleep_between_buffer_retrieval_attempts=600.0)
    first_retrieve = threading.Event()
    stopper = threading.Thread(target=lambda: (first_retrieve.wait(), training.stop()))
    stopper.start()
    # The loop pulls once, finds too few samples and sleeps 600 s: stop() from the other thread
    # must end that wait (the test would time out otherwise).
    interface = FakeInterface(on_retrieve=lambda itf: first_retrieve.set())
    assert training.run_epoch(interface) == []
    stopper.join()
    assert training.stopped and training.epoch == 0 and interface.retrieves == 1


def test_max_wait_raises_timeout():
    training = make_training(sleep_between_buffer_retrieval_attempts=0.001)
    training.max_wait_s = 0.0
    with pytest.raises(TimeoutError, match="are the workers running"):
        training.run_epoch(FakeInterface())


def test_scheduler_env_class_and_device(caplog):
    calls = []

    class SpacesEnv(gymnasium.Env):
        observation_space = OBS_SPACE
        action_space = ACT_SPACE

    training = make_training(env_cls=SpacesEnv, device=None, agent_scheduler=lambda a, e: calls.append((a, e)))
    assert training.device == ("cuda" if torch.cuda.is_available() else "cpu")
    interface = FakeInterface(endless=10)
    with caplog.at_level(logging.INFO, logger="tmrl.metrics"):
        training.run_epoch(interface)
        training.run_epoch(interface)
    assert calls == [(training.agent, 0), (training.agent, 1)]
    assert any("epoch 1 round 1/2" in r.getMessage() and "upd/s" in r.getMessage() for r in caplog.records)


def test_missing_classes_are_user_errors():
    with pytest.raises(UserError, match="memory_cls"):
        TrainingOffline(env_cls=(OBS_SPACE, ACT_SPACE), training_agent_cls=TinyAgent)
    with pytest.raises(UserError, match="steps"):
        make_training(steps=0)


def test_rows_go_to_the_metrics_logger(tmp_path):
    training = make_training()
    metrics = MetricsLogger("run1", folder=tmp_path, tensorboard=False)
    assert not (tmp_path / "logs").exists()
    training.run_epoch(FakeInterface(endless=10), logger=metrics)
    with open(metrics.csv_path, newline="") as f:
        rows = list(csv.DictReader(f))
    assert [r["round"] for r in rows] == ["0", "1"]
    assert float(rows[1]["total_updates"]) == 20


def test_with_the_real_sac_agent():
    sac = pytest.importorskip("tmrl.algorithms.sac")
    training = make_training(training_agent_cls=partial(sac.SACAgent), rounds=1, steps=5)
    stats = training.run_epoch(FakeInterface(endless=10))
    assert training.total_updates == 5
    assert np.isfinite(stats[0]["loss_critic"]) and np.isfinite(stats[0]["loss_actor"])


# --- seams: rounds as data, callbacks, profiling ----------------------------------------------------


def test_a_round_is_a_function_returning_its_metrics():
    from tmrl.training_offline import RoundMetrics

    training = make_training()
    interface = FakeInterface(endless=10)
    interface.training = training
    result = training.run_round(interface, rnd=0)
    assert isinstance(result, RoundMetrics) and not result.stopped
    assert result.updates == 10 and result.total_updates == 10 and result.round == 0
    assert result.agent["loss_actor"] == 0.5 and "entropy_coef" not in result.agent  # None values skipped
    row = result.as_row()
    assert row["updates_per_second"] == pytest.approx(10 / result.round_time)
    # the epoch's rows are the rounds' rows, same keys in the same order
    epoch_rows = make_training().run_epoch(FakeInterface(endless=10))
    assert list(epoch_rows[0]) == list(row)


def test_callbacks_see_every_round_and_can_end_the_epoch():
    from tmrl.training_offline import TrainingCallback

    events: list[tuple] = []

    class Recorder(TrainingCallback):
        def on_epoch_start(self, training):
            events.append(("start", training.epoch))

        def on_round_end(self, training, metrics):
            events.append(("round", metrics.round, metrics.total_updates))

        def on_epoch_end(self, training, rows):
            events.append(("end", len(rows)))

    training = make_training()
    training.add_callback(Recorder())
    seen = []
    training.add_callback(lambda m: seen.append(m.round))  # a plain function: called after each round
    training.run_epoch(FakeInterface(endless=10))
    assert events == [("start", 0), ("round", 0, 10), ("round", 1, 20), ("end", 2)]
    assert seen == [0, 1] and training.epoch == 1

    # a callback that returns False ends the epoch after that round, uncounted (like stop())
    training.add_callback(lambda m: False if m.round == 0 else None)
    rows = training.run_epoch(FakeInterface(endless=10))
    assert len(rows) == 1 and training.epoch == 1 and training.total_updates == 30


def test_profiling_is_a_context_manager_that_logs_only_when_enabled(caplog):
    from tmrl.training_offline import profiled

    caplog.set_level(logging.INFO, logger="tmrl.training_offline")
    with profiled(False, "nothing"):
        sum(range(1000))
    assert not any("profile of" in r.getMessage() for r in caplog.records)
    with profiled(True, "the block"):
        sorted(range(1000), key=lambda x: -x)
    (line,) = [r.getMessage() for r in caplog.records if "profile of the block" in r.getMessage()]
    assert "cumulative" in line


# --- a trainer that cannot keep the ratio says so ---------------------------------------------------


def _behind_rounds(caplog: pytest.LogCaptureFixture, *, rounds: int, steps: int, start_training: int, update_buffer_interval: int,
                   endless: int) -> list[dict]:
    """The round rows of one epoch at 4 updates asked per sample, the workers sending ``endless``
    samples per pull, with the trainer's warnings captured in ``caplog``."""
    training = make_training(max_training_steps_per_env_step=4.0, rounds=rounds, steps=steps,
                             start_training=start_training, update_buffer_interval=update_buffer_interval)
    interface = FakeInterface([], endless=endless)
    interface.training = training
    with caplog.at_level(logging.WARNING, logger="tmrl.training_offline"):
        return training.run_epoch(interface)


def test_a_trainer_behind_the_asked_ratio_says_so_once_in_the_log_and_in_every_round_line(caplog):
    """Workers that send ten samples per update to a setting that asks four updates per sample:
    the trainer never waits, so each round is behind, the round line says by how much, and the
    log warns once (not once per round)."""
    from tmrl.metrics import format_row

    rows = _behind_rounds(caplog, rounds=3, steps=10, start_training=0, update_buffer_interval=1, endless=10)
    assert len(rows) == 3
    for row in rows:
        assert row["behind"] is True and row["updates_per_sample_asked"] == 4.0
        assert row["updates_per_sample"] == pytest.approx(0.1, abs=0.02)
        assert f"behind: {row['updates_per_sample']:.2f} of 4 upd/smp" in format_row(row)
    warnings = [r.getMessage() for r in caplog.records if "behind" in r.getMessage()]
    assert len(warnings) == 1, warnings
    assert "4 asked" in warnings[0] and "MAX_TRAINING_STEPS_PER_ENVIRONMENT_STEP" in warnings[0]


def test_a_trainer_that_keeps_the_ratio_is_not_behind(caplog):
    """One sample per pull and four updates asked per sample: the ratio binds (the trainer waits
    for samples), so no round is behind, no line says so and nothing is logged."""
    from tmrl.metrics import format_row

    rows = _behind_rounds(caplog, rounds=4, steps=12, start_training=8, update_buffer_interval=100, endless=1)
    assert [row["behind"] for row in rows] == [False] * 4
    # the 8 samples before training allow 32 updates; from then on each sample arrives when the
    # ratio asks for it (the first round also holds the samples received before training started)
    fed = [row["updates_per_sample"] for row in rows[1:] if row["updates_per_sample"] is not None]
    assert fed and all(v == pytest.approx(4.0, rel=0.1) for v in fed), fed
    assert not any("behind" in format_row(row) for row in rows)
    assert not [r for r in caplog.records if "behind" in r.getMessage()]


def test_a_round_that_waited_for_samples_is_not_behind_even_when_they_came_in_a_burst(caplog):
    """Samples in bursts of 10, pulled only when the ratio of 4 binds: a round that waited for
    samples then received a burst it had no time to train on did few updates per sample, yet it
    kept up (it was the trainer that waited), so it is not behind."""
    rows = _behind_rounds(caplog, rounds=8, steps=12, start_training=8, update_buffer_interval=100, endless=10)
    burst = [row for row in rows if row["updates_per_sample"] is not None and row["updates_per_sample"] < 3.6]
    assert burst, rows  # a round did receive a burst it could not train through
    assert not any(row["behind"] for row in rows)
    assert not [r for r in caplog.records if "behind" in r.getMessage()]
