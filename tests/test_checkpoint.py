"""Tests of tmrl.checkpoint: round trips, incremental memory segments, refusal of bad folders."""

from __future__ import annotations

import json
import logging
import random
import shutil

import gymnasium
import numpy as np
import pytest
import torch

import tmrl.checkpoint as ckpt
from tmrl.checkpoint import CheckpointError, load_checkpoint, load_memory, save_checkpoint
from tmrl.memory import GenericTorchMemory, RealTimeTorchMemory, TorchMemory
from tmrl.training_offline import TorchTrainingOffline
from tmrl.util import partial

OBS_SPACE = gymnasium.spaces.Tuple((gymnasium.spaces.Box(-1, 1, (3,), np.float32),))
ACT_SPACE = gymnasium.spaces.Box(-1, 1, (2,), np.float32)


class Buf:
    def __init__(self, samples=(), sources=None):
        self.memory = list(samples)
        self.sources = sources
        self.stat_train_return = 3.0
        self.stat_test_return = 4.0
        self.stat_train_steps = 5
        self.stat_test_steps = 6

    def __len__(self):
        return len(self.memory)


def samples(n: int, start: int = 0, episode_len: int = 7, first_act=None) -> list[tuple]:
    out = []
    for i in range(start, start + n):
        t = i % episode_len
        act = first_act if t == 0 else np.array([i, -t], np.float32)
        out.append((act, (np.array([i, t, 0.5], np.float32),), float(i), t == episode_len - 1, False, {}))
    return out


class TinyAgent:
    """Linear model, Adam, and a learned scalar: everything a real agent checkpoints."""

    def __init__(self, observation_space, action_space, device):
        self.model = torch.nn.Linear(5, 1)
        self.log_alpha = torch.zeros(1, requires_grad=True)
        self.optimizer = torch.optim.Adam([*self.model.parameters(), self.log_alpha], lr=1e-2)

    def train(self, batch):
        o, a, r, *_ = batch
        loss = ((self.model(torch.cat([*o, a], -1)).squeeze(-1) - r) ** 2).mean() + self.log_alpha.exp().sum()
        self.optimizer.zero_grad()
        loss.backward()
        self.optimizer.step()
        return {"loss_critic": loss.item()}

    def get_actor(self):
        return self.model

    def state_dict(self):
        return {"model": self.model.state_dict(), "optimizer": self.optimizer.state_dict(),
                "log_alpha": self.log_alpha.detach().clone()}

    def load_state_dict(self, state):
        self.model.load_state_dict(state["model"])
        self.optimizer.load_state_dict(state["optimizer"])
        with torch.no_grad():
            self.log_alpha.copy_(state["log_alpha"])


def training_cls(memory_cls=None, training_agent_cls=TinyAgent, **kwargs):
    return partial(
        TorchTrainingOffline,
        env_cls=(OBS_SPACE, ACT_SPACE),
        memory_cls=memory_cls or partial(GenericTorchMemory, memory_size=50, batch_size=8),
        training_agent_cls=training_agent_cls,
        device="cpu",
        **kwargs,
    )


def trained(cls, n_samples=40):
    training = cls()
    training.memory.append(Buf(samples(n_samples)))
    training.total_samples = n_samples
    for _ in range(5):
        training.agent.train(training.memory.sample())
    training.total_updates = 5
    training.epoch = 2
    return training


def test_round_trip_agent_optimizer_memory_counters_and_rng(tmp_path, caplog):
    cls = training_cls()
    training = trained(cls)
    path = tmp_path / "ckpt"
    save_checkpoint(training, path)
    # what the original process draws next, from every generator
    expect = (random.random(), np.random.rand(), torch.rand(1).item(), training.memory.sample_indices().tolist())

    with caplog.at_level(logging.INFO, logger="tmrl.checkpoint"):
        restored = load_checkpoint(path, cls)
    assert any("resumed from checkpoint" in r.getMessage() and "epoch 2" in r.getMessage()
               and f"{len(training.memory)} samples in memory" in r.getMessage() for r in caplog.records)
    assert (restored.epoch, restored.total_updates, restored.total_samples) == (2, 5, 40)
    for p, q in zip(training.agent.model.parameters(), restored.agent.model.parameters()):
        assert torch.equal(p, q)
    assert torch.equal(training.agent.log_alpha, restored.agent.log_alpha)
    s1, s2 = training.agent.optimizer.state_dict(), restored.agent.optimizer.state_dict()
    for k in s1["state"]:
        assert torch.equal(s1["state"][k]["exp_avg"], s2["state"][k]["exp_avg"])
        assert s1["state"][k]["step"] == s2["state"][k]["step"]
    assert np.array_equal(training.memory.valid_slots(), restored.memory.valid_slots())
    assert restored.memory.stat_test_return == 4.0
    got = (random.random(), np.random.rand(), torch.rand(1).item(), restored.memory.sample_indices().tolist())
    assert got == expect
    # the restored memory gives the same batches, and training continues identically
    idx = restored.memory.valid_slots()
    for a, b in zip(training.memory.sample(idx), restored.memory.sample(idx)):
        a, b = (a[0], b[0]) if isinstance(a, tuple) else (a, b)
        assert torch.equal(a, b)
    batch = training.memory.sample(idx)
    assert training.agent.train(batch) == restored.agent.train(batch)


def test_memory_segments_are_incremental_and_compacted(tmp_path):
    cls = training_cls(memory_cls=partial(GenericTorchMemory, memory_size=50, batch_size=8))
    training = trained(cls, n_samples=40)
    path = tmp_path / "ckpt"
    save_checkpoint(training, path)
    first = json.loads((path / "checkpoint.json").read_text())["memory"]["segments"]
    assert [(s["start"], s["stop"]) for s in first] == [(0, 40)]
    training.memory.append(Buf(samples(5, start=40)))
    save_checkpoint(training, path)
    segs = json.loads((path / "checkpoint.json").read_text())["memory"]["segments"]
    # only the 5 new samples were written; the first segment is reused as is
    assert [(s["start"], s["stop"]) for s in segs] == [(0, 40), (40, 45)]
    assert segs[0]["file"] == first[0]["file"]
    from safetensors import safe_open

    with safe_open(str(path / segs[1]["file"]), framework="numpy") as f:
        assert {len(f.get_tensor(k)) for k in f.keys()} == {5}  # noqa: SIM118
    assert len(list(path.glob("state-*.pt"))) == 1  # the previous state file was removed
    # wrap around: 50 slots hold samples 30..79; the old segment is still partly live, then dead
    training.memory.append(Buf(samples(35, start=45)))
    save_checkpoint(training, path)
    segs = json.loads((path / "checkpoint.json").read_text())["memory"]["segments"]
    assert [(s["start"], s["stop"]) for s in segs] == [(0, 40), (40, 45), (45, 80)]
    training.memory.append(Buf(samples(25, start=80)))  # holds 55..104: stored rows 60 <= 2 * 50
    save_checkpoint(training, path)
    segs = json.loads((path / "checkpoint.json").read_text())["memory"]["segments"]
    assert [(s["start"], s["stop"]) for s in segs] == [(45, 80), (80, 105)]
    assert len(list(path.glob("memory-*.safetensors"))) == 2
    restored = load_checkpoint(path, cls)
    assert restored.memory.total == 105
    idx = training.memory.valid_slots()
    assert np.array_equal(idx, restored.memory.valid_slots())
    for a, b in zip(training.memory.sample(idx), restored.memory.sample(idx)):
        a, b = (a[0], b[0]) if isinstance(a, tuple) else (a, b)
        assert torch.equal(a, b)
    # a run resumed from a backup (same memory uid, older history) is written in full
    backup = tmp_path / "backup"
    shutil.copytree(path, backup)
    training.memory.append(Buf(samples(5, start=105)))
    save_checkpoint(training, path)
    resumed = load_checkpoint(backup, cls)
    resumed.memory.append(Buf(samples(20, start=500)))
    save_checkpoint(resumed, path)
    segs = json.loads((path / "checkpoint.json").read_text())["memory"]["segments"]
    assert [(s["start"], s["stop"]) for s in segs] == [(75, 125)]
    again = load_checkpoint(path, cls)
    idx = resumed.memory.valid_slots()
    assert np.array_equal(idx, again.memory.valid_slots())
    assert torch.equal(resumed.memory.sample(idx)[1], again.memory.sample(idx)[1])
    # a different memory (new run) at the same path is written in full, not appended
    other = trained(cls, n_samples=10)
    save_checkpoint(other, path)
    segs = json.loads((path / "checkpoint.json").read_text())["memory"]["segments"]
    assert [(s["start"], s["stop"]) for s in segs] == [(0, 10)]
    assert len(list(path.glob("memory-*.safetensors"))) == 1


def test_realtime_memory_round_trip_and_dataset_path(tmp_path):
    default = np.zeros(2, np.float32)
    mem_cls = partial(RealTimeTorchMemory, act_buf_len=3, memory_size=30, batch_size=4)
    cls = training_cls(memory_cls=mem_cls)
    training = cls()
    training.memory.append(Buf(samples(20, first_act=default), sources=[i % 2 for i in range(20)]))
    save_checkpoint(training, tmp_path / "c")
    n_saved = len(training.memory)
    restored = load_checkpoint(tmp_path / "c", cls)
    # stream state survives: the next samples of source 1 continue its episode
    more = Buf(samples(4, start=20, first_act=default), sources=[1, 1, 0, 0])
    training.memory.append(more)
    restored.memory.append(more)
    idx = training.memory.valid_slots()
    assert np.array_equal(idx, restored.memory.valid_slots())
    for slot in idx:
        a, b = training.memory.get_transition(slot), restored.memory.get_transition(slot)
        for x, y in zip(a[0] + a[3], b[0] + b[3]):
            assert np.array_equal(x, y)
    # a new memory can start from the samples of a checkpoint
    fresh = RealTimeTorchMemory(act_buf_len=3, memory_size=30, dataset_path=str(tmp_path / "c"))
    assert len(fresh) == n_saved and len(fresh) < len(training.memory)
    assert fresh.total == 20


def test_interrupted_save_keeps_the_previous_checkpoint(tmp_path, monkeypatch):
    cls = training_cls()
    training = trained(cls)
    path = tmp_path / "ckpt"
    save_checkpoint(training, path)
    training.epoch = 3
    training.memory.append(Buf(samples(5, start=40)))

    def crash(*args, **kwargs):
        raise OSError("disk full")

    monkeypatch.setattr(ckpt, "atomic_write_text", crash)
    with pytest.raises(OSError):
        save_checkpoint(training, path)
    monkeypatch.undo()
    restored = load_checkpoint(path, cls)
    assert restored.epoch == 2 and restored.memory.total == 40
    save_checkpoint(training, path)  # the next save cleans the orphan files of the crashed one
    assert len(list(path.glob("state-*.pt"))) == 1


def one_line(err) -> str:
    text = str(err.value)
    assert "\n" not in text
    return text


def test_corrupt_truncated_and_foreign_checkpoints_are_refused(tmp_path):
    cls = training_cls()
    path = tmp_path / "ckpt"
    save_checkpoint(trained(cls), path)
    header = json.loads((path / "checkpoint.json").read_text())
    seg = path / header["memory"]["segments"][0]["file"]
    state = path / header["state"]["file"]

    data = bytearray(seg.read_bytes())
    data[len(data) // 2] ^= 0xFF
    seg.write_bytes(bytes(data))
    with pytest.raises(CheckpointError) as err:
        load_checkpoint(path, cls)
    assert "corrupt" in one_line(err) and seg.name in one_line(err)
    data[len(data) // 2] ^= 0xFF
    seg.write_bytes(bytes(data))

    state.write_bytes(state.read_bytes()[:-100])
    with pytest.raises(CheckpointError) as err:
        load_checkpoint(path, cls)
    assert "truncated" in one_line(err)

    (path / "checkpoint.json").write_text('{"format": "tmrl-chec')
    with pytest.raises(CheckpointError) as err:
        load_checkpoint(path, cls)
    assert "corrupt" in one_line(err)

    (path / "checkpoint.json").write_text(json.dumps({"format": "something else"}))
    with pytest.raises(CheckpointError) as err:
        load_checkpoint(path, cls)
    assert "not a tmrl checkpoint" in one_line(err)

    legacy = tmp_path / "tutorial_t.tcpt"
    legacy.write_bytes(b"\x80\x04\x95 pickled trainer")
    with pytest.raises(CheckpointError) as err:
        load_checkpoint(legacy, cls)
    assert "pickle" in one_line(err)
    with pytest.raises(CheckpointError):
        save_checkpoint(trained(cls), legacy)
    assert legacy.read_bytes().startswith(b"\x80\x04")  # never overwritten

    empty = tmp_path / "empty"
    empty.mkdir()
    with pytest.raises(CheckpointError) as err:
        load_checkpoint(empty, cls)
    assert "checkpoint.json" in one_line(err)
    with pytest.raises(CheckpointError) as err:
        load_checkpoint(tmp_path / "missing", cls)
    assert "no checkpoint" in one_line(err)


def test_agent_that_does_not_fit_is_refused(tmp_path):
    cls = training_cls()
    save_checkpoint(trained(cls), tmp_path / "c")

    class WiderAgent(TinyAgent):
        def __init__(self, *args, **kwargs):
            super().__init__(*args, **kwargs)
            self.model = torch.nn.Linear(6, 1)

    other = partial(cls, training_agent_cls=WiderAgent)
    with pytest.raises(CheckpointError) as err:
        load_checkpoint(tmp_path / "c", other)
    assert "does not fit" in one_line(err)


class ListMemory(TorchMemory):
    """A user memory keeping its samples in self.data (checkpointed through tmrl.wire)."""

    def __init__(self, device=None, nb_steps=1, memory_size=100, batch_size=4):
        super().__init__(device=device, nb_steps=nb_steps, memory_size=memory_size, batch_size=batch_size)

    def append_buffer(self, buffer):
        self.data.extend(buffer.memory)

    def __len__(self):
        return max(0, len(self.data) - 1)

    def get_transition(self, item):
        prev, now = self.data[item], self.data[item + 1]
        return prev[1], now[0], now[2], now[1], now[3], now[4], now[5]


def test_user_memory_data_round_trip(tmp_path):
    pytest.importorskip("tmrl.wire")
    cls = training_cls(memory_cls=ListMemory)
    training = cls()
    training.memory.append(Buf(samples(10, first_act=np.zeros(2, np.float32))))
    save_checkpoint(training, tmp_path / "c")
    restored = load_checkpoint(tmp_path / "c", cls)
    assert len(restored.memory) == 9
    a, b = training.memory.sample([3, 4]), restored.memory.sample([3, 4])
    assert torch.equal(a[1], b[1]) and torch.equal(a[0][0], b[0][0])


def test_trainer_default_functions(tmp_path):
    cls = training_cls()
    ckpt.dump_run_instance(trained(cls), tmp_path / "c")
    assert ckpt.load_run_instance(tmp_path / "c", cls).epoch == 2
    assert ckpt.make_load_run_instance_fn(cls)(tmp_path / "c").total_updates == 5
    mem = GenericTorchMemory(memory_size=50)
    load_memory(mem, tmp_path / "c")
    assert mem.total == 40


def test_round_trip_with_the_real_sac_agent(tmp_path):
    sac = pytest.importorskip("tmrl.algorithms.sac")
    cls = training_cls(training_agent_cls=partial(sac.SACAgent))
    training = cls()
    training.memory.append(Buf(samples(40)))
    for _ in range(3):
        training.agent.train(training.memory.sample())
    save_checkpoint(training, tmp_path / "c")
    restored = load_checkpoint(tmp_path / "c", cls)
    batch = training.memory.sample(training.memory.valid_slots()[:8])
    torch.manual_seed(1)
    a = training.agent.train(batch)
    torch.manual_seed(1)
    b = restored.agent.train(batch)
    assert {k: float(v) for k, v in a.items()} == {k: float(v) for k, v in b.items()}


def test_dataset_into_a_bigger_or_smaller_memory(tmp_path):
    cls = training_cls(memory_cls=partial(RealTimeTorchMemory, act_buf_len=2, memory_size=50, batch_size=8))
    training = cls()
    training.memory.append(Buf(samples(105, first_act=np.zeros(2, np.float32))))
    save_checkpoint(training, tmp_path / "c")
    saved = training.memory
    bigger = RealTimeTorchMemory(act_buf_len=2, memory_size=200, batch_size=64, dataset_path=str(tmp_path / "c"))
    # the same transitions as the saved memory: none reaches back before the oldest saved sample
    assert sorted(saved._count[saved.valid_slots()]) == sorted(bigger._count[bigger.valid_slots()])
    for _ in range(20):
        for slot in bigger.sample_indices():
            counter = int(bigger._count[slot])
            tr = bigger.get_transition(slot)
            want = saved.get_transition(counter % 50)
            for x, y in zip(tr[0] + tr[3], want[0] + want[3]):
                assert np.array_equal(x, y)
    # saving the bigger memory keeps only what it holds, and it loads back the same
    holder = cls()
    holder.memory = bigger
    save_checkpoint(holder, tmp_path / "d")
    again = RealTimeTorchMemory(act_buf_len=2, memory_size=200, dataset_path=str(tmp_path / "d"))
    assert np.array_equal(again.valid_slots(), bigger.valid_slots())
    smaller = RealTimeTorchMemory(act_buf_len=2, memory_size=20, dataset_path=str(tmp_path / "c"))
    assert smaller.size == 20 and smaller.total == 105 and len(smaller) > 0


# ------------------------------------------------------------------------------------------------
# checkpoints that fail safe (issue 15)


def test_a_checkpoint_folder_without_its_header_is_refused_never_overwritten(tmp_path, port_factory):
    from tmrl.networking import Trainer

    cls = training_cls()
    path = tmp_path / "ckpt"
    training = trained(cls)
    save_checkpoint(training, path)
    save_checkpoint(training, path)  # generation 2: a run with history
    (path / "checkpoint.json").unlink()  # lost (a bad copy, a hand clean-up)
    before = {p.name: p.read_bytes() for p in path.iterdir()}
    trainer = Trainer(training_cls=cls, server_ip="127.0.0.1", server_port=port_factory(), password="pw",
                      security=None, keys_dir=str(tmp_path / "keys"), model_path=str(tmp_path / "m.tmod"),
                      checkpoint_path=str(path))
    try:
        with pytest.raises(CheckpointError) as err:
            trainer.run()  # would have started afresh and deleted the state at its first save
    finally:
        trainer.interface.close()
    assert "no checkpoint.json" in one_line(err) and "move the folder away" in one_line(err)
    with pytest.raises(CheckpointError):
        save_checkpoint(trained(cls), path)
    assert {p.name: p.read_bytes() for p in path.iterdir()} == before


def test_an_interrupted_first_save_still_starts_afresh(tmp_path):
    cls = training_cls()
    path = tmp_path / "ckpt"
    save_checkpoint(trained(cls), path)
    (path / "checkpoint.json").unlink()  # the first save died before its header
    assert ckpt.checkpoint_complete(path) is False
    save_checkpoint(trained(cls), path)
    assert ckpt.checkpoint_complete(path) is True


@pytest.mark.parametrize(
    "edit",
    [
        lambda h: h.update(generation=-1),
        lambda h: h.update(epoch="x"),
        lambda h: h.update(total_samples=2.5),
        lambda h: h.update(run_id=["not", "a", "string"]),
        lambda h: h["state"].update(file="../../etc/passwd"),
        lambda h: h["state"].update(size="big"),
        lambda h: h.update(memory=[]),
        lambda h: h["memory"].update(kind="zzz"),
        lambda h: h["memory"].update(stats=[1, 2]),
        lambda h: h["memory"]["segments"][0].update(start=10**6),
        lambda h: h["memory"]["meta"].update(total="many"),
        lambda h: h["rng"].update(python="state"),
        lambda h: h["rng"].update(numpy=["MT19937", [1, 2], 0, 0, 0.0]),
    ],
)
def test_bad_header_values_are_refused_in_one_line(tmp_path, edit):
    cls = training_cls()
    path = tmp_path / "ckpt"
    save_checkpoint(trained(cls), path)
    header = json.loads((path / "checkpoint.json").read_text())
    edit(header)
    (path / "checkpoint.json").write_text(json.dumps(header))
    with pytest.raises(CheckpointError) as err:
        load_checkpoint(path, cls)
    assert "checkpoint.json" in one_line(err) or "corrupt" in one_line(err)


def test_the_run_identity_is_kept_by_the_checkpoint(tmp_path):
    cls = training_cls()
    training = trained(cls)
    training.run_id = "0123456789abcdef"
    save_checkpoint(training, tmp_path / "c")
    assert load_checkpoint(tmp_path / "c", cls).run_id == "0123456789abcdef"


def test_a_save_removes_the_temporaries_a_killed_save_left(tmp_path):
    # a trainer killed while it saved leaves its temporaries: the segments' and the header's
    # (atomic_write_text names it .checkpoint.json.<random>.tmp); the next save removes them,
    # and nothing else (a user's own file in the folder stays)
    training = trained(training_cls())
    path = tmp_path / "ckpt"
    save_checkpoint(training, path)
    left = [path / ".checkpoint.json.k3x_9ab2.tmp", path / ".state-000002.pt.u7q1zz0a.tmp",
            path / ".memory-000002.safetensors.p0o9i8u7.tmp"]
    for f in left:
        f.write_bytes(b"partial")
    mine = [path / ".notes.tmp", path / "checkpoint.json.bak"]
    for f in mine:
        f.write_bytes(b"user")
    save_checkpoint(training, path)
    assert not any(f.exists() for f in left)
    assert all(f.exists() for f in mine)
    assert load_checkpoint(path, training_cls()).epoch == training.epoch


def test_a_checkpoint_held_for_a_moment_by_another_process_still_loads_and_saves(tmp_path, monkeypatch):
    """Windows: an antivirus or a backup tool that has a checkpoint file open makes opening,
    replacing or removing it fail for a moment (PermissionError). Loading and saving wait for it;
    neither calls the checkpoint corrupt nor loses it."""
    import builtins
    import os

    from tmrl import platform

    monkeypatch.setattr(platform, "BUSY_DELAYS", (0.0,) * 6)
    cls = training_cls()
    training = trained(cls)
    path = tmp_path / "ckpt"
    save_checkpoint(training, path)
    real_open, real_replace, real_unlink = builtins.open, os.replace, os.unlink
    calls: dict[tuple[str, str], int] = {}

    def flaky(kind, real):
        def call(target, *args, **kwargs):  # every other call on each checkpoint file is refused
            key = (kind, str(target))
            calls[key] = calls.get(key, 0) + 1
            if str(target).startswith(str(path)) and calls[key] % 2 == 1:
                raise PermissionError(13, "being used by another process (emulated)", str(target))
            return real(target, *args, **kwargs)
        return call

    monkeypatch.setattr(builtins, "open", flaky("open", real_open))
    restored = load_checkpoint(path, cls)
    assert (restored.epoch, restored.total_updates) == (training.epoch, training.total_updates)
    monkeypatch.setattr(os, "replace", flaky("replace", real_replace))
    monkeypatch.setattr(os, "unlink", flaky("unlink", real_unlink))
    restored.epoch += 1
    save_checkpoint(restored, path)
    assert any(kind == "replace" and n >= 2 for (kind, _), n in calls.items())  # refused, then retried
    monkeypatch.undo()
    assert load_checkpoint(path, cls).epoch == training.epoch + 1
