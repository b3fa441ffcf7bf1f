"""The non-finite guard decided on the device (tmrl/algorithms/guard.py): no host read per update,
and exactly the host guard's semantics.

An update whose loss or gradients hold NaN or inf changes no parameter, target, optimizer state
(Adam's step counts and moments included), running statistic, entropy coefficient or kept loss,
and is counted; the count is read with the metrics. The agents decide on the device off a CPU;
here the device path is forced on the CPU (``agent.guard.device_side = True``) and run beside the
host path on twin agents, which must stay bit for bit equal through good and bad updates.

"No host read" on the CPU: every Python-level read of a tensor's value (``bool``, ``float``,
``int``, ``item``, ``tolist``, ``numpy``), each a synchronisation on a GPU, is made to raise
during the device path's updates. Synchronisations inside PyTorch's C++ (a blocking copy to the
GPU, ``nonzero``) cannot show on a CPU: the ``gpu`` twin runs the updates under
``torch.cuda.set_sync_debug_mode("error")``.
"""

from __future__ import annotations

import contextlib
import logging
import math
from collections.abc import Callable, Iterator
from typing import Any

import numpy as np
import pytest
import torch
from gymnasium import spaces

from tmrl.algorithms import BROAgent, CrossQAgent, DroQAgent, DrQAgent, REDQSACAgent, SACAgent, TQCAgent
from tmrl.algorithms.bro import BROActorCritic
from tmrl.algorithms.simbav2 import SimbaV2Agent, SimbaV2ActorCritic
from tmrl.algorithms.crossq import CrossQActorCritic
from tmrl.algorithms.droq import DroQMLPActorCritic
from tmrl.algorithms.drq import DrQActorCritic
from tmrl.algorithms.guard import GuardedUpdate, NonFiniteGuard, Rollback
from tmrl.algorithms.tqc import TQCActorCritic
from tmrl.models import MLPActorCritic, REDQMLPActorCritic
from tmrl.util import partial

OBS = spaces.Box(-1.0, 1.0, (3,), np.float32)
ACT = spaces.Box(-1.0, 1.0, (1,), np.float32)
H = (16, 16)
BATCH = 16
DRQ_SIZES = {"channels": (4, 4), "kernels": (3, 3), "strides": (2, 1), "feature_dim": 8, "hidden_sizes": (16,)}
DRQ_ACT = spaces.Box(-1.0, 1.0, (3,), np.float32)
DRQ_OBS = spaces.Tuple([spaces.Box(0, 1, (1,))] * 3 + [spaces.Box(0, 255, (2, 16, 16), np.uint8), DRQ_ACT, DRQ_ACT])
# alpha starts at its ceiling and its target entropy pushes it up: every policy update goes
# through the ceiling's hold, which cuts it back
ALPHA = {"alpha": 0.2, "alpha_max": 0.2, "target_entropy": 5.0}

AGENTS: dict[str, Callable[..., SACAgent]] = {
    "SAC-fused": lambda d, c: SACAgent(OBS, ACT, d, model_cls=partial(MLPActorCritic, hidden_sizes=H), compile=c,
                                       **ALPHA),
    "SAC": lambda d, c: SACAgent(OBS, ACT, d, model_cls=partial(MLPActorCritic, hidden_sizes=H), fused=False,
                                 compile=c, **ALPHA),
    "SAC-sequential": lambda d, c: SACAgent(OBS, ACT, d, model_cls=partial(MLPActorCritic, hidden_sizes=H),
                                            update_order="sequential", compile=c, **ALPHA),
    "REDQSAC": lambda d, c: REDQSACAgent(OBS, ACT, d, model_cls=partial(REDQMLPActorCritic, hidden_sizes=H), n=3,
                                         m=2, q_updates_per_policy_update=2, compile=c, **ALPHA),
    "DROQ": lambda d, c: DroQAgent(OBS, ACT, d, model_cls=partial(DroQMLPActorCritic, hidden_sizes=H),
                                   q_updates_per_policy_update=2, compile=c, **ALPHA),
    "TQC": lambda d, c: TQCAgent(OBS, ACT, d, model_cls=partial(TQCActorCritic, hidden_sizes=H, critic_hidden_sizes=H),
                                 n=2, n_quantiles=5, compile=c, **ALPHA),
    "BRO": lambda d, c: BROAgent(OBS, ACT, d, model_cls=partial(BROActorCritic, hidden_sizes=H), n=2, n_quantiles=5,
                                 critic_width=H[0], compile=c, **ALPHA),
    "SIMBAV2": lambda d, c: SimbaV2Agent(OBS, ACT, d, model_cls=partial(SimbaV2ActorCritic, hidden_sizes=H), n=2,
                                         n_atoms=11, critic_width=H[0], compile=c, **ALPHA),
    "CROSSQ": lambda d, c: CrossQAgent(OBS, ACT, d, model_cls=partial(CrossQActorCritic, hidden_sizes=H),
                                       critic_width=16, policy_delay=2, renorm_warmup_steps=2, compile=c, **ALPHA),
    "DRQ": lambda d, c: DrQAgent(DRQ_OBS, DRQ_ACT, d, model_cls=partial(DrQActorCritic, **DRQ_SIZES), image_pad=2,
                                 compile=c, **ALPHA),
}


@pytest.fixture(autouse=True)
def _one_thread():
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


def make(name: str, device_side: bool, device: str = "cpu", compile: str = "off") -> SACAgent:
    torch.manual_seed(0)
    agent = AGENTS[name](device, compile)
    agent.guard.device_side = device_side
    return agent


def batches(name: str, n: int, device: str = "cpu") -> list[tuple]:
    g = torch.Generator().manual_seed(1)
    if name == "DRQ":
        def obs() -> tuple:
            scalars = tuple(torch.rand(BATCH, 1, generator=g) for _ in range(3))
            frames = torch.randint(0, 256, (BATCH, 2, 16, 16), generator=g, dtype=torch.uint8)
            return (*scalars, frames, torch.rand(BATCH, 3, generator=g) * 2 - 1,
                    torch.rand(BATCH, 3, generator=g) * 2 - 1)
        act_dim = 3
    else:
        def obs() -> torch.Tensor:  # type: ignore[misc]
            return torch.randn(BATCH, 3, generator=g)
        act_dim = 1
    out = []
    for _ in range(n):
        b = (obs(), torch.rand(BATCH, act_dim, generator=g) * 2 - 1, torch.randn(BATCH, generator=g), obs(),
             (torch.rand(BATCH, generator=g) < 0.2).float(), torch.zeros(BATCH))
        out.append(tuple(tuple(t.to(device) for t in x) if isinstance(x, tuple) else x.to(device) for x in b))
    return out


def nan_reward(batch: tuple) -> tuple:
    rew = batch[2].clone()
    rew[3] = math.nan
    return batch[:2] + (rew,) + batch[3:]


def nan_gradient_param(name: str, agent: SACAgent) -> torch.Tensor | None:
    """A parameter whose gradient a hook makes NaN while the loss stays finite (None for the fused
    update, which computes its gradients without autograd). The policy's for the agents whose
    actor steps after the critics (a failure there keeps the critics' step)."""
    if name == "SAC-fused":
        return None
    if name in ("CROSSQ", "SAC-sequential"):
        return agent.actor.mu_layer.weight
    return agent.critics.parameters()[0]


@contextlib.contextmanager
def nan_gradient(param: torch.Tensor | None) -> Iterator[None]:
    handle = param.register_hook(lambda grad: grad * math.nan) if param is not None else None
    try:
        yield
    finally:
        if handle is not None:
            handle.remove()


def flat_state(agent: SACAgent) -> dict[str, Any]:
    """Everything an update may change: the checkpoint state (model and its running statistics,
    targets, optimizers with their step counts and moments, log(alpha), counters, kept losses)."""
    out: dict[str, Any] = {}

    def walk(obj: Any, path: str) -> None:
        if isinstance(obj, dict):
            for k, v in obj.items():
                walk(v, f"{path}/{k}")
        elif isinstance(obj, (list, tuple)):
            for i, v in enumerate(obj):
                walk(v, f"{path}/{i}")
        elif isinstance(obj, torch.Tensor):
            out[path] = obj.detach().cpu().clone()
        else:
            out[path] = obj

    walk(agent.state_dict(), "")
    out["loss_pi"], out["loss_alpha"] = agent.loss_pi.detach().cpu().clone(), agent.loss_alpha.detach().cpu().clone()
    return out


def assert_same(got: dict[str, Any], expected: dict[str, Any], skip: tuple[str, ...] = ()) -> None:
    assert set(got) == set(expected)
    for key, value in expected.items():
        if key in skip:
            continue
        if isinstance(value, torch.Tensor):
            assert torch.equal(got[key], value), key
        else:
            assert got[key] == value, key


def is_nan(value: Any) -> bool:
    return math.isnan(float(value))


# --- the device path keeps the host path's semantics, bit for bit ----------------------------------


@pytest.mark.parametrize("name", list(AGENTS))
def test_the_device_guard_gives_the_host_guards_updates_bit_for_bit(name: str):
    host, device = make(name, False), make(name, True)
    bad_grad = {id(device): nan_gradient_param(name, device), id(host): nan_gradient_param(name, host)}
    counts = []
    for i, b in enumerate(batches(name, 8)):
        snapshot = flat_state(device)
        results = []
        for agent in (host, device):
            torch.manual_seed(100 + i)
            if i == 2:  # a NaN reward: loss and gradients not finite
                results.append(agent.train(nan_reward(b)))
            elif i == 5:  # a NaN gradient under a finite loss (the fused update: NaN actions)
                param = bad_grad[id(agent)]
                bad = b if param is not None else b[:1] + (b[1] * math.nan,) + b[2:]
                with nan_gradient(param):
                    results.append(agent.train(bad))
            else:
                results.append(agent.train(b))
        if i >= 2:  # from the third update every optimizer has its state: the device decides
            assert device.guard._pending is not None and host.guard._pending is None
        assert_same(flat_state(device), flat_state(host))
        counts.append((device.guard.skipped, host.guard.skipped))
        if i == 2 or (i == 5 and name not in ("CROSSQ", "SAC-sequential")):
            # nothing changed (an update counter aside), the losses reported NaN
            assert_same(flat_state(device), snapshot, skip=("/i_update",))
            assert is_nan(results[1]["loss_critic"]) and is_nan(results[1]["loss_actor"])
    assert counts[-1] == (2, 2) and [c[0] for c in counts] == [0, 0, 1, 1, 1, 2, 2, 2]
    # the ceiling held the coefficient (it would have risen): the hold was exercised
    assert float(device.log_alpha.detach()) == device._log_alpha_max


@pytest.mark.parametrize("name", ["CROSSQ", "SAC-sequential"])
def test_a_bad_policy_step_after_the_critics_keeps_the_critics_step_on_the_device(name: str):
    """CrossQ and the sequential order step the critics (and, in the sequential order, the
    entropy coefficient) before the actor's loss is computed: a NaN actor gradient keeps that
    step (and CrossQ's statistics), not the actor's, the targets' or the actor optimizer's, on
    the device as on the host."""
    host, device = make(name, False), make(name, True)
    gen = batches(name, 4)
    for agent in (host, device):
        torch.manual_seed(3)
        for b in gen[:3]:
            agent.train(b)
    before = flat_state(device)
    for agent in (host, device):
        torch.manual_seed(4)
        with nan_gradient(agent.actor.mu_layer.weight):
            agent.train(gen[3])  # CrossQ: the 4th update steps its policy
    after = flat_state(device)
    assert_same(after, flat_state(host))
    moved = {k for k in before if isinstance(before[k], torch.Tensor) and not torch.equal(before[k], after[k])}
    assert any(k.startswith("/model/qs.") for k in moved) and any(k.startswith("/optimizer_critic/") for k in moved)
    assert not any(k.startswith(("/model/actor.", "/model_target/", "/optimizer_actor/")) for k in moved), moved
    assert any("running_mean" in k for k in moved) == (name == "CROSSQ")
    assert device.guard.skipped == host.guard.skipped == 1


def test_a_crossq_update_skipped_by_its_critics_changes_nothing_even_when_its_policy_was_due():
    """On the device the policy's half of a skipped CrossQ update still runs (masked): its actor,
    coefficient and their optimizers stay as they were all the same."""
    agent = make("CROSSQ", True)
    gen = batches("CROSSQ", 4)
    for b in gen[:3]:
        agent.train(b)
    before = flat_state(agent)
    metrics = agent.train(nan_reward(gen[3]))  # the 4th update: critics and policy
    assert_same(flat_state(agent), before, skip=("/i_update",))
    assert agent.guard.skipped == 1 and is_nan(metrics["loss_actor"]) and is_nan(metrics["debug_log_pi"])


def test_the_first_update_of_an_optimizer_is_checked_on_the_host():
    """Adam creates its state at its first step: an update before every stepping optimizer has
    its state is decided on the host (and skipped there, leaving no state behind)."""
    agent = make("SAC", True)
    metrics = agent.train(nan_reward(batches("SAC", 1)[0]))
    assert agent.guard._pending is None and agent.guard.skipped == 1 and is_nan(metrics["loss_critic"])
    assert not agent.q_optimizer.state and not agent.pi_optimizer.state
    agent.train(batches("SAC", 1)[0])
    assert agent.q_optimizer.state and agent._begin_update(True).on_device


def test_the_count_is_read_once_with_one_log_line(caplog):
    agent = make("SAC", True)
    gen = batches("SAC", 6)
    agent.train(gen[0])
    with caplog.at_level(logging.WARNING, logger="tmrl.algorithms.guard"):
        for b in gen[1:4]:
            agent.train(nan_reward(b))
        assert not caplog.records  # nothing read yet: nothing logged
        assert agent.skipped_updates == 3 and agent.guard._pending is None
        agent.train(gen[4])
        assert agent.skipped_updates == 3
    lines = [r.getMessage() for r in caplog.records]
    assert len(lines) == 1 and "skipped a training update" in lines[0] and "(3 skipped so far)" in lines[0]


def test_a_rollback_puts_back_exactly_what_it_copied_unless_the_flag_is_true():
    a = torch.randn(3, 4)
    b = torch.arange(5, dtype=torch.int64)
    c = torch.tensor(2.0)
    originals = [t.clone() for t in (a, b, c)]
    rollback = Rollback([a, b, c, a])  # one twice: copied once
    for t in (a, c):
        t.fill_(math.nan)
    b.add_(7)
    rollback.restore_unless(torch.tensor(True))
    assert torch.isnan(a).all() and torch.isnan(c) and torch.equal(b, originals[1] + 7)
    rollback.restore_unless(torch.tensor(False))
    assert all(torch.equal(t, o) for t, o in zip((a, b, c), originals))


def test_a_host_guarded_update_takes_no_copies():
    guard = NonFiniteGuard(device_side=False)
    g = GuardedUpdate(guard, on_device=False)
    p = torch.nn.Parameter(torch.ones(3))
    p.grad = torch.full((3,), math.nan)
    g.keep([p])
    assert not g._kept and not g.check(torch.tensor(1.0), [p]) and p.grad is None and guard.skipped == 1


# --- no host read per update ---------------------------------------------------------------------

_READS = ("__bool__", "__float__", "__int__", "__index__", "item", "tolist", "numpy")


class HostRead(AssertionError):
    pass


@contextlib.contextmanager
def no_host_reads(monkeypatch: pytest.MonkeyPatch) -> Iterator[None]:
    """Every Python-level read of a tensor's value raises inside the block."""
    with monkeypatch.context() as m:
        for attr in _READS:
            def read(self: torch.Tensor, *args: Any, _attr: str = attr, **kwargs: Any) -> Any:
                raise HostRead(f"Tensor.{_attr} read on the host during an update")

            m.setattr(torch.Tensor, attr, read)
        yield


@pytest.mark.parametrize("name", list(AGENTS))
def test_the_device_path_reads_no_tensor_on_the_host(name: str, monkeypatch):
    agent = make(name, True)
    gen = batches(name, 7)
    for b in gen[:2]:  # every optimizer's first step
        agent.train(b)
    with no_host_reads(monkeypatch):
        for i, b in enumerate(gen[2:]):
            agent.train(nan_reward(b) if i == 1 else b)
    assert agent.guard.skipped == 1
    # the same updates on the host path read: the check above can fail
    host = make(name, False)
    for b in gen[:2]:
        host.train(b)
    with no_host_reads(monkeypatch), pytest.raises(HostRead):
        host.train(gen[2])


@pytest.mark.gpu
@pytest.mark.parametrize("mode", ["off", "compile", "cudagraph"])
@pytest.mark.parametrize("name", list(AGENTS))
def test_cuda_updates_do_not_synchronise(name: str, mode: str):
    torch._dynamo.reset()
    agent = make(name, True, device="cuda", compile=mode)
    gen = batches(name, 12, "cuda")
    for b in gen[:6]:  # first steps, the first-update checks of both kinds, graph recordings
        agent.train(b)
    assert agent._compile_state.mode == (mode if name != "SAC-sequential" else "off")
    torch.cuda.synchronize()
    torch.cuda.set_sync_debug_mode("error")
    try:
        for i, b in enumerate(gen[6:]):
            agent.train(nan_reward(b) if i == 2 else b)
    finally:
        torch.cuda.set_sync_debug_mode("default")
    assert agent.guard.skipped == 1
    assert all(bool(torch.isfinite(p).all()) for p in agent.model.parameters())


@pytest.mark.parametrize("foreach", [True, False])
def test_a_rollback_puts_back_only_what_a_false_flag_refuses(monkeypatch, foreach):
    from tmrl.algorithms.guard import Rollback

    if not foreach:  # an older PyTorch without torch._foreach_copy_
        monkeypatch.delattr(torch, "_foreach_copy_")
    a, b = torch.arange(4.0), torch.ones(2, 3, dtype=torch.float64)
    saved = Rollback([a, b, a])
    a.add_(10.0)
    b.mul_(3.0)
    saved.restore_unless(torch.tensor(True))
    assert torch.equal(a, torch.arange(4.0) + 10) and torch.equal(b, torch.full((2, 3), 3.0, dtype=torch.float64))
    saved.restore_unless(torch.tensor(False))
    assert torch.equal(a, torch.arange(4.0)) and torch.equal(b, torch.ones(2, 3, dtype=torch.float64))
