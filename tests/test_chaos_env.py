"""The environment parts of ``python -m bench chaos --env sim`` (bench/chaos_env.py) fit together,
without a fault schedule nor any process: a worker built from them drives the simulator, its
samples cross the wire format and the trainer's sample schema into the trainer's replay memory,
a training step runs on them, and the trainer's actor, saved as a ``.tmod`` file, loads into the
worker's actor and into the evaluation, which returns a test return.
"""

from __future__ import annotations

import math
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from bench import chaos_env


def _sim_profile() -> dict:
    p = chaos_env.profile("sim", "test", {})
    p.update(rate=1e6, ep_max_length=300, batch_size=32)  # as fast as it goes; short episodes
    return p


@pytest.mark.timeout(120)
def test_sim_worker_samples_train_the_trainer_and_its_weights_evaluate(tmp_path):
    import numpy as np
    import torch

    from tmrl import wire
    from tmrl.distributed import pack_buffer, unpack_buffer
    from tmrl.networking import RolloutWorker
    from tmrl.spaces import SampleSchema

    torch.manual_seed(0)
    p = _sim_profile()
    worker = RolloutWorker(**chaos_env.worker_parts("sim", p), device="cpu", standalone=True, model_history=0,
                           max_samples_per_episode=p["episode"], model_path=str(tmp_path / "worker.tmod"))
    collect = chaos_env.collector("sim", p)
    calls = 0
    while collect.episodes == 0:  # one whole episode, in payloads of `chunk` steps
        collect(worker)
        calls += 1
        assert calls <= p["ep_max_length"] // p["chunk"] + 1, "the episode did not end at ep_max_length"
    n = len(worker.buffer)
    assert n == worker.buffer.stat_train_steps + 1  # the reset's sample and one per step
    assert calls == math.ceil(worker.buffer.stat_train_steps / p["chunk"])

    run = chaos_env.training_cls("sim", p)()
    schema = SampleSchema(run.agent.observation_space, run.agent.action_space, **chaos_env.trainer_parts("sim", p))
    payload = wire.decode(wire.encode(pack_buffer(worker.buffer, worker.source_id, 0)))
    run.memory.append(unpack_buffer(payload, schema=schema))  # raises SampleRejected off the schema
    assert len(run.memory) == n - 1  # one transition per step after the reset
    assert len(run.memory) >= p["batch_size"]

    before = [t.detach().clone() for t in run.agent.get_actor().parameters()]
    losses = run.agent.train(run.memory.sample())
    assert all(math.isfinite(float(v)) for v in losses.values()), losses
    after = list(run.agent.get_actor().parameters())
    assert any(not torch.equal(a, b) for a, b in zip(before, after)), "the training step changed nothing"

    path = tmp_path / "trainer.tmod"
    run.agent.get_actor().save(path)
    worker.actor = worker.actor.load(str(path), device="cpu")
    obs, _ = worker.reset(collect_samples=False)
    assert np.allclose(worker.act(obs, test=True), run.agent.get_actor().act_(obs, test=True))

    evaluation = chaos_env.Evaluation("sim", p)
    evaluation.load(path)
    ret = evaluation.test_return(3)
    assert isinstance(ret, float) and math.isfinite(ret)
    assert 0.0 <= evaluation.extra["progress"] <= 1.0
    assert evaluation.test_return(1) == ret  # the simulator's deterministic episodes are all one


def test_pendulum_keeps_the_chaos_profile_and_unknown_envs_are_refused():
    base = {"rate": 250.0, "episode": 200}
    assert chaos_env.profile("pendulum", "bench", base) is base
    with pytest.raises(ValueError, match="unknown chaos environment"):
        chaos_env.profile("cartpole", "bench", base)
