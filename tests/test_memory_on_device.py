"""Tests of the replay memory's rings on the training device (``MEMORY_ON_DEVICE``,
tmrl/memory/resident.py): batches gathered on the device are the host path's, value for value and
dtype for dtype, across workers, episode ends and ring wrap-arounds; checkpoints move between the
two; a device that cannot hold the rings falls back to the host ("auto") or stops with one line
("on"). On this machine the device is the CPU with ``on_device="on"`` (the same code as on a GPU,
without the pinned copies); the tests marked ``gpu`` repeat the comparison on CUDA and check that
sampling never waits for the GPU."""

from __future__ import annotations

import logging
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from tmrl.checkpoint import load_checkpoint, save_checkpoint
from tmrl.config.spec import ConfigError
from tmrl.driving.memories import ImageMemory, LidarMemory, RawImageMemory
from tmrl.errors import UserError
from tmrl.memory import GenericTorchMemory, RealTimeTorchMemory, builtin, resident
from tmrl.training_offline import TorchTrainingOffline
from tmrl.util import partial

DEVICES = ["cpu", pytest.param("cuda", marks=pytest.mark.gpu)]


class Buf(SimpleNamespace):
    def __len__(self):
        return len(self.memory)


def buf(samples, sources=None) -> Buf:
    return Buf(memory=list(samples), sources=sources, stat_train_return=1.0, stat_test_return=2.0,
               stat_train_steps=3, stat_test_steps=4)


def stream(rng: np.random.Generator, n: int, kind: str, workers: int = 3):
    """``n`` samples of ``workers`` interleaved workers, episodes of random lengths (some cut,
    some terminated), each sample's values distinct. ``kind``: "dict" (nested observation, no
    action at resets), "image" (speed, gear, rpm, uint8 frame) or "lidar" (speed, lidar)."""
    out, sources = [], []
    step = {w: 0 for w in range(workers)}
    for i in range(n):
        w = int(rng.integers(workers))
        t = step[w]
        end = rng.random() < 0.08
        terminated, truncated = (end, False) if rng.random() < 0.5 else (False, end)
        act = rng.standard_normal(3).astype(np.float32)
        if kind == "dict":
            obs = {"pos": rng.standard_normal((2, 2)), "flags": (np.int64(i), rng.random(1) < 0.5)}
            act = None if t == 0 else act
        elif kind == "image":
            obs = (np.float32([i]), np.float32([t]), np.float32([w]),
                   rng.integers(0, 256, (6, 5), dtype=np.uint8))
        else:
            obs = (np.float32([i]), rng.standard_normal(19).astype(np.float32))
        out.append((act, obs, float(rng.standard_normal()), terminated, truncated, {}))
        sources.append(w)
        step[w] = 0 if end else t + 1
    return out, sources


MEMORIES = {
    "generic": (lambda **kw: GenericTorchMemory(**kw), "dict"),
    "realtime": (lambda **kw: RealTimeTorchMemory(act_buf_len=3, **kw), "lidar"),
    "lidar": (lambda **kw: LidarMemory(hist_len=4, act_buf_len=2, **kw), "lidar"),
    "image": (lambda **kw: ImageMemory(hist_len=4, act_buf_len=2, **kw), "image"),
    "raw-image": (lambda **kw: RawImageMemory(hist_len=3, act_buf_len=1, **kw), "image"),
}


def twins(name: str, device: str, memory_size: int = 97, batch_size: int = 32):
    """The same memory on the host (``on_device="off"``) and with its rings on ``device``,
    drawing from the same seed."""
    make, kind = MEMORIES[name]
    host = make(memory_size=memory_size, batch_size=batch_size, device=device, on_device="off")
    dev = make(memory_size=memory_size, batch_size=batch_size, device=device, on_device="on")
    dev.rng = np.random.default_rng(7)
    host.rng = np.random.default_rng(7)
    return host, dev, kind


def leaves(tree):
    if isinstance(tree, dict):
        return [x for k in sorted(tree) for x in leaves(tree[k])]
    if isinstance(tree, (tuple, list)):
        return [x for v in tree for x in leaves(v)]
    return [tree]


def assert_same_batch(a, b):
    assert type(a) is type(b)
    la, lb = leaves(tuple(a)), leaves(tuple(b))
    assert len(la) == len(lb)
    for x, y in zip(la, lb):
        assert isinstance(y, torch.Tensor) and x.dtype == y.dtype and x.shape == y.shape and x.device == y.device
        assert torch.equal(x, y)


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("name", list(MEMORIES))
def test_device_batches_equal_the_host_batches(name, device):
    host, dev, kind = twins(name, device)
    assert host.device_ring is None and dev.device_ring is not None
    rng = np.random.default_rng(3)
    # appends of several sizes: within the ring, across its end, bigger than the whole ring
    for n in (40, 45, 30, 150, 8, 60):
        samples, sources = stream(rng, n, kind)
        host.append(buf(samples, sources))
        dev.append(buf(samples, sources))
        for _ in range(3):
            assert_same_batch(host.sample(), dev.sample())
        # the drawn slots stay the same: both memories consumed their generator alike
        assert host.rng.bit_generator.state == dev.rng.bit_generator.state
    valid = host.valid_slots()
    assert_same_batch(host.sample(valid), dev.sample(valid))


def test_the_device_rings_hold_the_host_rows_after_every_append():
    _, dev, kind = twins("image", "cpu", memory_size=23)
    rng = np.random.default_rng(5)
    for n in (10, 20, 7, 50, 23):
        samples, sources = stream(rng, n, kind)
        dev.append(buf(samples, sources))
        ring, st = dev.device_ring, dev._storage
        for d, h in zip(ring.obs, st.obs):
            assert d.dtype == torch.from_numpy(h).dtype and np.array_equal(d.numpy(), h)
        assert np.array_equal(ring.act.numpy(), st.act)
        assert np.array_equal(ring.rew.numpy(), st.rew)
        assert np.array_equal(ring.terminated.numpy(), st.terminated.astype(np.float32))
        assert np.array_equal(ring.truncated.numpy(), st.truncated.astype(np.float32))
    # each frame stored once: one uint8 row per slot, not one per history position
    assert ring.obs[3].shape == (23, 6, 5) and ring.obs[3].dtype == torch.uint8


def test_sampling_on_the_device_gathers_nothing_on_the_host(monkeypatch):
    _, dev, kind = twins("image", "cpu")
    samples, sources = stream(np.random.default_rng(1), 80, kind)
    dev.append(buf(samples, sources))

    def host_gather(*args, **kwargs):
        raise AssertionError("a batch was gathered from the host rings")

    monkeypatch.setattr(dev._storage, "observations", host_gather)
    monkeypatch.setattr(type(dev), "gather", host_gather)
    o = dev.sample().obs
    assert o[3].shape == (32, 4, 6, 5) and o[3].dtype == torch.float32


def test_auto_keeps_the_rings_on_the_host_of_a_cpu_trainer_and_modes_are_checked():
    assert GenericTorchMemory(device="cpu").device_ring is None
    assert GenericTorchMemory(device="cpu", on_device="off").device_ring is None
    # item-by-item sampling (a sample_preprocessor, crc_debug) reads the host: no rings to copy
    assert GenericTorchMemory(device="cpu", on_device="on", crc_debug=True).device_ring is None
    assert GenericTorchMemory(device="cpu", on_device="on", sample_preprocessor=lambda *t: t).device_ring is None
    assert GenericTorchMemory(device="cpu", on_device="on").device_ring is not None
    with pytest.raises(UserError, match="MEMORY_ON_DEVICE='gpu' is not known"):
        GenericTorchMemory(device="cpu", on_device="gpu")


def test_config_key_feeds_the_memory_and_refuses_unknown_values():
    from tmrl.config import loader, schema

    cfg = loader.validate({"MEMORY_ON_DEVICE": "off"})
    assert schema.arguments(cfg, "GenericTorchMemory")["on_device"] == "off"
    assert schema.arguments(loader.default_config(), "GenericTorchMemory")["on_device"] == "auto"
    with pytest.raises(ConfigError) as info:
        loader.validate({"MEMORY_ON_DEVICE": "always"})
    assert "MEMORY_ON_DEVICE" in str(info.value) and "\n" not in str(info.value)


def test_a_subclass_that_overrides_build_obs_keeps_the_host_path(caplog):
    class Doubled(GenericTorchMemory):
        def build_obs(self, slots):
            return self._storage.observations(slots) * 2

    with caplog.at_level(logging.INFO, logger="tmrl.memory.builtin"):
        mem = Doubled(device="cpu", on_device="on", memory_size=20, batch_size=4)
    assert mem.device_ring is None
    assert "overrides build_obs" in caplog.text
    mem.append(buf([(np.float32([i]), np.float32([i]), 0.0, False, False, {}) for i in range(6)]))
    o, *_ = mem.sample(np.array([1, 2]))
    assert torch.equal(o, torch.tensor([[0.0], [2.0]]))


def oom(monkeypatch, after: int):
    """Make the device's allocations fail after ``after`` of them succeeded."""
    calls = {"n": 0}
    real = resident._device_zeros

    def zeros(shape, dtype, device):
        calls["n"] += 1
        if calls["n"] > after:
            raise torch.OutOfMemoryError("CUDA out of memory. Tried to allocate 4.00 GiB")
        return real(shape, dtype, device)

    monkeypatch.setattr(resident, "_device_zeros", zeros)


def test_rings_that_do_not_fit_fall_back_to_the_host_with_auto(monkeypatch, caplog):
    # "auto" on a CPU device keeps the host path, so this test reaches the fallback by letting a
    # memory think its CPU is the GPU: the allocations of the flags succeed, the frames' do not.
    monkeypatch.setattr(resident, "wants_device_ring", lambda mode, device: mode != "off")
    monkeypatch.setattr(builtin, "wants_device_ring", resident.wants_device_ring)
    oom(monkeypatch, after=3)
    host, dev, kind = twins("image", "cpu")
    dev.on_device = "auto"
    samples, sources = stream(np.random.default_rng(2), 60, kind)
    host.append(buf(samples, sources))
    with caplog.at_level(logging.WARNING, logger="tmrl.memory.builtin"):
        dev.append(buf(samples, sources))
    assert dev.device_ring is None
    assert "do not fit" in caplog.text and "MEMORY_ON_DEVICE" in caplog.text
    assert len(caplog.records) == 1
    # nothing was lost: the host rings hold every sample and batches go on
    assert_same_batch(host.sample(), dev.sample())
    assert len(dev) == len(host)


def test_rings_that_do_not_fit_stop_the_run_in_one_line_with_on(monkeypatch):
    oom(monkeypatch, after=0)
    with pytest.raises(UserError) as err:
        GenericTorchMemory(device="cpu", on_device="on", memory_size=1000)
    msg = str(err.value)
    assert "\n" not in msg and "do not fit" in msg and "MEMORY_SIZE" in msg and 'MEMORY_ON_DEVICE to "off"' in msg
    # an allocation that fails later (the first frames) stops the append, the host keeps its rows
    monkeypatch.undo()
    mem = ImageMemory(hist_len=2, act_buf_len=1, device="cpu", on_device="on", memory_size=50, batch_size=4)
    oom(monkeypatch, after=0)
    samples, sources = stream(np.random.default_rng(2), 10, "image")
    with pytest.raises(UserError, match="do not fit"):
        mem.append(buf(samples, sources))
    assert mem.total == 10


def training(memory_cls, device="cpu"):
    import gymnasium

    obs = gymnasium.spaces.Tuple((gymnasium.spaces.Box(0, 1, (1,)), gymnasium.spaces.Box(-5, 5, (19,))))
    act = gymnasium.spaces.Box(-1, 1, (3,))

    class Agent:
        def __init__(self, observation_space, action_space, device):
            self.w = torch.zeros(1)

        def state_dict(self):
            return {"w": self.w}

        def load_state_dict(self, state):
            self.w = state["w"]

        def get_actor(self):
            return torch.nn.Linear(1, 1)

    return partial(TorchTrainingOffline, env_cls=(obs, act), memory_cls=memory_cls, training_agent_cls=Agent,
                   device=device)


@pytest.mark.parametrize("device", DEVICES)
def test_checkpoints_move_between_device_and_host_memories(tmp_path, device):
    make = lambda mode: partial(LidarMemory, hist_len=3, act_buf_len=2, memory_size=40, batch_size=16,
                                on_device=mode)
    on_dev = training(make("on"), device)()
    samples, sources = stream(np.random.default_rng(4), 70, "lidar")
    on_dev.memory.append(buf(samples, sources))
    save_checkpoint(on_dev, tmp_path / "from-device")
    on_host = load_checkpoint(tmp_path / "from-device", training(make("off"), "cpu"))
    assert on_host.memory.device_ring is None
    slots = on_dev.memory.valid_slots()
    assert np.array_equal(slots, on_host.memory.valid_slots())
    assert_same_batch(on_host.memory.sample(slots), to_cpu(on_dev.memory.sample(slots)))
    # and back: a host checkpoint restored into a memory whose rings are on the device
    save_checkpoint(on_host, tmp_path / "from-host")
    back = load_checkpoint(tmp_path / "from-host", training(make("on"), device))
    assert back.memory.device_ring is not None
    assert_same_batch(to_cpu(back.memory.sample(slots)), on_host.memory.sample(slots))
    # the restored device rings go on taking samples where the saved streams stopped
    more, more_sources = stream(np.random.default_rng(9), 25, "lidar")
    back.memory.append(buf(more, more_sources))
    on_host.memory.append(buf(more, more_sources))
    slots = on_host.memory.valid_slots()
    assert_same_batch(to_cpu(back.memory.sample(slots)), on_host.memory.sample(slots))


def to_cpu(batch):
    def move(t):
        if isinstance(t, dict):
            return {k: move(v) for k, v in t.items()}
        if isinstance(t, (tuple, list)):
            return type(t)(move(v) for v in t)
        return t.cpu()

    return type(batch)(*(move(x) for x in batch))


@pytest.mark.gpu
def test_sampling_on_the_gpu_never_waits_for_it():
    mem = ImageMemory(hist_len=4, act_buf_len=2, memory_size=5000, batch_size=256, device="cuda")
    assert mem.device_ring is not None  # "auto" on a GPU
    samples, sources = stream(np.random.default_rng(1), 3000, "image")
    mem.append(buf(samples, sources))
    torch.cuda.synchronize()
    torch.cuda.set_sync_debug_mode("error")
    try:
        for _ in range(5):
            o = mem.sample().obs
    finally:
        torch.cuda.set_sync_debug_mode(0)
    assert o[3].device.type == "cuda" and o[3].shape == (256, 4, 6, 5)


def test_as_float32_scales_a_copy_never_its_input():
    for x in (np.arange(4, dtype=np.uint8), np.ones(4, np.float32), torch.arange(4, dtype=torch.uint8),
              torch.ones(4)):
        before = x.copy() if isinstance(x, np.ndarray) else x.clone()
        y = resident.as_float32(x, 0.5)
        assert y.dtype in (np.float32, torch.float32) and float(y[1]) == 0.5 * float(before[1])
        assert (x == before).all()


def test_copies_to_the_device_go_in_pieces_and_keep_every_row(monkeypatch, tmp_path):
    # a restore of a big memory is copied chunk_bytes at a time; here a few frames per piece
    monkeypatch.setattr(resident.DeviceRing, "chunk_bytes", 100)
    host, dev, kind = twins("image", "cpu", memory_size=41)
    samples, sources = stream(np.random.default_rng(6), 70, kind)
    host.append(buf(samples, sources))
    dev.append(buf(samples, sources))
    assert_same_batch(host.sample(host.valid_slots()), dev.sample(host.valid_slots()))
    dev.device_ring.reload()
    ring, st = dev.device_ring, dev._storage
    for d, h in zip(ring.obs, st.obs):
        assert np.array_equal(d.numpy(), h)
    assert np.array_equal(ring.act.numpy(), st.act) and np.array_equal(ring.rew.numpy(), st.rew)
    assert_same_batch(host.sample(host.valid_slots()), dev.sample(host.valid_slots()))
