"""tmrl.networking without a network: Buffer, the column packing of samples, the spaces check and
the standalone RolloutWorker. The helpers at the top (a counting environment, a JSON actor, a
recording training class) are also used by tests/test_networking_e2e.py and by the subprocesses
it starts."""

from __future__ import annotations

import json
import math
import os
from pathlib import Path
from typing import Any

import gymnasium
import numpy as np
import pytest

from tmrl import wire
from tmrl.errors import UserError
from tmrl.networking import (
    Buffer,
    PayloadError,
    RolloutWorker,
    SpacesMismatchError,
    check_spaces,
    describe_spaces,
    pack_buffer,
    unpack_buffer,
)

# ------------------------------------------------------------------------------------------------
# helpers shared with the end-to-end tests


class CountingEnv(gymnasium.Env):
    """Obs: 3 floats; each reset and step puts a fresh sequence number in ``info["seq"]`` (and in
    ``obs[0]``), so that a receiver can tell exactly which samples arrived."""

    def __init__(self, obs_dim: int = 3, episode_length: int = 20):
        self.observation_space = gymnasium.spaces.Box(-np.inf, np.inf, (obs_dim,), np.float32)
        self.action_space = gymnasium.spaces.Box(-1.0, 1.0, (1,), np.float32)
        self.episode_length = episode_length
        self.seq = 0
        self.t = 0

    def _obs(self) -> np.ndarray:
        obs = np.zeros(self.observation_space.shape, np.float32)
        obs[0] = self.seq
        return obs

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        self.t = 0
        info = {"seq": self.seq}
        obs = self._obs()
        self.seq += 1
        return obs, info

    def step(self, action):
        self.t += 1
        info = {"seq": self.seq}
        obs = self._obs()
        self.seq += 1
        return obs, float(action[0]), self.t >= self.episode_length, False, info


class JsonActor:
    """A one-number policy (``bias``) saved as JSON: the tutorial's style of user actor. It has the
    ActorModule interface without inheriting it, so that the subprocesses of the end-to-end tests
    start without importing torch (seconds on a loaded machine)."""

    def __init__(self, observation_space: Any, action_space: Any):
        self.observation_space = observation_space
        self.action_space = action_space
        self.bias = 0.0

    def act_(self, obs: Any, test: bool = False) -> np.ndarray:
        return self.act(obs, test)

    def act(self, obs: Any, test: bool = False) -> np.ndarray:
        return np.array([self.bias], np.float32)

    def save(self, path: str | os.PathLike[str]) -> None:
        Path(path).write_text(json.dumps({"bias": self.bias}))

    def load(self, path: str | os.PathLike[str], device: Any) -> JsonActor:
        self.bias = json.loads(Path(path).read_text())["bias"]
        return self

    def to_device(self, device: Any) -> JsonActor:
        return self


class RecordingTraining:
    """A training class for the trainer seam: each epoch it collects samples until it has seen
    ``samples_per_epoch`` new ones, records their ``seq`` per worker in a JSON-lines log and
    broadcasts a JsonActor whose bias is the epoch number."""

    def __init__(
        self,
        log_path: str,
        epochs: int = 1000,
        samples_per_epoch: int = 20,
        obs_dim: int = 3,
        poll: float = 0.005,
    ):
        self.log_path = log_path
        self.epochs = epochs
        self.epoch = 0
        self.samples_per_epoch = samples_per_epoch
        self.obs_dim = obs_dim
        self.poll = poll
        self.stop = False  # set to end every remaining epoch at once
        env = CountingEnv(obs_dim)
        self.actor = JsonActor(env.observation_space, env.action_space)

    def run_epoch(self, interface: Any) -> list[dict]:
        import time

        got = 0
        with open(self.log_path, "a") as log:
            while got < self.samples_per_epoch and not self.stop:
                buf = interface.retrieve_buffer()
                if len(buf):
                    seqs: dict[str, list[int]] = {}
                    for sample, src in zip(buf.memory, buf.sources):
                        seqs.setdefault(str(src), []).append(int(sample[5]["seq"]))
                    log.write(
                        json.dumps({"epoch": self.epoch, "seqs": seqs, "ret": buf.stat_train_return}) + "\n"
                    )
                    log.flush()
                    got += len(buf)
                else:
                    time.sleep(self.poll)
        self.epoch += 1
        self.actor.bias = float(self.epoch)
        interface.broadcast_model(self.actor)
        return [{"epoch": self.epoch}]

    # checkpoint functions (JSON: the trainer's dump/load hooks)
    @staticmethod
    def dump(run: RecordingTraining, path: str) -> None:
        from tmrl.util import atomic_write_text

        atomic_write_text(
            path,
            json.dumps(
                {
                    "log_path": run.log_path,
                    "epochs": run.epochs,
                    "epoch": run.epoch,
                    "samples_per_epoch": run.samples_per_epoch,
                    "obs_dim": run.obs_dim,
                }
            ),
        )

    @staticmethod
    def load(path: str) -> RecordingTraining:
        d = json.loads(Path(path).read_text())
        run = RecordingTraining(d["log_path"], d["epochs"], d["samples_per_epoch"], d["obs_dim"])
        run.epoch = d["epoch"]
        run.actor.bias = float(run.epoch)
        return run


def read_log(path: str | os.PathLike[str]) -> list[dict]:
    p = Path(path)
    if not p.exists():
        return []
    return [json.loads(line) for line in p.read_text().splitlines() if line.strip()]


def received_seqs(path: str | os.PathLike[str]) -> dict[str, list[int]]:
    out: dict[str, list[int]] = {}
    for entry in read_log(path):
        for src, seqs in entry["seqs"].items():
            out.setdefault(src, []).extend(seqs)
    return out


def make_worker(tmp_path: Path, standalone: bool = True, obs_dim: int = 3, **kwargs: Any) -> RolloutWorker:
    return RolloutWorker(
        env_cls=lambda: CountingEnv(obs_dim),
        actor_module_cls=JsonActor,
        standalone=standalone,
        model_path=str(tmp_path / f"worker_{os.getpid()}_{id(kwargs)}.json"),
        model_history=0,
        **kwargs,
    )


# ------------------------------------------------------------------------------------------------
# Buffer


def _sample(i: int, act: Any = "arr") -> tuple:
    a = np.array([i], np.float32) if act == "arr" else act
    return (a, np.full(3, i, np.float32), float(-i), False, i % 5 == 4, {"seq": i})


def test_buffer_append_clear_len_and_maxlen_drops_oldest():
    b = Buffer(maxlen=3)
    for i in range(5):
        b.append_sample(_sample(i))
    assert len(b) == 3
    assert [s[5]["seq"] for s in b.memory] == [2, 3, 4]
    assert b.dropped == 2
    b.stat_train_return = 7.0
    b.clear()
    assert len(b) == 0 and b.stat_train_return == 7.0


def test_buffer_iadd_keeps_stats_per_worker_and_fills_sources():
    a, b = Buffer(maxlen=100), Buffer(maxlen=100)
    a.source_id, b.source_id = 1, 2
    a.append_sample(_sample(0))
    b.append_sample(_sample(1))
    b.append_sample(_sample(2))
    a.stat_train_return, a.stat_train_steps = -100.0, 10
    b.stat_train_return, b.stat_train_steps = -300.0, 21
    merged = Buffer(maxlen=100)
    merged += a
    merged += b
    assert merged.sources == [1, 2, 2]
    # the second merge does not overwrite the first worker's statistics
    assert merged.stats[1]["stat_train_return"] == -100.0
    assert merged.stat_train_return == pytest.approx(-200.0)
    assert merged.stat_train_steps == 16  # round(15.5)
    empty = Buffer(maxlen=5)
    assert empty.stat_test_return == 0.0 and empty.stat_test_steps == 0


# ------------------------------------------------------------------------------------------------
# column packing


def _same(x: Any, y: Any) -> bool:
    if isinstance(x, np.ndarray):
        return isinstance(y, np.ndarray) and x.dtype == y.dtype and np.array_equal(x, y)
    if isinstance(x, (tuple, list)):
        return type(x) is type(y) and len(x) == len(y) and all(_same(a, b) for a, b in zip(x, y))
    if isinstance(x, dict):
        return isinstance(y, dict) and x.keys() == y.keys() and all(_same(x[k], y[k]) for k in x)
    return type(x) is type(y) and x == y or (isinstance(x, float) and isinstance(y, float) and x == y)


def _roundtrip(buf: Buffer, src: int = 9) -> Buffer:
    return unpack_buffer(wire.decode(wire.encode(pack_buffer(buf, src, 0))), maxlen=10_000)


def test_pack_roundtrip_uniform_samples_with_reset_none_actions_is_exact_and_small():
    b = Buffer(maxlen=10_000)
    for i in range(1000):
        b.append_sample(_sample(i, act=None if i % 100 == 5 else "arr"))  # resets mid-buffer
    b.source_id = 9
    b.stat_test_return = 3.5
    data = wire.encode(pack_buffer(b, 9, 0))
    assert len(data) / 1000 < 40  # a per-sample encoding costs ~96 B here
    out = unpack_buffer(wire.decode(data), maxlen=10_000)
    assert len(out) == 1000 and out.sources == [9] * 1000
    assert all(_same(s, r) for s, r in zip(b.memory, out.memory))
    assert out.stats == {9: {"stat_test_return": 3.5}}


def test_pack_roundtrip_mixed_structures_falls_back_exactly():
    b = Buffer(maxlen=100)
    samples = [
        (
            None,
            (np.zeros((2, 2), np.uint8), [1.0, 2]),
            np.float32(1.5),
            True,
            False,
            {"a": "x", "crc": (None, 1)},
        ),
        (
            np.array([1.0]),
            (np.ones((2, 2), np.uint8), [3.0, 4]),
            np.float32(2.5),
            False,
            True,
            {"a": "y", "crc": (np.zeros(2), 2)},
        ),
        (np.array([2.0]), (np.ones((3, 2), np.uint8), [5.0]), 7, False, False, {"b": 1}),
    ]
    for s in samples:
        b.append_sample(s)
    out = _roundtrip(b)
    assert all(_same(s, r) for s, r in zip(samples, out.memory)), out.memory


def test_pack_roundtrip_non_tuple_samples_and_empty_buffer():
    b = Buffer(maxlen=10)
    b.append_sample([1, 2, 3])
    assert _roundtrip(b).memory == [[1, 2, 3]]
    assert len(_roundtrip(Buffer(maxlen=10))) == 0


def _episode_buffer(src: int, n: int, offset: float) -> Buffer:
    """Samples with a structured observation (a dict of an image and a tuple of a vector and a
    float), ``None`` as the action after each reset, episodes of 7 steps, an info per sample."""
    b = Buffer(maxlen=10_000)
    b.source_id = src
    for i in range(n):
        k = offset + i
        obs = {
            "img": np.full((2, 3), i % 255, np.uint8),
            "rest": (np.array([k, -k], np.float32), float(k)),
        }
        act = None if i % 7 == 0 else np.array([k / 10, 1.0], np.float32)
        b.append_sample((act, obs, float(i), i % 7 == 6, False, {"i": i}))
    return b


def test_received_buffers_reach_the_memory_as_columns_and_store_the_same_as_tuples():
    from tmrl.memory import GenericTorchMemory

    sent = [_episode_buffer(3, 30, 0.0), _episode_buffer(4, 20, 100.0)]
    received = Buffer(maxlen=10_000)
    received.sources = []
    for b in sent:
        received += _roundtrip(b, src=b.source_id)
    assert len(received) == 50 and received.sources == [3] * 30 + [4] * 20
    cols = received.as_columns()
    assert cols is not None and received._memory == []  # no tuple built so far
    act, obs, rew, term, trunc = cols
    assert act.shape == (50, 2) and not act[0].any() and act[1, 0] == pytest.approx(0.1)
    assert obs["img"].shape == (50, 2, 3) and obs["rest"][0].shape == (50, 2)
    assert rew.tolist() == [float(i) for i in range(30)] + [float(i) for i in range(20)]

    fast, slow = (GenericTorchMemory(memory_size=40, batch_size=8) for _ in range(2))
    fast.append_buffer(received)
    assert received._memory == []  # the memory took the columns: still no tuples
    reference = Buffer(maxlen=10_000)
    reference.sources = []
    for b in sent:
        reference += b  # plain tuples: the per-sample path
    slow.append_buffer(reference)
    assert fast.total == slow.total == 50
    for name, ring in slow.ring_arrays().items():
        assert np.array_equal(fast.ring_arrays()[name], ring), name
    assert fast.obs_spec == slow.obs_spec
    assert np.array_equal(fast.valid_slots(), slow.valid_slots())
    for slot in fast.valid_slots()[:5].tolist():
        assert all(_same(x, y) for x, y in zip(fast.get_transition(slot)[:6], slow.get_transition(slot)[:6]))
    # reading `memory` still gives every sample, in order, as tuples
    assert [s[5]["i"] for s in received.memory] == list(range(30)) + list(range(20))


def test_received_columns_mixed_with_local_samples_keep_their_order():
    local = _episode_buffer(1, 3, 50.0)
    received = _roundtrip(_episode_buffer(2, 4, 0.0), src=2)
    received += Buffer(maxlen=10)  # merging nothing keeps the columns
    assert received.as_columns() is not None
    local += received
    local.append_sample(_sample(99))
    assert len(local) == 8 and local.as_columns() is None
    assert [s[5].get("i", s[5].get("seq")) for s in local.memory] == [0, 1, 2, 0, 1, 2, 3, 99]
    assert local.sources == [1, 1, 1, 2, 2, 2, 2, 1]


def test_memory_reports_a_structure_change_in_received_columns():
    from tmrl.memory import GenericTorchMemory

    mem = GenericTorchMemory(memory_size=40, batch_size=8)
    mem.append_buffer(_roundtrip(_episode_buffer(2, 8, 0.0), src=2))
    other = Buffer(maxlen=10)
    for i in range(3):
        other.append_sample((np.zeros(2, np.float32), (np.zeros(2), 1.0), 0.0, False, False, {}))
    with pytest.raises(UserError, match="changed structure"):
        mem.append_buffer(_roundtrip(other, src=5))
    assert mem.total == 8  # the good samples are still there


@pytest.mark.parametrize(
    "payload",
    [
        {"kind": "samples", "v": 1, "n": 1, "src": 1, "cols": [("T", [("A", np.zeros(3))])] * 6},
        {"kind": "samples", "v": 1, "n": 2, "src": 1, "cols": [("N", np.array([True, False]), ("F", np.zeros(2)))] * 6},
        None,
        {"kind": "samples"},
        {"kind": "samples", "v": 1, "n": 2, "src": 1, "cols": [("R", [1])] * 6},
        {"kind": "samples", "v": 1, "n": 1, "src": 1, "cols": [("?", 1)] * 6},
        {"kind": "samples", "v": 1, "n": 1, "src": 1, "cols": [("A", np.zeros(3))] * 6},
        {"kind": "samples", "v": 99, "n": 0, "src": 1, "cols": []},
    ],
)
def test_unpack_rejects_malformed_payloads_with_payload_error(payload):
    with pytest.raises(PayloadError):
        unpack_buffer(payload, maxlen=10)


# ------------------------------------------------------------------------------------------------
# weights envelope


def test_weights_envelope_roundtrip_and_corruption():
    from tmrl.networking import pack_weights, unpack_weights

    data = bytes(range(256)) * 10
    env = pack_weights(data, {"observation": {"type": "Box"}}, 7)
    header, view = unpack_weights(env)
    assert (
        bytes(view) == data
        and header["version"] == 7
        and header["spaces"] == {"observation": {"type": "Box"}}
    )
    for bad in (env[:-1], b"garbage" * 3, env[:10], b"TMRLWGT1" + b"\xff" * 20):
        with pytest.raises(PayloadError):
            unpack_weights(bad)


# ------------------------------------------------------------------------------------------------
# spaces


def test_check_spaces_names_both_sides():
    box3 = gymnasium.spaces.Box(-1, 1, (3,), np.float32)
    box4 = gymnasium.spaces.Box(-1, 1, (4,), np.float32)
    act = gymnasium.spaces.Box(-1, 1, (1,), np.float32)
    check_spaces(describe_spaces(box3, act), describe_spaces(box3, act))
    with pytest.raises(SpacesMismatchError) as err:
        check_spaces(describe_spaces(box3, act), describe_spaces(box4, act))
    msg = str(err.value)
    assert "(4,)" in msg and "(3,)" in msg and "observation" in msg and "\n" not in msg
    tup = gymnasium.spaces.Tuple((box3, gymnasium.spaces.Discrete(2)))
    d = describe_spaces(tup, act)
    assert wire.decode(wire.encode(d)) == d


# ------------------------------------------------------------------------------------------------
# standalone worker


def test_standalone_worker_collects_samples_with_reset_action_none_and_truncation(tmp_path):
    w = make_worker(tmp_path, max_samples_per_episode=5)
    assert not w.connected
    w.collect_train_episode()
    mem = w.buffer.memory
    assert len(mem) == 6  # reset sample + 5 steps
    assert mem[0][0] is None and mem[0][2] == 0.0 and mem[0][3] is False and mem[0][4] is False
    assert [s[5]["seq"] for s in mem] == list(range(6))
    assert mem[-1][4] is True and not any(s[4] for s in mem[:-1])  # cut at max_samples_per_episode
    assert w.buffer.stat_train_steps == 5
    w.send_and_clear_buffer()  # standalone: nothing to send to, no error
    assert len(w.buffer) == 0
    assert w.update_actor_weights() == 0 and w.ignore_actor_weights() == 0
    w.run_episodes(max_samples_per_episode=3, nb_episodes=2)
    assert w.buffer.stat_test_steps == 3 and len(w.buffer) == 0


def test_standalone_worker_terminated_episode_is_not_truncated_and_default_action_used(tmp_path):
    class RTEnv(CountingEnv):
        default_action = np.array([0.25], np.float32)

    w = RolloutWorker(
        env_cls=lambda: RTEnv(episode_length=3),
        actor_module_cls=JsonActor,
        standalone=True,
        model_path=str(tmp_path / "m.json"),
        model_history=0,
        max_samples_per_episode=3,
    )
    w.collect_train_episode()
    mem = w.buffer.memory
    assert np.array_equal(mem[0][0], RTEnv.default_action)
    assert mem[-1][3] is True and mem[-1][4] is False


def test_worker_crc_debug_stores_full_transition_before_compression(tmp_path):
    seen = []

    def compressor(act, obs, rew, terminated, truncated, info):
        seen.append(info["crc_sample"])
        return act, obs[:1], rew, terminated, truncated, info

    w = make_worker(tmp_path, max_samples_per_episode=2, crc_debug=True, sample_compressor=compressor)
    w.collect_train_episode()
    assert seen[0][0] is None  # reset: no previous observation
    prev_obs, _act, new_obs, _rew, _term, _trunc = seen[1]
    assert prev_obs[0] == 0 and new_obs[0] == 1 and new_obs.shape == (3,)
    assert w.buffer.memory[1][1].shape == (1,)  # compressed sample, full transition in info
    assert seen[2][5] is True  # the cut is visible in the stored transition


def test_worker_loads_existing_model_file_at_start(tmp_path):
    path = tmp_path / "pre.json"
    path.write_text(json.dumps({"bias": 0.75}))
    w = RolloutWorker(
        env_cls=CountingEnv,
        actor_module_cls=JsonActor,
        standalone=True,
        model_path=str(path),
        model_history=0,
    )
    assert w.act(np.zeros(3, np.float32))[0] == pytest.approx(0.75)


def test_worker_refuses_unsendable_sample_with_user_error(tmp_path, monkeypatch):
    w = make_worker(tmp_path, max_samples_per_episode=1)

    class FakeLink:
        connected = True

        def send_samples(self, obj):
            wire.encode(obj)

    w._link = FakeLink()
    w.buffer.append_sample((None, object(), 0.0, False, False, {}))
    with pytest.raises(UserError, match="sample_compressor"):
        w.send_and_clear_buffer()


def test_run_env_benchmark_rejects_bad_steps_and_envs_without_benchmarks(tmp_path):
    w = make_worker(tmp_path)
    with pytest.raises(UserError):
        w.run_env_benchmark(math.inf)
    with pytest.raises(UserError, match="benchmark"):
        w.run_env_benchmark(3)


# ------------------------------------------------------------------------------------------------
# CRC debug mode through the wire into a memory


def test_crc_debug_samples_survive_the_wire_and_the_memory_checks_them(tmp_path):
    from tmrl.memory import CRCMismatchError, GenericTorchMemory

    def lying_compressor(act, obs, rew, terminated, truncated, info):
        return act, obs * 2, rew, terminated, truncated, info  # no memory undoes this

    for compressor, ok in ((None, True), (lying_compressor, False)):
        w = make_worker(tmp_path, max_samples_per_episode=8, crc_debug=True, sample_compressor=compressor)
        w.collect_train_episode()
        received = unpack_buffer(wire.decode(wire.encode(pack_buffer(w.buffer, w.source_id, 0))), maxlen=100)
        memory = GenericTorchMemory(memory_size=100, batch_size=4, crc_debug=True)
        memory.append(received)
        slots = memory.valid_slots()
        assert len(slots) == 8
        if ok:
            for i in slots:
                memory[int(i)]
        else:
            with pytest.raises(CRCMismatchError, match="new_obs"):
                for i in slots:
                    memory[int(i)]


# ------------------------------------------------------------------------------------------------
# roles


def test_run_worker_rejects_unknown_mode():
    from tmrl.roles import run_worker

    with pytest.raises(UserError, match="train, expert, test"):
        run_worker({}, "play")


def test_payload_order_drops_second_copies_and_keeps_late_payloads():
    from tmrl.networking import PayloadOrder

    order = PayloadOrder()
    assert [order.accept(7, s) for s in (0, 1, 2)] == [True, True, True]
    assert order.accept(7, 1) is False  # re-sent after a dropped connection
    assert order.accept(7, 5) is True  # 3 and 4 are missing for now
    assert order.lost == 2
    assert order.accept(7, 4) is True  # re-queued by the relay, arrives late: still new
    assert order.lost == 1
    assert order.accept(7, 4) is False
    assert order.accept(8, 1) is True  # another worker has its own numbering
    assert order.accept(8, None) is True  # unnumbered payloads are not checked
    assert order.duplicates == 2


# ------------------------------------------------------------------------------------------------
# transport options from the config


class _RecordedLink:
    """Stands in for WorkerLink/TrainerLink: keeps the arguments it was built with."""

    def __init__(self, *args: Any, **kwargs: Any):
        self.args, self.kwargs = args, kwargs


def _link_built_with_config(monkeypatch, override: dict[str, Any]) -> _RecordedLink:
    """The link arguments that the worker and trainer derive from a config (``override`` on the
    defaults), read by a freshly imported config_constants."""
    import sys

    import tmrl.config
    from tmrl.config import loader
    from tmrl.networking import _make_link

    monkeypatch.setenv(loader.OVERRIDE_ENV, json.dumps(override))
    # monkeypatch puts the modules back afterwards: the rest of the session keeps its config.
    monkeypatch.delitem(sys.modules, "tmrl.config.config_constants", raising=False)
    monkeypatch.delattr(tmrl.config, "config_constants", raising=False)
    return _make_link(_RecordedLink, "127.0.0.1", None, None, None, None, None, None, None)


def test_links_from_the_default_config_refuse_pickle(monkeypatch):
    link = _link_built_with_config(monkeypatch, {})
    assert link.kwargs["allow_pickle"] is False


def test_allow_pickle_in_the_config_reaches_the_links(monkeypatch):
    link = _link_built_with_config(monkeypatch, {"ALLOW_PICKLE": True})
    assert link.kwargs["allow_pickle"] is True
