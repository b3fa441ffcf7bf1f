"""The competition-style examples (docs/competition.md): examples/custom_agent.py (a TD3 training
agent of our own on Pendulum-v1) and examples/competition_sim.py (an actor module of our own on the
simulator's pipeline, trained by the configured SAC), run end to end with a tiny budget, plus unit
checks of the TD3 update and of the entry's model.
"""

from __future__ import annotations

import itertools
import json
import os
import re
import signal
import subprocess
import sys
from pathlib import Path

import gymnasium
import numpy as np
import pytest
import torch
from test_examples_usage import load_example, ok  # the other examples' helpers

ROOT = Path(__file__).resolve().parents[1]
EXAMPLES = ROOT / "examples"
ROUND = re.compile(r"^round (\d+)\.(\d+): (\d+) env steps, (\d+) updates", re.MULTILINE)
#: Smaller settings for the simulator runs (the shipped simlidar config trains 200 steps per round
#: after 1000 samples): rounds of 25 updates after 300 samples.
SMALL_SIM_RUN = {"TRAINING_STEPS_PER_ROUND": 25, "ENVIRONMENT_STEPS_BEFORE_TRAINING": 300, "BATCH_SIZE": 64,
                 "MEMORY_SIZE": 20000, "UPDATE_MODEL_INTERVAL": 5, "UPDATE_BUFFER_INTERVAL": 5}


def example_env(tmp_path: Path, override: dict | None = None) -> dict[str, str]:
    env = dict(os.environ, TMRL_DATA=str(tmp_path / "data"), OMP_NUM_THREADS="1")
    env.pop("TMRL_CONFIG_OVERRIDE", None)
    if override:
        env["TMRL_CONFIG_OVERRIDE"] = json.dumps(override)
    return env


def run_example(name: str, *args: str, tmp_path: Path, timeout: float = 120,
                override: dict | None = None) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, str(EXAMPLES / name), *args], cwd=tmp_path,
                          env=example_env(tmp_path, override), capture_output=True, text=True, timeout=timeout,
                          check=False)


def rounds(out: str) -> list[tuple[int, int]]:
    """``(env steps, updates)`` of each round line."""
    return [(int(m[2]), int(m[3])) for m in ROUND.findall(out)]


def assert_training_went_on(out: str) -> None:
    found = rounds(out)
    assert len(found) >= 2, out[-2000:]
    updates = [u for _, u in found]
    assert updates[0] > 0 and all(b > a for a, b in itertools.pairwise(updates)), updates


# --- examples/custom_agent.py: TD3 ------------------------------------------------------------------


@pytest.fixture(scope="module")
def td3():
    return load_example("custom_agent.py")


def pendulum_spaces():
    env = gymnasium.make("Pendulum-v1")
    try:
        return env.observation_space, env.action_space
    finally:
        env.close()


def random_batch(b: int = 32, terminated: float = 0.0):
    from tmrl.batch import Batch

    g = torch.Generator().manual_seed(0)
    obs = torch.rand((b, 3), generator=g) * 2 - 1
    act = torch.rand((b, 1), generator=g) * 4 - 2
    return Batch(obs, act, torch.rand(b, generator=g), torch.rand((b, 3), generator=g) * 2 - 1,
                 torch.full((b,), terminated), torch.zeros(b))


def params(module: torch.nn.Module) -> list[torch.Tensor]:
    return [p.detach().clone() for p in module.parameters()]


def changed(before: list[torch.Tensor], module: torch.nn.Module) -> bool:
    return any(not torch.equal(a, p) for a, p in zip(before, module.parameters()))


def test_td3_updates_the_actor_and_the_targets_every_policy_delay_updates(td3):
    torch.manual_seed(0)
    agent = td3.TD3Agent(*pendulum_spaces(), device="cpu", policy_delay=3, polyak=0.9)
    batch = random_batch()
    for call in range(1, 7):
        actor, q1 = params(agent.model.actor), params(agent.model.q1)
        target, online_before = params(agent.model_target), params(agent.model)
        metrics = agent.train(batch)
        assert changed(q1, agent.model.q1), "the critics learn at every update"
        policy_update = call % 3 == 0
        assert changed(actor, agent.model.actor) == policy_update, f"update {call}"
        assert changed(target, agent.model_target) == policy_update, f"update {call}"
        if policy_update:
            # target <- polyak target + (1 - polyak) online: each target moved towards its online
            # net, which is not touched by the averaging
            for t_old, t_new, online in zip(target, agent.model_target.parameters(), agent.model.parameters()):
                assert torch.allclose(t_new, 0.9 * t_old + 0.1 * online, atol=1e-6)
            assert not all(torch.equal(a, b) for a, b in zip(online_before, agent.model.parameters()))
        assert {"loss_critic", "loss_actor"} <= set(metrics)
    assert int(agent.updates) == 6


def test_td3_targets_do_not_bootstrap_on_terminated_transitions(td3):
    agent = td3.TD3Agent(*pendulum_spaces(), device="cpu")
    done = random_batch(terminated=1.0)
    assert torch.equal(agent.target_value(done), done.rew)
    going_on = random_batch(terminated=0.0)  # truncated or not, the future counts
    assert not torch.allclose(agent.target_value(going_on), going_on.rew)


def test_td3_state_dict_resumes_the_rhythm_and_the_networks(td3):
    spaces = pendulum_spaces()
    agent = td3.TD3Agent(*spaces, device="cpu")
    agent.train(random_batch())
    state = agent.state_dict()
    assert {"model", "model_target", "actor_optimizer", "critic_optimizer", "updates"} <= set(state)
    fresh = td3.TD3Agent(*spaces, device="cpu")
    fresh.load_state_dict(state)
    assert int(fresh.updates) == 1
    assert all(torch.equal(a, b) for a, b in zip(fresh.model_target.parameters(), agent.model_target.parameters()))


def test_custom_agent_trains_on_pendulum_and_its_weights_load(tmp_path, td3, port_factory):
    out = ok(run_example("custom_agent.py", "--minutes", "0.25", "--port", str(port_factory()), tmp_path=tmp_path,
                         timeout=100))
    assert_training_went_on(out)
    assert re.search(r"^done: best test return -?[\d.]+; the actor's weights are in", out, re.MULTILINE), out[-1000:]
    weights = tmp_path / "data" / "weights" / "custom_agent_td3.tmod"
    from safetensors.torch import load_file

    assert set(load_file(str(weights))) == {"net.0.weight", "net.0.bias", "net.2.weight", "net.2.bias",
                                            "net.4.weight", "net.4.bias"}  # tensors only, no buffers
    obs_space, act_space = pendulum_spaces()
    actor = td3.worker_actor_cls()(observation_space=obs_space, action_space=act_space).load(str(weights), "cpu")
    for test in (True, False):
        action = actor.act_(obs_space.sample(), test=test)
        assert action.shape == (1,) and act_space.contains(action.astype(np.float32))


# --- examples/competition_sim.py: the entry on the simulator ------------------------------------------


@pytest.fixture(scope="module")
def entry():
    return load_example("competition_sim.py")


def sim_env():
    import tmrl.sim  # noqa: F401 (registers the environments)

    return gymnasium.make("tmrl.sim:tmrl/SimLidar-v0", img_hist_len=4, act_buf_len=2)


def test_the_entry_reads_flat_or_shaped_lidar_and_sac_trains_it(entry):
    from tmrl.algorithms.sac import SACAgent
    from tmrl.driving.preprocessors import preprocess_lidar_obs

    env = sim_env()
    obs, _ = env.reset(seed=0)
    features = entry.LidarFeatures(env.observation_space)
    assert (features.lidar, features.hist) == (1, 4)
    from tmrl.actor import collate_one

    shaped, flat = collate_one(tuple(obs)), collate_one(preprocess_lidar_obs(obs))
    assert features(shaped).shape == (1, features.out_dim)
    assert torch.equal(features(shaped), features(flat))  # the preprocessor's flat lidar, the same features

    agent = SACAgent(env.observation_space, env.action_space, device="cpu", model_cls=entry.ConvLidarActorCritic)
    assert agent.fused_update is None  # a model of our own takes the autograd path
    b = 16
    batch_obs = tuple(o.repeat(b, 1) for o in flat)
    before = params(agent.model.actor)
    act = torch.rand((b, 3)) * 2 - 1
    agent.train((batch_obs, act, torch.rand(b), batch_obs, torch.zeros(b), torch.zeros(b)))
    assert changed(before, agent.model.actor)
    env.close()


def test_the_entry_weights_are_data_only_and_load_into_a_fresh_actor(entry, tmp_path):
    env = sim_env()
    a = entry.ConvLidarActorCritic(env.observation_space, env.action_space).actor
    a.save(tmp_path / "w.tmod")
    b = entry.ConvLidarActor(env.observation_space, env.action_space).load(tmp_path / "w.tmod", "cpu")
    obs, _ = env.reset(seed=1)
    assert np.array_equal(a.act_(tuple(obs), test=True), b.act_(tuple(obs), test=True))
    assert (tmp_path / "w.tmod").read_bytes()[8:9] == b"{"  # safetensors: a length, then a JSON header
    env.close()


def check_entry_weights(entry, path: Path) -> None:
    from tmrl.driving.preprocessors import preprocess_lidar_obs

    env = sim_env()
    actor = entry.ConvLidarActor(env.observation_space, env.action_space).load(path, "cpu")
    obs, _ = env.reset(seed=0)
    for test in (True, False):
        action = actor.act_(preprocess_lidar_obs(obs), test=test)
        assert action.shape == (3,) and env.action_space.contains(action.astype(np.float32))
    env.close()


def test_competition_sim_in_one_process_trains_and_counts_laps(tmp_path, entry, port_factory):
    out = ok(run_example("competition_sim.py", "--minutes", "0.25", "--port", str(port_factory()), tmp_path=tmp_path,
                         timeout=120, override=SMALL_SIM_RUN))
    assert_training_went_on(out)
    assert re.search(r"^round .* \| \d+ episodes, \d+ laps.*, best progress \d+%$", out, re.MULTILINE), out[-1000:]
    version = re.search(r"^worker: \d+ episodes, \d+ laps.*, weights version (\d+)$", out, re.MULTILINE)
    assert version and int(version[1]) >= 2, out[-1000:]  # the first broadcast, then training's
    data = tmp_path / "data"
    cfg = json.loads((data / "config" / "config.json").read_text())
    assert cfg["ENV"]["RTGYM_INTERFACE"] == "SIMLIDAR"  # created for the simulator
    assert (data / "logs" / "competition_sim" / "metrics.csv").is_file()  # as --trainer writes it
    assert (data / "checkpoints" / "competition_sim_t.tcpt").exists()
    for name in ("competition_sim_t.tmod", "competition_sim.tmod"):  # the trainer's and the worker's copies
        check_entry_weights(entry, data / "weights" / name)


@pytest.mark.posix
def test_competition_sim_as_three_roles(tmp_path, entry, port_factory):
    port = str(port_factory())
    env = example_env(tmp_path, SMALL_SIM_RUN)

    def start(*args: str) -> subprocess.Popen:
        return subprocess.Popen([sys.executable, str(EXAMPLES / "competition_sim.py"), *args, "--port", port],
                                cwd=tmp_path, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)

    server = start("--server")
    worker = start("--worker")
    trainer = start("--trainer", "--minutes", "0.25")
    try:
        t_out, t_err = trainer.communicate(timeout=120)
        assert trainer.returncode == 0, f"{t_out[-2000:]}\n{t_err[-3000:]}"
        assert_training_went_on(t_out)
        assert "trainer done:" in t_out
        worker.send_signal(signal.SIGINT)  # a worker runs until Ctrl-C
        w_out, w_err = worker.communicate(timeout=30)
        assert "Traceback" not in w_err, w_err[-3000:]
        assert re.search(r"^episode 1: return -?[\d.]+, progress \d+%", w_out, re.MULTILINE), w_out[-1000:]
        version = re.search(r"^worker stopped: .*weights version (\d+)$", w_out, re.MULTILINE)
        assert version and int(version[1]) >= 1, w_out[-1000:]
        check_entry_weights(entry, tmp_path / "data" / "weights" / "competition_sim.tmod")
    finally:
        for proc in (trainer, worker, server):
            if proc.poll() is None:
                proc.send_signal(signal.SIGINT)
        for proc in (trainer, worker, server):
            try:
                proc.communicate(timeout=20)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.communicate()


def test_competition_sim_refuses_a_config_without_lidar(tmp_path):
    from tmrl.config.loader import install

    install(tmp_path / "data", env="pendulum")
    out = run_example("competition_sim.py", "--minutes", "0.1", tmp_path=tmp_path, timeout=60)
    assert out.returncode == 1
    assert "config.json is set up for GYM" in out.stderr and "--install --env simlidar" in out.stderr
