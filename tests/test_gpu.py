"""Training on a GPU: every agent trains and acts there from a replay memory that collates there,
a checkpoint taken on one device resumes on the other, and SAC on the GPU follows SAC on the CPU.

Each check takes the device as a parameter: its ``cuda`` twin carries the ``gpu`` marker (skipped
with "needs a CUDA GPU" where PyTorch sees none, tests/conftest.py; allowed to skip in CI,
tests/ci_skips.py) and runs on a GPU machine with ``pytest -m gpu tests/test_gpu.py``; its ``cpu``
twin runs the same code everywhere. The ``meta`` device (tensors with shapes and no data) stands
in for a GPU where only placement is checked.
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterator
from typing import Any

import numpy as np
import pytest
import torch
from ci_skips import GPU_SKIP_REASON
from gymnasium import spaces

from tmrl.algorithms import SACAgent, agent_class
from tmrl.checkpoint import load_checkpoint, save_checkpoint
from tmrl.memory import GenericTorchMemory
from tmrl.models import MLPActorCritic
from tmrl.training_offline import TorchTrainingOffline
from tmrl.util import partial

ALGORITHMS = ("SAC", "REDQSAC", "DROQ", "TQC", "CROSSQ")
OBS = spaces.Tuple((spaces.Box(-1.0, 1.0, (3,), np.float32),))
ACT = spaces.Box(-1.0, 1.0, (2,), np.float32)

gpu = pytest.mark.gpu
DEVICES = [pytest.param("cpu", id="cpu"), pytest.param("cuda", id="cuda", marks=gpu)]


@pytest.fixture(autouse=True)
def _exact_float32():
    # float32 products in full precision on the GPU too (TF32 would be a tolerance of its own),
    # one CPU thread (a shared machine).
    precision, threads = torch.get_float32_matmul_precision(), torch.get_num_threads()
    torch.set_float32_matmul_precision("highest")
    torch.set_num_threads(1)
    yield
    torch.set_float32_matmul_precision(precision)
    torch.set_num_threads(threads)


# --- helpers ----------------------------------------------------------------------------------------


class Buf:
    """What a worker sends: samples and the statistics of its episodes."""

    def __init__(self, samples: list[tuple]) -> None:
        self.memory = samples
        self.sources = None
        self.stat_train_return = self.stat_test_return = 0.0
        self.stat_train_steps = self.stat_test_steps = 0

    def __len__(self) -> int:
        return len(self.memory)


def samples(n: int, seed: int = 0, episode_len: int = 25) -> list[tuple]:
    """``(act, obs, rew, terminated, truncated, info)`` in episodes of ``episode_len`` steps."""
    rng = np.random.default_rng(seed)
    out = []
    for i in range(n):
        t = i % episode_len
        act = np.zeros(2, np.float32) if t == 0 else rng.uniform(-1, 1, 2).astype(np.float32)
        obs = (rng.uniform(-1, 1, 3).astype(np.float32),)
        out.append((act, obs, 0.0 if t == 0 else float(rng.normal()), t == episode_len - 1, False, {}))
    return out


def filled_memory(device: str, n: int = 200, batch_size: int = 32) -> GenericTorchMemory:
    memory = GenericTorchMemory(device=device, nb_steps=1, memory_size=1000, batch_size=batch_size)
    memory.append(Buf(samples(n)))
    return memory


def leaves(obj: Any, path: str = "") -> Iterator[tuple[str, Any]]:
    """Every leaf of a nested state dict (tensors and plain values), with its path."""
    if isinstance(obj, dict):
        for k, v in obj.items():
            yield from leaves(v, f"{path}/{k}")
    elif isinstance(obj, (list, tuple)):
        for i, v in enumerate(obj):
            yield from leaves(v, f"{path}/{i}")
    else:
        yield path, obj


def tensors_of(agent: Any) -> list[torch.Tensor]:
    """The agent's parameters, its targets' and its entropy coefficient."""
    out = [*agent.model.parameters(), *agent.model_target.parameters()]
    return out + ([agent.log_alpha] if getattr(agent, "log_alpha", None) is not None else [])


def to_device(batch: tuple, device: str) -> tuple:
    return tuple(tuple(t.to(device) for t in x) if isinstance(x, tuple) else x.to(device) for x in batch)


@contextlib.contextmanager
def noise_drawn_on_the_cpu(seed: int) -> Iterator[None]:
    """``torch.randn``/``torch.randn_like`` (the actor's and the fused update's Gaussian noise)
    drawn from one CPU generator and moved to where they were asked for: the same noise on every
    device (the CPU's and a GPU's generators draw different numbers from the same seed)."""
    gen = torch.Generator().manual_seed(seed)
    randn, randn_like = torch.randn, torch.randn_like

    def drawn(*size: Any, device: Any = None, dtype: Any = None) -> torch.Tensor:
        shape = size[0] if len(size) == 1 and isinstance(size[0], (tuple, list, torch.Size)) else size
        return randn(*shape, generator=gen, dtype=dtype).to(device)

    def drawn_like(t: torch.Tensor) -> torch.Tensor:
        return randn(t.shape, generator=gen, dtype=t.dtype).to(t.device)

    torch.randn, torch.randn_like = drawn, drawn_like
    try:
        yield
    finally:
        torch.randn, torch.randn_like = randn, randn_like


# --- the marker -------------------------------------------------------------------------------------


def test_gpu_twins_skip_exactly_where_pytorch_sees_no_gpu(request):
    marked = [item for item in request.session.items if item.get_closest_marker("gpu") is not None]
    skips = [[m.kwargs.get("reason") for m in item.iter_markers("skip")] for item in marked]
    if torch.cuda.is_available():
        assert not any(skips)
    else:
        assert all(GPU_SKIP_REASON in s for s in skips)


# --- placement (meta stands in for a GPU) ------------------------------------------------------------


@pytest.mark.parametrize("device", [pytest.param("meta", id="meta"), pytest.param("cuda", id="cuda", marks=gpu)])
@pytest.mark.parametrize("algo", ALGORITHMS)
def test_an_agent_and_its_memory_live_on_the_device_they_are_given(algo, device):
    agent = agent_class(algo)(OBS, ACT, device)
    kind = torch.device(device).type
    assert {t.device.type for t in tensors_of(agent)} == {kind}
    assert torch.device(agent.get_actor().device).type == kind
    memory = filled_memory(device)
    obs, act, rew, next_obs, terminated, truncated = memory.sample()
    assert {t.device.type for t in (*obs, act, rew, *next_obs, terminated, truncated)} == {kind}


# --- (a) each agent trains and acts on the device -------------------------------------------------------


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("algo", ALGORITHMS)
def test_each_agent_trains_from_its_memory_and_acts_on_the_device(algo, device):
    torch.manual_seed(0)
    memory = filled_memory(device)
    agent = agent_class(algo)(OBS, ACT, device)
    before = [t.detach().clone() for t in tensors_of(agent)]
    for _ in range(20):
        metrics = agent.train(memory.sample())
    kind = torch.device(device).type
    after = tensors_of(agent)
    assert agent.skipped_updates == 0  # no update was dropped for a non-finite loss or gradient
    assert all(t.device.type == kind and bool(torch.isfinite(t).all()) for t in after)
    assert not any(torch.equal(a, b) for a, b in zip(before, after))  # it trained: every tensor, targets too
    assert all(np.isfinite(float(v)) for v in metrics.values())
    actor = agent.get_actor()
    assert torch.device(actor.device).type == kind
    one_obs = (np.array([0.1, -0.2, 0.3], np.float32),)
    for test in (False, True):
        action = actor.act_(one_obs, test=test)
        assert isinstance(action, np.ndarray) and action.shape == (2,)
        assert np.all(np.isfinite(action)) and np.all(np.abs(action) <= 1.0)


# --- (b) a checkpoint resumes on another device ---------------------------------------------------------


def training_on(algo: str, device: str) -> partial:
    return partial(TorchTrainingOffline, env_cls=(OBS, ACT),
                   memory_cls=partial(GenericTorchMemory, memory_size=300, batch_size=32),
                   training_agent_cls=partial(agent_class(algo)), device=device)


@pytest.mark.parametrize(
    ("saved_on", "resumed_on"),
    [pytest.param("cpu", "cpu", id="cpu-cpu"), pytest.param("cuda", "cpu", id="cuda-cpu", marks=gpu),
     pytest.param("cpu", "cuda", id="cpu-cuda", marks=gpu)],
)
@pytest.mark.parametrize("algo", ALGORITHMS)
def test_a_checkpoint_resumes_on_another_device_with_the_same_state(algo, saved_on, resumed_on, tmp_path):
    torch.manual_seed(0)
    training = training_on(algo, saved_on)()
    training.memory.append(Buf(samples(200)))
    for _ in range(5):
        training.agent.train(training.memory.sample())
    save_checkpoint(training, tmp_path / "ckpt")
    torch.manual_seed(1)  # another initialisation: everything must come from the checkpoint
    restored = load_checkpoint(tmp_path / "ckpt", training_on(algo, resumed_on))
    saved, loaded = dict(leaves(training.agent.state_dict())), dict(leaves(restored.agent.state_dict()))
    assert saved.keys() == loaded.keys()
    for key, value in saved.items():
        if isinstance(value, torch.Tensor):
            assert torch.equal(value.cpu(), loaded[key].cpu()), key
        else:
            assert value == loaded[key], key
    kind = torch.device(resumed_on).type
    assert all(t.device.type == kind for t in tensors_of(restored.agent))
    assert torch.device(restored.agent.get_actor().device).type == kind
    idx = training.memory.valid_slots()
    assert np.array_equal(idx, restored.memory.valid_slots())
    batch = restored.memory.sample(idx[:32])
    assert batch[1].device.type == kind
    restored.agent.train(batch)  # the optimizers' state sits where their parameters are: training goes on
    assert restored.agent.skipped_updates == 0
    assert all(bool(torch.isfinite(t).all()) for t in tensors_of(restored.agent))


# --- (c) SAC on the device follows SAC on the CPU --------------------------------------------------------


@pytest.mark.parametrize("fused", [True, False], ids=["fused", "autograd"])
@pytest.mark.parametrize("device", DEVICES)
def test_sac_on_the_device_gives_the_parameters_sac_gives_on_the_cpu(device, fused):
    """Same seed, same batches, same noise: ten updates on ``device`` end within float tolerance of
    ten on the CPU. SGD for the actor and critics, so that a rounding difference stays one (Adam
    turns the sign of a near-zero gradient into a step of the learning rate)."""
    gen = torch.Generator().manual_seed(3)
    batches = []
    for _ in range(10):
        o, o2 = (torch.rand(32, 3, generator=gen) * 2 - 1,), (torch.rand(32, 3, generator=gen) * 2 - 1,)
        a, r = torch.rand(32, 2, generator=gen) * 2 - 1, torch.randn(32, generator=gen)
        batches.append((o, a, r, o2, (torch.rand(32, generator=gen) < 0.1).float(), torch.zeros(32)))

    def run(dev: str) -> tuple[list[torch.Tensor], list[torch.Tensor]]:
        torch.manual_seed(0)
        agent = SACAgent(OBS, ACT, dev, model_cls=partial(MLPActorCritic, hidden_sizes=(64, 64)), lr_actor=1e-2,
                         lr_critic=1e-2, optimizer_actor="sgd", optimizer_critic="sgd", fused=fused)
        assert (agent.fused_update is not None) == fused
        start = [t.detach().cpu().clone() for t in tensors_of(agent)]
        with noise_drawn_on_the_cpu(7):
            for b in batches:
                agent.train(to_device(b, dev))
        assert agent.skipped_updates == 0
        return start, [t.detach().cpu() for t in tensors_of(agent)]

    start_cpu, on_cpu = run("cpu")
    start_dev, on_dev = run(device)
    assert all(torch.equal(a, b) for a, b in zip(start_cpu, start_dev))  # one initialisation
    assert sum(not torch.equal(a, b) for a, b in zip(start_cpu, on_cpu)) > len(on_cpu) // 2  # it trained
    for i, (want, got) in enumerate(zip(on_cpu, on_dev)):
        torch.testing.assert_close(got, want, rtol=1e-4, atol=1e-5, msg=lambda m, i=i: f"tensor {i}: {m}")


@pytest.mark.parametrize("fused", [True, False], ids=["fused", "autograd"])
def test_every_random_draw_of_a_sac_update_goes_through_the_cpu_noise(fused):
    """What makes the comparison above fair: under :func:`noise_drawn_on_the_cpu`, the global
    generator's state does not change the updates (no draw escapes to a device's own generator)."""
    gen = torch.Generator().manual_seed(3)
    batch = ((torch.rand(32, 3, generator=gen),), torch.rand(32, 2, generator=gen), torch.randn(32, generator=gen),
             (torch.rand(32, 3, generator=gen),), torch.zeros(32), torch.zeros(32))

    def run(global_seed: int, patched: bool) -> list[torch.Tensor]:
        torch.manual_seed(0)
        agent = SACAgent(OBS, ACT, "cpu", model_cls=partial(MLPActorCritic, hidden_sizes=(16, 16)), fused=fused)
        torch.manual_seed(global_seed)
        with noise_drawn_on_the_cpu(7) if patched else contextlib.nullcontext():
            for _ in range(3):
                agent.train(batch)
        return [t.detach().clone() for t in tensors_of(agent)]

    assert all(torch.equal(a, b) for a, b in zip(run(1, True), run(2, True)))
    assert not all(torch.equal(a, b) for a, b in zip(run(1, False), run(2, False)))  # the draws matter
