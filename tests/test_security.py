"""Nothing a peer sends can stop or poison a run (issue 15), tested as an attacker with the
password would try it: hostile payloads come from a real ``WorkerLink``/``TrainerLink`` through a
real relay on 127.0.0.1 to a real ``Trainer``/``RolloutWorker``.

One test per defect: off-schema sample batches (1), non-finite values (2), a fake trainer (3),
relay memory (5), separated runs (7), the password on the wire (8), log floods and spurious
lines (9). Stopping (4) is in tests/test_security_stop.py, checkpoints (6) in
tests/test_checkpoint.py, the fuzz test in tests/test_security_fuzz.py.
"""

from __future__ import annotations

import logging
import math
import socket
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import gymnasium
import numpy as np
import pytest

from tmrl import wire
from tmrl.networking import Buffer, RolloutWorker, Trainer, TrainerInterface, pack_buffer, pack_weights
from tmrl.transport import RelayServer, TrainerLink, WorkerLink
from tmrl.transport.credentials import TRAINER_PUBLIC_KEY_FILE, TrainerKey, ensure_trainer_key
from tmrl.util import partial

sys.path.insert(0, str(Path(__file__).resolve().parent))
from test_networking import CountingEnv, JsonActor

pytestmark = pytest.mark.timeout(120)

PW = "security-test-password"
OBS = gymnasium.spaces.Box(-np.inf, np.inf, (3,), np.float32)
ACT = gymnasium.spaces.Box(-1.0, 1.0, (1,), np.float32)


# ------------------------------------------------------------------------------------------------
# helpers (also used by tests/test_security_fuzz.py and tests/test_security_stop.py)


def wait_for(cond: Callable[[], Any], timeout: float = 20.0, what: str = "condition") -> Any:
    """Poll ``cond`` until it is truthy (effects that happen in other processes)."""
    deadline = time.monotonic() + timeout
    while True:
        value = cond()
        if value:
            return value
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out waiting for {what}")
        time.sleep(0.02)


def genuine_payload(first: int, n: int, src: int = 7, seq: int = 0, run: str | None = None) -> dict:
    """A payload as a worker of the (OBS, ACT) environment packs it: ``obs[0]`` of each sample is
    its number (``first`` ... ``first + n - 1``), the first sample starts an episode."""
    buf = Buffer(maxlen=100_000)
    buf.source_id = src
    for i in range(first, first + n):
        act = None if i == first else np.array([0.5], np.float32)
        buf.append_sample((act, np.array([i, 0.0, 0.0], np.float32), 0.25, False, i == first + n - 1, {}))
    buf.stat_train_return = 1.5
    return pack_buffer(buf, src, seq, run=run)


def sac_training(memory_size: int = 10_000, spaces: tuple = (OBS, ACT), **kw: Any) -> Any:
    """A real, small SAC training class on ``spaces`` (by default those of CountingEnv)."""
    from tmrl.algorithms.sac import SACAgent
    from tmrl.memory import GenericTorchMemory
    from tmrl.models import MLPActorCritic
    from tmrl.training_offline import TorchTrainingOffline

    args = dict(
        env_cls=spaces,
        memory_cls=partial(GenericTorchMemory, memory_size=memory_size, batch_size=16),
        training_agent_cls=partial(SACAgent, model_cls=partial(MLPActorCritic, hidden_sizes=(16, 16))),
        epochs=1,
        rounds=1,
        steps=10,
        update_buffer_interval=5,
        update_model_interval=5,
        max_training_steps_per_env_step=1000.0,
        start_training=0,
        sleep_between_buffer_retrieval_attempts=0.01,
        device="cpu",
    )
    args.update(kw)
    return partial(TorchTrainingOffline, **args)


def make_trainer(tmp_path: Path, port: int, training: Any = None, **kw: Any) -> Trainer:
    # The workers' functions are given (none here): the schema comes from the spaces, as with --trainer.
    kw.setdefault("obs_preprocessor", None)
    kw.setdefault("sample_compressor", None)
    return Trainer(
        training_cls=training or sac_training(),
        server_ip="127.0.0.1",
        server_port=port,
        password=PW,
        security=None,
        header_size=10,
        keys_dir=str(tmp_path / "credentials"),
        model_path=str(tmp_path / "trainer.tmod"),
        checkpoint_path=kw.pop("checkpoint_path", None),
        **kw,
    )


def stored_firsts(memory: Any) -> list[int]:
    """``obs[0]`` of every sample the memory holds, oldest first."""
    n = min(memory.total, memory.capacity)
    if n == 0:
        return []
    return sorted(int(x) for x in memory.obs_leaf(0)[:n, 0])


def params_finite(agent: Any) -> bool:
    return all(bool(np.isfinite(p.detach().numpy()).all()) for p in agent.model.parameters())


def relay(port: int, tmp_path: Path | None = None, **kw: Any) -> RelayServer:
    kw.setdefault("security", None)
    return RelayServer(port, PW, **kw)


def attacker(port: int, **kw: Any) -> WorkerLink:
    """A worker link with the password, sending whatever it likes."""
    link = WorkerLink("127.0.0.1", port, PW, security=None, **kw)
    assert link.wait_connected(30)
    return link


@pytest.fixture
def closing():
    objs: list[Any] = []
    yield objs
    for o in reversed(objs):
        (o.stop if hasattr(o, "stop") else o.close)()


# ------------------------------------------------------------------------------------------------
# 1. sample batches are validated against the run's schema before the memory


def _mutate(payload: dict, how: str) -> dict:
    cols = payload["cols"]
    n = payload["n"]
    obs = cols[1][1]
    if how == "obs of another shape":
        cols[1] = ("A", np.zeros((n, 4), np.float32))
    elif how == "action of the wrong size":
        cols[0] = ("N", cols[0][1], ("A", np.zeros((n - 1, 2), np.float32)))
    elif how == "a (0, 2**40) observation":
        cols[1] = ("A", np.zeros((n, 0, 2**40), np.float32))
    elif how == "strings":
        cols[1] = ("R", ["not a number"] * n)
    elif how == "NaN observation":
        obs[n // 2, 1] = np.nan
    elif how == "infinite reward":
        cols[2] = ("F", np.full(n, np.inf))
    elif how == "reward beyond float32":
        cols[2] = ("F", np.full(n, 1e300))
    elif how == "complex observation":
        cols[1] = ("A", obs.astype(np.complex64))
    elif how == "integer observation":
        cols[1] = ("A", obs.astype(np.int64))
    elif how == "bool observation":
        cols[1] = ("A", obs > 0)
    elif how == "action outside the space":
        cols[0][2][1][:] = 5.0
    elif how == "NaN action":
        cols[0][2][1][0] = np.nan
    elif how == "float flags":
        cols[3] = ("F", np.full(n, 0.5))
    elif how == "tuple where the run has an array":
        cols[1] = ("T", [("A", obs), ("A", obs)])
    elif how == "None observations":
        cols[1] = ("0",)
    else:
        raise AssertionError(how)
    return payload


HOSTILE = [
    "obs of another shape",
    "action of the wrong size",
    "a (0, 2**40) observation",
    "strings",
    "NaN observation",
    "infinite reward",
    "reward beyond float32",
    "complex observation",
    "integer observation",
    "bool observation",
    "action outside the space",
    "NaN action",
    "float flags",
    "tuple where the run has an array",
    "None observations",
]


def test_off_schema_batches_are_dropped_and_the_first_payload_never_decides_shapes(
    tmp_path, port_factory, closing, caplog
):
    caplog.set_level(logging.INFO, logger="tmrl")
    port = port_factory()
    closing.append(relay(port))
    trainer = make_trainer(tmp_path, port)
    closing.append(trainer.interface)
    run = trainer._load_or_create()
    assert trainer.interface.wait_connected(30)
    bad = attacker(port)
    closing.append(bad)
    # Hostile payloads FIRST (a fresh trainer's memory has no shapes yet), then a genuine worker.
    for i, how in enumerate(HOSTILE):
        bad.send_samples(_mutate(genuine_payload(1000 * (i + 1), 10, src=666, seq=i), how))
    good = attacker(port)
    closing.append(good)
    good.send_samples(genuine_payload(0, 20, src=7, seq=0))
    good.send_samples(genuine_payload(20, 20, src=7, seq=1))
    iface = trainer.interface
    wait_for(
        lambda: run.update_buffer(iface) >= 0 and run.memory.total >= 40 and iface.rejected_batches >= len(HOSTILE),
        what="every batch to arrive",
    )
    assert iface.rejected_batches == len(HOSTILE)
    assert stored_firsts(run.memory) == list(range(40))  # exactly the genuine samples
    assert run.memory.obs_leaf(0).shape[1:] == (3,) and run.memory.obs_leaf(0).dtype == np.float32
    # one rate-limited line per second, naming the worker and the first problem
    lines = [r.getMessage() for r in caplog.records if "dropped a sample batch" in r.getMessage()]
    assert 1 <= len(lines) < len(HOSTILE)
    assert "worker 666" in lines[0] and "obs has shape (4,) where the run expects (3,)" in lines[0]
    stats = run.run_epoch(iface)  # the trainer goes on training on what it has
    assert stats[-1]["rejected_batches"] == len(HOSTILE) and params_finite(run.agent)


def test_non_finite_episode_statistics_are_dropped(tmp_path, port_factory, closing):
    port = port_factory()
    closing.append(relay(port))
    iface = TrainerInterface(server_ip="127.0.0.1", server_port=port, password=PW, security=None,
                             header_size=10, keys_dir=str(tmp_path / "k"), model_path=str(tmp_path / "t.tmod"))
    closing.append(iface)
    link = attacker(port)
    closing.append(link)
    payload = genuine_payload(0, 5, src=9)
    payload["stats"] = {"stat_train_return": math.nan, "stat_test_return": math.inf,
                        "stat_train_steps": True, "stat_test_steps": 12}
    link.send_samples(payload)
    got = wait_for(lambda: (b := iface.retrieve_buffer()) and len(b) and b, what="the batch")
    assert got.stats[9] == {"stat_test_steps": 12}
    assert math.isfinite(got.stat_train_return) and math.isfinite(got.stat_test_return)


# ------------------------------------------------------------------------------------------------
# 2. non-finite losses, gradients and parameters never reach the weights or a checkpoint


def _batch(n: int = 16, rew: float = 0.0) -> tuple:
    import torch

    o = (torch.zeros(n, 3),)
    return o, torch.zeros(n, 1), torch.full((n,), rew), o, torch.zeros(n), torch.zeros(n)


@pytest.mark.parametrize("agent_name", ["sac", "redq"])
def test_a_non_finite_update_is_skipped_and_counted(agent_name, caplog):
    import torch

    from tmrl.algorithms.redq import REDQSACAgent
    from tmrl.algorithms.sac import SACAgent
    from tmrl.models import MLPActorCritic, REDQMLPActorCritic

    if agent_name == "sac":
        agent = SACAgent(OBS, ACT, "cpu", model_cls=partial(MLPActorCritic, hidden_sizes=(8, 8)))
    else:
        agent = REDQSACAgent(OBS, ACT, "cpu", model_cls=partial(REDQMLPActorCritic, hidden_sizes=(8, 8)), n=3)
    agent.train(_batch())
    before = [p.detach().clone() for p in agent.model.parameters()]
    target = [p.detach().clone() for p in agent.model_target.parameters()]
    for _ in range(3):
        agent.train(_batch(rew=math.nan))
    assert agent.skipped_updates == 3
    assert all(torch.equal(a, b) for a, b in zip(before, agent.model.parameters()))
    assert all(torch.equal(a, b) for a, b in zip(target, agent.model_target.parameters()))
    warnings = [r for r in caplog.records if "skipped a training update" in r.getMessage()]
    assert len(warnings) == 1  # logged once, then summarised
    agent.train(_batch())  # and training goes on
    assert agent.skipped_updates == 3 and params_finite(agent)


def test_the_last_good_state_is_a_copy_that_reuses_its_own_tensors():
    import torch

    from tmrl.algorithms.guard import copy_state_into
    from tmrl.algorithms.sac import SACAgent
    from tmrl.models import MLPActorCritic

    agent = SACAgent(OBS, ACT, "cpu", model_cls=partial(MLPActorCritic, hidden_sizes=(8, 8)))
    agent.train(_batch())  # the optimizers hold state too
    live = agent.state_dict()
    snap = copy_state_into(None, live)
    kept = {k: v.clone() for k, v in snap["model"].items()}
    with torch.no_grad():
        for p in agent.model.parameters():
            p.add_(1.0)  # the live state moves on...
    for key, value in snap["model"].items():  # ...the copy does not
        assert torch.equal(value, kept[key]) and value.data_ptr() != live["model"][key].data_ptr()
    ptrs = {k: v.data_ptr() for k, v in snap["model"].items()}
    again = copy_state_into(snap, agent.state_dict())
    for key, value in again["model"].items():  # the next copy lands in the same tensors
        assert value.data_ptr() == ptrs[key] and torch.equal(value, agent.model.state_dict()[key])
    adam = again["optimizer_critic"]["state"]
    assert adam and all(torch.is_tensor(s["exp_avg"]) for s in adam.values())
    assert again["optimizer_critic"]["param_groups"] == live["optimizer_critic"]["param_groups"]


def test_non_finite_parameters_are_restored_and_never_broadcast_or_saved(tmp_path, port_factory, closing):
    import torch

    from tmrl.checkpoint import CheckpointError, save_checkpoint

    port = port_factory()
    closing.append(relay(port))
    trainer = make_trainer(tmp_path, port, sac_training(spaces=_pendulum_spaces()))
    closing.append(trainer.interface)
    run = trainer._load_or_create()  # broadcasts the (finite) initial actor
    w = RolloutWorker(env_cls=lambda: gymnasium.make("Pendulum-v1"), actor_module_cls=_pendulum_actor(),
                      server_ip="127.0.0.1", server_port=port, password=PW, security=None, header_size=10,
                      keys_dir=str(tmp_path / "credentials"), model_path=str(tmp_path / "w.tmod"),
                      model_history=0)
    closing.append(w)
    assert w.update_actor_weights(verbose=False, blocking=True) == 1
    first = next(run.agent.model.parameters())
    with torch.no_grad():
        first[0, 0] = math.nan
    with pytest.raises(CheckpointError, match="NaN or infinite"):
        save_checkpoint(run, tmp_path / "ckpt")
    assert not (tmp_path / "ckpt" / "checkpoint.json").exists()
    # the training loop restores the last good state before it broadcasts
    assert run.ensure_finite() and run.restored_states == 1 and params_finite(run.agent)
    # an actor with NaN weights is neither kept as the trainer's model file nor sent
    with torch.no_grad():
        first[0, 0] = math.nan
    before = (tmp_path / "trainer.tmod").read_bytes()
    trainer.interface.broadcast_model(run.agent.get_actor())
    assert trainer.interface.skipped_broadcasts == 1
    assert (tmp_path / "trainer.tmod").read_bytes() == before
    assert w._link.latest_weights(block=True, timeout=1.0) is None  # nothing was sent


def _pendulum_spaces() -> tuple:
    env = gymnasium.make("Pendulum-v1")
    return env.observation_space, env.action_space


def _pendulum_actor() -> Any:
    from tmrl.models import SquashedGaussianMLPActor

    return partial(SquashedGaussianMLPActor, hidden_sizes=(16, 16))


# ------------------------------------------------------------------------------------------------
# 3. weights are the trainer's: a fake trainer cannot crash or poison the workers


def _worker(tmp_path: Path, port: int, name: str = "w", keys: Path | None = None) -> RolloutWorker:
    return RolloutWorker(
        env_cls=CountingEnv,
        actor_module_cls=JsonActor,
        server_ip="127.0.0.1",
        server_port=port,
        password=PW,
        security=None,
        header_size=10,
        keys_dir=str(keys or tmp_path / "worker_credentials"),
        model_path=str(tmp_path / f"{name}.json"),
        model_history=0,
        max_samples_per_episode=5,
    )


def _json_weights(bias: float) -> bytes:
    return ('{"bias": %s}' % bias).encode()


def _nan_safetensors() -> bytes:
    from safetensors.numpy import save

    return save({"w": np.array([1.0, np.nan], np.float32)})


def test_a_fake_trainer_cannot_crash_workers_even_through_the_stored_broadcast(tmp_path, port_factory, closing, caplog):
    port = port_factory()
    closing.append(relay(port))
    w = _worker(tmp_path, port)
    closing.append(w)
    assert w.wait_connected(30)
    fake = TrainerLink("127.0.0.1", port, PW, security=None)  # the slot is free: it gets in
    closing.append(fake)
    assert fake.wait_connected(30)
    spaces = {"observation": {"type": "Box", "shape": [9], "dtype": "float32"}, "action": None}
    junk = [
        b"garbage, not an envelope",
        pack_weights(_json_weights(1.0), spaces, 1),  # other spaces
        pack_weights(_nan_safetensors(), None, 2),  # NaN weights
        pack_weights(b"{not json", None, 3),  # a file the actor cannot load
    ]
    for envelope in junk:
        fake.broadcast_weights(envelope)
        assert w.update_actor_weights(verbose=False, blocking=True) == 0  # never raises
        assert w.actor.bias == 0.0 and not (tmp_path / "w.json").exists()
    assert w.rejected_weights == len(junk)
    # the relay keeps the last junk and gives it to every worker that connects: it goes on too
    late = _worker(tmp_path, port, "late")
    closing.append(late)
    assert late.update_actor_weights(verbose=False, blocking=True) == 0
    late.collect_train_episode()
    late.send_and_clear_buffer()
    # a worker restarted over a junk model file starts (one line), with a fresh actor
    (tmp_path / "w2.json").write_bytes(b"\x00junk")
    restarted = _worker(tmp_path, port, "w2")
    closing.append(restarted)
    assert restarted.actor.bias == 0.0
    assert any("ignored the weights file" in r.getMessage() for r in caplog.records)
    # good weights still load
    fake.broadcast_weights(pack_weights(_json_weights(0.75), None, 5))
    assert w.update_actor_weights(verbose=False, blocking=True) == 1 and w.actor.bias == 0.75
    assert (tmp_path / "w.json").read_bytes() == _json_weights(0.75)


def test_two_workers_sharing_a_model_path_take_the_same_weights_at_once(tmp_path, port_factory, closing):
    """Two workers of one machine with one data folder: B takes the broadcast while A is loading it
    (A's load runs B's update), and both end with the weights, nothing left behind."""
    port = port_factory()
    closing.append(relay(port))
    a, b = _worker(tmp_path, port, "shared"), _worker(tmp_path, port, "shared")
    closing += [a, b]
    fake = TrainerLink("127.0.0.1", port, PW, security=None)
    closing.append(fake)
    assert a.wait_connected(30) and b.wait_connected(30) and fake.wait_connected(30)
    fake.broadcast_weights(pack_weights(_json_weights(0.5), None, 1))
    load = a.actor.load

    def load_while_b_takes_them(path, device):
        assert b.update_actor_weights(verbose=False, blocking=True) == 1
        return load(path, device)

    a.actor.load = load_while_b_takes_them
    assert a.update_actor_weights(verbose=False, blocking=True) == 1
    assert a.actor.bias == 0.5 and b.actor.bias == 0.5 and a.rejected_weights == b.rejected_weights == 0
    assert (tmp_path / "shared.json").read_bytes() == _json_weights(0.5)
    assert not list(tmp_path.glob(".shared.json*"))


def test_run_synchronous_counts_the_broadcasts_a_worker_never_saw(tmp_path, port_factory, closing):
    """A worker keeps only the newest weights: three broadcasts it did not read in time arrive as
    one. Pacing by models received counts the trainer's versions, so it does not wait forever for
    models the trainer already made (and the trainer, waiting for samples, will not make)."""
    port = port_factory()
    closing.append(relay(port))
    w = _worker(tmp_path, port)
    closing.append(w)
    fake = TrainerLink("127.0.0.1", port, PW, security=None)
    closing.append(fake)
    assert w.wait_connected(30) and fake.wait_connected(30)
    fake.broadcast_weights(pack_weights(_json_weights(0.1), None, 1))
    assert w.update_actor_weights(verbose=False, blocking=True) == 1 and w.weights_version == 1
    for version in (2, 3, 4):
        fake.broadcast_weights(pack_weights(_json_weights(0.1 * version), None, version))
    deadline = time.monotonic() + 30  # until the three broadcasts have reached the worker as one
    while b'{"bias": 0.4' not in (w._link._weights or b"") and time.monotonic() < deadline:
        time.sleep(0.01)
    assert b'{"bias": 0.4' in (w._link._weights or b"")
    result: list[int] = []
    # 3 steps taken, 1 model so far, at most 1 step per model: it needs models 2, 3 and 4
    waiter = threading.Thread(target=lambda: result.append(w._wait_for_models(3, 1, 1.0, False, False)), daemon=True)
    waiter.start()
    waiter.join(20)
    stuck = waiter.is_alive()
    if stuck:  # the bug: it waits for a fifth broadcast; give it one so that the thread ends
        fake.broadcast_weights(pack_weights(_json_weights(0.5), None, 5))
        waiter.join(20)
    assert not stuck and result == [4] and w.weights_version == 4 and w.actor.bias == pytest.approx(0.4)


def test_a_torch_worker_refuses_non_finite_or_misshapen_weights(tmp_path, port_factory, closing):
    from safetensors.numpy import save

    port = port_factory()
    closing.append(relay(port))
    w = RolloutWorker(env_cls=lambda: gymnasium.make("Pendulum-v1"), actor_module_cls=_pendulum_actor(),
                      server_ip="127.0.0.1", server_port=port, password=PW, security=None, header_size=10,
                      keys_dir=str(tmp_path / "k"), model_path=str(tmp_path / "w.tmod"), model_history=0)
    closing.append(w)
    fake = TrainerLink("127.0.0.1", port, PW, security=None)
    closing.append(fake)
    assert w.wait_connected(30) and fake.wait_connected(30)
    mine = {k: v.numpy().copy() for k, v in w.actor.state_dict().items()}
    poisoned = dict(mine)
    name = next(iter(poisoned))
    poisoned[name] = np.full_like(poisoned[name], np.nan)  # the right names and shapes, NaN values
    # other values everywhere, one tensor of another shape: a plain load would copy the others
    misshapen = {k: v + 1 for k, v in mine.items()}
    last = list(misshapen)[-1]
    misshapen[last] = np.zeros((2, *mine[last].shape), mine[last].dtype)
    for tensors in (poisoned, misshapen):
        fake.broadcast_weights(pack_weights(save(tensors), None, 1))
        assert w.update_actor_weights(verbose=False, blocking=True) == 0
        for k, v in w.actor.state_dict().items():  # the actor is untouched, not half-loaded
            assert np.array_equal(v.numpy(), mine[k])
    assert not (tmp_path / "w.tmod").exists() and w.rejected_weights == 2


def test_workers_that_pin_the_trainer_key_load_its_weights_only(tmp_path, port_factory, closing):
    keys = tmp_path / "worker_keys"
    real = ensure_trainer_key(tmp_path / "trainer_keys")
    keys.mkdir()
    (keys / TRAINER_PUBLIC_KEY_FILE).write_bytes(real.public_pem)  # copied as the docs say
    port = port_factory()
    closing.append(relay(port))
    w = _worker(tmp_path, port, keys=keys)
    closing.append(w)
    fake = TrainerLink("127.0.0.1", port, PW, security=None)
    closing.append(fake)
    assert w.wait_connected(30) and fake.wait_connected(30)
    other = TrainerKey(ensure_trainer_key(tmp_path / "attacker").private_pem)
    for envelope in (pack_weights(_json_weights(9.0), None, 1),  # unsigned
                     pack_weights(_json_weights(9.0), None, 2, key=other)):  # another key
        fake.broadcast_weights(envelope)
        assert w.update_actor_weights(verbose=False, blocking=True) == 0 and w.actor.bias == 0.0
    tampered = bytearray(pack_weights(_json_weights(3.0), None, 3, key=real))
    tampered[-2:-1] = b"9"  # same size, other content: the signed checksum no longer matches
    fake.broadcast_weights(bytes(tampered))
    assert w.update_actor_weights(verbose=False, blocking=True) == 0 and w.actor.bias == 0.0
    fake.broadcast_weights(pack_weights(_json_weights(3.0), None, 4, key=real))
    assert w.update_actor_weights(verbose=False, blocking=True) == 1 and w.actor.bias == 3.0


def test_a_relay_that_pins_the_trainer_key_refuses_any_other_trainer(tmp_path, port_factory, closing, caplog):
    keys = tmp_path / "credentials"
    port = port_factory()
    real = ensure_trainer_key(keys)  # the trainer ran once on this machine: the key is pinned
    closing.append(relay(port, trainer_key_file=keys / TRAINER_PUBLIC_KEY_FILE))
    impostor = TrainerLink("127.0.0.1", port, PW, security=None,
                           trainer_key=ensure_trainer_key(tmp_path / "other"))
    closing.append(impostor)
    keyless = TrainerLink("127.0.0.1", port, PW, security=None)
    closing.append(keyless)
    wait_for(lambda: impostor.refused and keyless.refused, what="both refusals")
    assert "does not hold the trainer key" in impostor.refused and not impostor.connected
    trainer = TrainerLink("127.0.0.1", port, PW, security=None, trainer_key=real)
    closing.append(trainer)
    assert trainer.wait_connected(30)


# ------------------------------------------------------------------------------------------------
# 5. relay memory is bounded overall


class _RawLink:
    """A hand-made connection speaking the relay protocol, able to stop half-way."""

    def __init__(self, port: int):
        from tmrl.transport._netproc import session_token

        self.sock = socket.create_connection(("127.0.0.1", port), timeout=20)
        env = self._read()
        self.token = session_token(PW.encode(), env[2])
        self.send((1, "HELLO", None, ("workers",)))
        assert self._read()[1] == "WELCOME"

    def _exact(self, n: int) -> bytes:
        data = b""
        while len(data) < n:
            chunk = self.sock.recv(n - len(data))
            if not chunk:
                raise ConnectionError("closed")
            data += chunk
        return data

    def _read(self) -> Any:
        return wire.decode(self._exact(int(self._exact(10))))

    def send(self, env: Any) -> None:
        body = wire.encode(env)
        self.sock.sendall(f"{len(body):<10}".encode() + self.token + body)

    def closed(self, timeout: float = 20.0) -> bool:
        self.sock.settimeout(timeout)
        try:
            while self.sock.recv(65536):
                pass
            return True
        except (ConnectionResetError, BrokenPipeError):
            return True
        except TimeoutError:
            return False


def test_relay_memory_has_a_budget_and_half_sent_objects_a_timeout(port_factory, closing, caplog):
    caplog.set_level(logging.INFO, logger="tmrl.transport")
    port = port_factory()
    mib = 1 << 20
    closing.append(relay(port, header_size=10, max_total_bytes=5 * mib, partial_timeout=1.5))
    chunk = b"x" * (mib - 4096)
    raws = [_RawLink(port) for _ in range(3)]
    for k, raw in enumerate(raws):  # each sends 2 of the 3 parts of an object, then stalls
        for idx in range(2):
            raw.send((2 + idx, "OBJ", {"trainers": 1}, ((k, 1), idx, 3, 3 * len(chunk), chunk)))
            time.sleep(0.05)
    # the third would take the relay past its budget: closed at once, with one line
    assert raws[2].closed(10)
    # (the relay's log lines come from its own process: wait for them rather than read them once)
    wait_for(lambda: any("memory budget" in r.getMessage() and "SERVER_MEMORY_BYTES" in r.getMessage()
                         for r in caplog.records), what="the memory budget line")
    # the two others are closed once their half-sent object has waited partial_timeout
    assert raws[0].closed(10) and raws[1].closed(10)
    wait_for(lambda: any("no part of a message for 2 s" in r.getMessage() for r in caplog.records),
             what="the half-sent object timeout line")
    # the memory they held is free again: a genuine worker and trainer still get through
    worker = WorkerLink("127.0.0.1", port, PW, security=None)
    trainer = TrainerLink("127.0.0.1", port, PW, security=None)
    closing.extend([worker, trainer])
    worker.send_samples(np.zeros(mib // 2, np.float32))  # 2 MiB
    got = wait_for(lambda: trainer.receive_samples(), what="the sample object")
    assert got[0].shape == (mib // 2,)


def test_relay_caps_workers_by_default(port_factory, closing):
    from tmrl.transport.relay import DEFAULT_MAX_WORKERS

    port = port_factory()
    closing.append(relay(port))
    raws = [_RawLink(port) for _ in range(DEFAULT_MAX_WORKERS)]
    with pytest.raises((AssertionError, ConnectionError)):
        _RawLink(port)  # refused instead of WELCOMEd
    for raw in raws:
        raw.sock.close()


# ------------------------------------------------------------------------------------------------
# 7. runs are separated


def test_a_new_run_drops_samples_made_for_the_previous_one(tmp_path, port_factory, closing):
    port = port_factory()
    closing.append(relay(port))
    first = make_trainer(tmp_path, port, sac_training(spaces=_pendulum_spaces()))
    first_run = first._load_or_create()  # a fresh run: identity A, broadcast at once
    w = RolloutWorker(env_cls=lambda: gymnasium.make("Pendulum-v1"), actor_module_cls=_pendulum_actor(),
                      server_ip="127.0.0.1", server_port=port, password=PW, security=None, header_size=10,
                      keys_dir=str(tmp_path / "credentials"), model_path=str(tmp_path / "w.tmod"),
                      model_history=0, max_samples_per_episode=10)
    closing.append(w)
    assert w.update_actor_weights(verbose=False, blocking=True) == 1 and w.run_id == first.run_id
    first.interface.close()
    # made with run A's weights, queued at the relay while no trainer is connected
    for _ in range(3):
        w.collect_train_episode()
        w.send_and_clear_buffer()
    second = make_trainer(tmp_path, port, sac_training(spaces=_pendulum_spaces()))
    closing.append(second.interface)
    run = second._load_or_create()  # a fresh run again: identity B
    assert second.run_id != first.run_id and first_run is not run
    wait_for(lambda: run.update_buffer(second.interface) >= 0 and second.interface.foreign_batches == 3,
             what="the previous run's batches")
    assert run.memory.total == 0
    # the worker gets run B's weights (broadcast at start) and its samples count again
    assert w.update_actor_weights(verbose=False, blocking=True) == 1 and w.run_id == second.run_id
    w.collect_train_episode()
    w.send_and_clear_buffer()
    wait_for(lambda: run.update_buffer(second.interface) >= 0 and run.memory.total == 11, what="run B's samples")


# ------------------------------------------------------------------------------------------------
# 8. the password never crosses the network


def test_the_password_is_never_sent_even_over_plain_tcp(port_factory, closing):
    from tmrl.transport._netproc import session_token

    server = socket.socket()
    server.bind(("127.0.0.1", 0))
    server.listen(1)
    port = server.getsockname()[1]
    nonce = b"n" * 32
    received = bytearray()

    def fake_relay() -> None:
        conn, _ = server.accept()
        hello = wire.encode((0, "HELLO", nonce))
        conn.sendall(f"{len(hello):<10}".encode() + hello)
        conn.settimeout(5)
        try:
            while len(received) < 200:
                data = conn.recv(4096)
                if not data:
                    break
                received.extend(data)
        except OSError:
            pass
        conn.close()

    t = threading.Thread(target=fake_relay, daemon=True)
    t.start()
    link = WorkerLink("127.0.0.1", port, PW, security=None, header_size=10)
    closing.append(link)
    t.join(15)
    server.close()
    assert received, "the link sent nothing"
    assert PW.encode() not in received
    assert session_token(PW.encode(), nonce) in received  # what it sends instead


def test_docs_give_one_tls_default():
    from tmrl.config.schema import SCHEMA

    assert SCHEMA.fields["TLS"].default is False
    root = Path(__file__).resolve().parents[1]
    text = " ".join(
        (root / name).read_text() for name in (
            "README.md", "docs/networking.md", "docs/transport.md", "docs/security.md", "docs/deployment.md"
        )
    )
    assert "TLS is on by default" not in text and "TLS is off by default" in text


# ------------------------------------------------------------------------------------------------
# 9. logs: no floods, no spurious lines


def test_a_disconnected_worker_logs_drops_once_a_second(port_factory, closing, caplog):
    caplog.set_level(logging.INFO, logger="tmrl.transport")
    link = WorkerLink("127.0.0.1", port_factory(), PW, security=None, max_store=2)  # no relay there
    closing.append(link)
    for i in range(200):
        link.send_samples(i)
    time.sleep(0.1)
    wait_for(lambda: any("dropped the oldest unsent object" in r.getMessage() for r in caplog.records),
             what="the first drop line")
    lines = [r.getMessage() for r in caplog.records if "dropped the oldest" in r.getMessage()]
    assert len(lines) <= 3  # 198 drops


def test_a_busy_port_gives_no_spurious_relay_line(port_factory, caplog):
    from tmrl.errors import UserError

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        s.listen(1)
        port = s.getsockname()[1]
        with pytest.raises(UserError, match="already in use"):
            RelayServer(port, PW, security=None)
        time.sleep(0.3)
    assert not any("exited unexpectedly" in r.getMessage() for r in caplog.records)
