"""tmrl.config.config_objects on the simulator (SIM*) and TrackMania (TM20*) interfaces: the objects
``--server/--trainer/--worker`` are built from, and the whole sample path on the simulator
(environment -> worker -> compressor -> wire format -> replay memory -> agent -> weights back to
the worker's policy). Also the CLI's dispatch that depends on the interface.

config_objects reads the configuration when imported: every test imports a fresh copy (and puts
the previous modules back afterwards, so that other tests see no trace of it).
"""

from __future__ import annotations

import importlib
import json
import os
import shutil
import subprocess
import sys
import textwrap
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch
from conftest import free_port

from tmrl.config import loader
from tmrl.config.loader import ConfigError

REPO = Path(__file__).resolve().parents[1]
SIM = ["SIMLIDAR", "SIMLIDARPROGRESS", "SIMFULL"]
TM = ["TM20FULL", "TM20LIDAR", "TM20LIDARPROGRESS"]
_FRESH = ("tmrl.config.config_objects", "tmrl.config.config_constants")

# Small enough for one short epoch on a CPU: 2 episodes of 30 steps, 5 updates of batch 16.
SMALL = {
    "MEMORY_SIZE": 1000, "BATCH_SIZE": 16, "MAX_EPOCHS": 1, "ROUNDS_PER_EPOCH": 1, "TRAINING_STEPS_PER_ROUND": 5,
    "ENVIRONMENT_STEPS_BEFORE_TRAINING": 40, "UPDATE_BUFFER_INTERVAL": 5, "UPDATE_MODEL_INTERVAL": 5,
    "MAX_TRAINING_STEPS_PER_ENVIRONMENT_STEP": 1000.0, "ENV": {"RTGYM_CONFIG": {"ep_max_length": 30}},
}


@pytest.fixture
def fresh_objects(monkeypatch, _isolated_data_folder) -> Callable[..., Any]:
    """``load(override, config_file=None)``: a freshly imported config_objects that read
    ``config_file`` (copied to the data folder) with ``override`` applied."""
    import tmrl.config as package

    saved_modules = {name: sys.modules.get(name) for name in _FRESH}
    saved_attrs = {name: vars(package).get(name.rsplit(".", 1)[1]) for name in _FRESH}

    def forget() -> None:
        for name in _FRESH:
            sys.modules.pop(name, None)
            if hasattr(package, name.rsplit(".", 1)[1]):
                delattr(package, name.rsplit(".", 1)[1])

    def load(override: dict[str, Any] | None = None, config_file: Path | None = None) -> Any:
        if config_file is not None:
            (_isolated_data_folder / "config").mkdir(parents=True, exist_ok=True)
            shutil.copyfile(config_file, _isolated_data_folder / "config" / "config.json")
        monkeypatch.setenv(loader.OVERRIDE_ENV, json.dumps(override or {}))
        forget()
        return importlib.import_module("tmrl.config.config_objects")

    yield load
    forget()
    for name, module in saved_modules.items():
        if module is not None:
            sys.modules[name] = module
            setattr(package, name.rsplit(".", 1)[1], saved_attrs[name])


class FakeInterface:
    """The trainer's side of the network, in process: hands out the given buffer once, then
    empty buffers; keeps the weights broadcast."""

    def __init__(self, buffer: Any):
        from tmrl.networking import Buffer

        self.buffers = [buffer]
        self.empty = Buffer
        self.broadcasts: list[dict[str, torch.Tensor]] = []

    def retrieve_buffer(self) -> Any:
        return self.buffers.pop(0) if self.buffers else self.empty()

    def broadcast_model(self, actor: torch.nn.Module) -> None:
        self.broadcasts.append({k: v.detach().clone() for k, v in actor.state_dict().items()})


# --- the simulator: built from the shipped config files -----------------------------------------


@pytest.mark.parametrize("name", SIM)
def test_shipped_sim_config_runs_the_whole_sample_path(name, fresh_objects, tmp_path):
    from tmrl.algorithms.sac import SACAgent
    from tmrl.networking import RolloutWorker, pack_buffer, unpack_buffer
    from tmrl.sim import interfaces as sim
    from tmrl.training_offline import TorchTrainingOffline

    torch.manual_seed(0)
    o = fresh_objects(SMALL, REPO / "config" / f"config_{name.lower()}.json")
    parts = sim.pipeline_parts(name)
    assert o.ENV_CLS.func is sim.SimEnv and o.ENV_CLS.keywords["interface"] == name
    assert o.ENV_CLS.keywords["track"] == "classic" and o.ENV_CLS.keywords["act_buf_len"] == 2
    assert o.ENV_CLS.keywords["ep_max_length"] == 30 and o.ENV_CLS.keywords["img_hist_len"] == 4
    assert o.MEMORY.func is parts["memory_cls"]
    assert {k: o.MEMORY.keywords[k] for k in ("hist_len", "act_buf_len", "memory_size", "batch_size")} == \
        {"hist_len": 4, "act_buf_len": 2, "memory_size": 1000, "batch_size": 16}
    assert o.POLICY is parts["actor_cls"] and o.TRAIN_MODEL is parts["model_cls"]
    assert o.OBS_PREPROCESSOR is parts["obs_preprocessor"] and o.SAMPLE_COMPRESSOR is parts["sample_compressor"]
    assert o.AGENT.func is SACAgent and o.AGENT.keywords["lr_actor"] == 1e-3 and o.AGENT.keywords["alpha"] == 0.2
    assert o.AGENT.keywords["update_order"] == "simultaneous"
    assert o.TRAINER.func is TorchTrainingOffline and o.TRAINER.keywords["env_cls"] is o.ENV_CLS
    assert o.CONFIG_DICT["interface"] is sim.interface_class(name)

    # The environment resets and steps.
    env = o.ENV_CLS()
    obs, _ = env.reset()
    assert env.observation_space.contains(obs)
    obs, rew, terminated, truncated, _ = env.step(np.array([1.0, 0.0, 0.0], np.float32))
    assert env.observation_space.contains(obs) and np.isfinite(rew) and not (terminated or truncated)

    # A worker collects two episodes; its policy acts on the preprocessed observation.
    worker = RolloutWorker(env_cls=o.ENV_CLS, actor_module_cls=o.POLICY, sample_compressor=o.SAMPLE_COMPRESSOR,
                           obs_preprocessor=o.OBS_PREPROCESSOR, standalone=True, model_path=str(tmp_path / "w.tmod"),
                           model_history=0)
    act = worker.act(o.OBS_PREPROCESSOR(obs))
    assert worker.env.action_space.contains(np.asarray(act, np.float32))
    worker.collect_train_episode()
    worker.collect_train_episode()
    assert len(worker.buffer) == 2 * 31  # the reset sample and 30 steps per episode
    # Samples are compressed: the newest frame only, no action buffer.
    assert len(worker.buffer.memory[1][1]) == len(env.observation_space.spaces) - 2
    buffer = unpack_buffer(pack_buffer(worker.buffer, worker.source_id, 0))  # the network's format

    # The trainer built from TRAINER learns from them and broadcasts weights the worker loads.
    training = o.TRAINER(sleep_between_buffer_retrieval_attempts=0.0)
    training.max_wait_s = 60.0
    interface = FakeInterface(buffer)
    before = {k: v.clone() for k, v in training.agent.get_actor().state_dict().items()}
    stats = training.run_epoch(interface)
    assert training.total_updates == 5 and len(training.memory) > 0
    assert np.isfinite(stats[-1]["loss_critic"])
    assert interface.broadcasts, "the trainer broadcast no weights"
    assert any(not torch.equal(before[k], v) for k, v in interface.broadcasts[-1].items())
    worker.actor.load_state_dict(interface.broadcasts[-1])
    assert worker.env.action_space.contains(np.asarray(worker.act(o.OBS_PREPROCESSOR(obs)), np.float32))
    worker.close()
    env.close()


def test_shipped_sim_configs_learn_like_the_demo():
    from tmrl.sim.demo import DEMO_SETTINGS

    for name in SIM:
        cfg = loader.load_config(REPO / "config" / f"config_{name.lower()}.json")
        env, alg = cfg["ENV"], cfg["ALG"]
        assert env["RTGYM_INTERFACE"] == name and env["SIM_FAST_MODE"] is True
        assert env["RTGYM_CONFIG"]["interface_kwargs"] == {"track": "classic"}
        assert (alg["LR_ACTOR"], alg["LR_CRITIC"], alg["GAMMA"], alg["ALPHA"], alg["LEARN_ENTROPY_COEF"]) == \
            (DEMO_SETTINGS["lr"], DEMO_SETTINGS["lr"], DEMO_SETTINGS["gamma"], DEMO_SETTINGS["alpha"], True)
        assert (cfg["BATCH_SIZE"], cfg["MEMORY_SIZE"]) == (DEMO_SETTINGS["batch_size"], DEMO_SETTINGS["memory_size"])
        assert alg["ALGORITHM"] == DEMO_SETTINGS["algorithm"]
        # the demo's pace in fast mode, its update-to-data ratio in real time
        assert (cfg["MAX_ENVIRONMENT_STEPS_PER_TRAINING_STEP"], cfg["MAX_TRAINING_STEPS_PER_ENVIRONMENT_STEP"]) == \
            (DEMO_SETTINGS["max_env_steps_per_training_step"], DEMO_SETTINGS["realtime_max_training_steps_per_env_step"])
        assert cfg["LOCALHOST_WORKER"] and cfg["LOCALHOST_TRAINER"]


# --- the simulator: other settings ---------------------------------------------------------------


def test_sim_real_time_mode_uses_the_real_time_env(fresh_objects):
    from tmrl.envs import GenericGymEnv
    from tmrl.sim.interfaces import SimLidarProgressInterface

    o = fresh_objects({"ENV": {"RTGYM_INTERFACE": "SIMLIDARPROGRESS", "SIM_FAST_MODE": False, "IMG_HIST_LEN": 2,
                               "RTGYM_CONFIG": {"ep_max_length": None, "interface_kwargs": {"lidar_scale": 0.2}}}})
    assert o.ENV_CLS.func is GenericGymEnv and o.ENV_CLS.keywords["id"] == "real-time-gym-ts-v1"
    rt = o.ENV_CLS.keywords["gym_kwargs"]["config"]
    assert rt is o.CONFIG_DICT and rt["interface"] is SimLidarProgressInterface
    assert rt["interface_kwargs"]["lidar_scale"] == 0.2 and rt["ep_max_length"] == float("inf")
    assert o.MEMORY.keywords["hist_len"] == 2
    env = o.ENV_CLS()
    try:
        obs, _ = env.reset()
        assert len(obs) == 5 and obs[2].shape == (2, 19)  # speed, progress, lidars, 2 actions
        obs, rew, *_ = env.step(np.array([1.0, 0.0, 0.0], np.float32))
        assert len(obs) == 5 and np.isfinite(rew) and np.array_equal(obs[4], [1.0, 0.0, 0.0])
    finally:
        env.close()


def test_update_order_reaches_the_sac_agent(fresh_objects):
    o = fresh_objects({**SMALL, "ALG": {"UPDATE_ORDER": "sequential"}, "ENV": {"RTGYM_INTERFACE": "SIMLIDAR"}})
    assert o.AGENT.keywords["update_order"] == "sequential"
    training = o.TRAINER(sleep_between_buffer_retrieval_attempts=0.0)
    assert training.agent.update_order == "sequential"


def test_sim_redq_passes_its_critic_count_to_the_driving_model(fresh_objects):
    from tmrl.algorithms.redq import REDQSACAgent

    o = fresh_objects({**SMALL, "ALG": {"ALGORITHM": "REDQSAC", "REDQ_N": 3, "REDQ_M": 2},
                       "ENV": {"RTGYM_INTERFACE": "SIMLIDAR"}})
    assert o.AGENT.func is REDQSACAgent and o.AGENT.keywords["n"] == 3
    training = o.TRAINER(sleep_between_buffer_retrieval_attempts=0.0)
    assert training.agent.n == 3 and len(training.agent.critics) == 3


@pytest.mark.parametrize("kwargs, key", [({"lidar_sise": [100, 50]}, "lidar_sise"), ({"view_width": 10}, "view_width")])
def test_sim_unknown_interface_kwarg_is_a_config_error(fresh_objects, kwargs, key):
    with pytest.raises(ConfigError, match=key) as err:
        fresh_objects({"ENV": {"RTGYM_INTERFACE": "SIMLIDAR", "RTGYM_CONFIG": {"interface_kwargs": kwargs}}})
    assert "\n" not in str(err.value)


def test_sim_accepts_the_original_save_replays(fresh_objects):
    o = fresh_objects({"ENV": {"RTGYM_INTERFACE": "SIMFULL",
                               "RTGYM_CONFIG": {"interface_kwargs": {"save_replays": False, "view_width": 20.0}}}})
    # save_replays now reaches the simulator, which saves a replay of every lap when it is on
    assert o.ENV_CLS.keywords["save_replays"] is False and o.ENV_CLS.keywords["view_width"] == 20.0
    assert o.ENV_CLS().interface.replays is None


# --- the drone: interface keywords are validated -------------------------------------------------


def test_drone_unknown_interface_kwarg_is_a_one_line_config_error(fresh_objects):
    with pytest.raises(ConfigError) as err:
        fresh_objects({"ENV": {"RTGYM_INTERFACE": "DRONE", "RTGYM_CONFIG": {"interface_kwargs": {"mas": 2.0}}}})
    text = str(err.value)
    assert "interface_kwargs.mas" in text and "mass" in text and "\n" not in text


def test_drone_kwargs_of_the_interface_and_of_the_drone_pass(fresh_objects):
    o = fresh_objects({"ENV": {"RTGYM_INTERFACE": "DRONE", "RTGYM_CONFIG": {
        "interface_kwargs": {"success_distance": 0.05, "mass": 2.0, "save_replays": False}}}})
    assert o.CONFIG_DICT["interface_kwargs"] == {"success_distance": 0.05, "mass": 2.0}


# --- the roles and config_objects: one configuration, the same objects ----------------------------

_ROLES_FIRST = textwrap.dedent(
    """
    import json
    from tmrl import roles
    trainer = roles.trainer_from_config()  # the roles first: they read the configuration
    trainer.interface.close(2.0)
    import tmrl.config.config_constants as c  # then a script's import of the compatibility modules
    import tmrl.config.config_objects as o
    worker = roles.worker_from_config(standalone=True)
    worker.close()
    agent = trainer.training_cls.keywords["training_agent_cls"]
    print(json.dumps({
        "trainer": trainer.training_cls is o.TRAINER, "agent": agent is o.AGENT,
        "lr": [agent.keywords["lr_actor"], o.AGENT.keywords["lr_actor"]],
        "worker": [worker.sample_compressor is o.SAMPLE_COMPRESSOR, type(worker.actor) is o.POLICY],
        "checkpoint": trainer.checkpoint_path == str(c.CHECKPOINT_PATH), "port": [trainer.settings.port, c.PORT],
    }))
    """
)

_SCRIPT_FIRST = textwrap.dedent(
    """
    import json
    from tmrl.config.loader import set_override_env
    set_override_env({"ALG": {"LR_ACTOR": 0.0456}})  # a script sets its overrides, then imports
    import tmrl.config.config_objects as o
    set_override_env({"ALG": {"LR_ACTOR": 0.0789}})  # too late: the configuration was read
    from tmrl import roles
    trainer = roles.trainer_from_config()
    trainer.interface.close(2.0)
    print(json.dumps({"trainer": trainer.training_cls is o.TRAINER, "lr": o.AGENT.keywords["lr_actor"]}))
    """
)


def _run_script(code: str, override: dict[str, Any]) -> dict[str, Any]:
    env = {**os.environ, loader.OVERRIDE_ENV: json.dumps(override)}
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=180,
                         check=False)
    assert out.returncode == 0, out.stderr[-3000:]
    return json.loads(out.stdout.strip().splitlines()[-1])


def test_roles_and_config_objects_hand_out_the_same_objects():
    """Roles first, config_objects imported afterwards by the script: one configuration, one set of
    objects (the trainer trains config_objects.TRAINER itself, the worker runs its compressor)."""
    port = free_port()
    got = _run_script(_ROLES_FIRST, {"RUN_NAME": "same_objects", "PORT": port, "ALG": {"LR_ACTOR": 0.0123},
                                     "ENV": {"RTGYM_INTERFACE": "SIMLIDAR"}})
    assert got == {"trainer": True, "agent": True, "lr": [0.0123, 0.0123], "worker": [True, True],
                   "checkpoint": True, "port": [port, port]}


def test_roles_run_the_configuration_config_constants_read():
    """A script that imported config_objects first: the roles build from the configuration it read
    (even when the override changed afterwards), the same objects."""
    got = _run_script(_SCRIPT_FIRST, {})
    assert got == {"trainer": True, "lr": 0.0456}


def test_assemble_builds_once_per_configuration():
    from tmrl.assembly import assemble

    gym = {"ENV": {"RTGYM_INTERFACE": "GYM"}}
    a, b = loader.load_config(overrides=gym), loader.load_config(overrides=gym)
    other = loader.load_config(overrides={**gym, "ALG": {"LR_ACTOR": 0.5}})
    assert a is not b and assemble(a) is assemble(b)  # equal configurations: the same objects
    assert assemble(other).AGENT.keywords["lr_actor"] == 0.5
    assert assemble(a).AGENT.keywords["lr_actor"] == a["ALG"]["LR_ACTOR"] != 0.5
    assert assemble(a).TRAINER.keywords["training_agent_cls"] is assemble(a).AGENT
    # the objects keep a copy: changing the dict afterwards changes none of them
    a["ALG"]["LR_ACTOR"] = 0.25
    assert assemble(b).ALG_CONFIG == b["ALG"] and assemble(b).ALG_CONFIG["LR_ACTOR"] != 0.25


# --- TrackMania: built without the game ----------------------------------------------------------

_TM_PROBE = textwrap.dedent(
    """
    import importlib, json, os, sys
    out = {}
    for name in %r:
        os.environ["TMRL_CONFIG_OVERRIDE"] = json.dumps({"ENV": {"RTGYM_INTERFACE": name,
            "RTGYM_CONFIG": {"interface_kwargs": {"save_replays": True}}}})
        for m in ("tmrl.config.config_objects", "tmrl.config.config_constants"):
            sys.modules.pop(m, None)
        o = importlib.import_module("tmrl.config.config_objects")
        rt = o.ENV_CLS.keywords["gym_kwargs"]["config"]
        iface = o.INT()  # building the interface touches no game
        out[name] = {"env": [o.ENV_CLS.func.__name__, o.ENV_CLS.keywords["id"]],
                     "iface": rt["interface"].__name__, "int": type(iface).__name__,
                     "save_replays": iface.save_replays, "memory": o.MEMORY.func.__name__,
                     "policy": o.POLICY.__name__, "model": o.TRAIN_MODEL.__name__,
                     "trainer": o.TRAINER.func.__name__, "pre": o.OBS_PREPROCESSOR.__name__,
                     "spaces": len(iface.get_observation_space().spaces)}
    out["game_modules"] = sorted(m for m in ("mss", "vgamepad", "cv2", "win32gui") if m in sys.modules)
    print(json.dumps(out))
    """
)


def test_trackmania_objects_build_without_the_game():
    env = dict(os.environ)
    out = subprocess.run([sys.executable, "-c", _TM_PROBE % (TM,)], capture_output=True, text=True, env=env,
                         timeout=120, check=False)
    assert out.returncode == 0, out.stderr
    v = json.loads(out.stdout)
    assert v.pop("game_modules") == []
    expected = {
        "TM20FULL": ("TM20FullInterface", "ImageMemory", "SquashedGaussianCNNActor", "CNNActorCritic", 4),
        "TM20LIDAR": ("TM20LidarInterface", "LidarMemory", "LidarActor", "LidarActorCritic", 2),
        "TM20LIDARPROGRESS": ("TM20LidarProgressInterface", "LidarProgressMemory", "LidarActor", "LidarActorCritic",
                              3),
    }
    for name, (iface, memory, policy, model, spaces) in expected.items():
        got = v[name]
        assert got["env"] == ["GenericGymEnv", "real-time-gym-ts-v1"], name
        assert (got["iface"], got["int"], got["memory"], got["policy"], got["model"], got["spaces"]) == \
            (iface, iface, memory, policy, model, spaces), name
        assert got["save_replays"] is True and got["trainer"] == "TorchTrainingOffline"


def test_trackmania_unknown_interface_kwarg_is_a_config_error(fresh_objects):
    with pytest.raises(ConfigError, match=r"interface_kwargs\.save_replay\b"):
        fresh_objects({"ENV": {"RTGYM_INTERFACE": "TM20LIDAR",
                               "RTGYM_CONFIG": {"interface_kwargs": {"save_replay": True}}}})


# --- the CLI's dispatch by interface -------------------------------------------------------------

_CLI = textwrap.dedent(
    """
    import json, sys
    import tmrl.cli as cli
    import types
    fake = types.ModuleType("fake_hooks")
    fake.tm = lambda cfg, steps=0: print("HOOK " + json.dumps({"tm": steps, "iface": cfg["ENV"]["RTGYM_INTERFACE"]}))
    fake.roles = lambda cfg: print("HOOK " + json.dumps({"roles": cfg["ENV"]["SIM_FAST_MODE"],
                                                         "bench": cfg["ENV"]["RTGYM_CONFIG"]["benchmark"]}))
    sys.modules["fake_hooks"] = fake
    cli.TM_HOOKS["benchmark"] = ("fake_hooks", "tm")
    cli.HOOKS["benchmark"] = ("fake_hooks", "roles")
    sys.exit(cli.main(sys.argv[1:]))
    """
)


@pytest.mark.parametrize("iface, expected", [
    ("TM20LIDAR", {"tm": 500, "iface": "TM20LIDAR"}),
    ("SIMLIDAR", {"roles": False, "bench": True}),  # the real-time simulator: fast mode has no clock
    ("GYM", {"roles": True, "bench": True}),
])
def test_benchmark_dispatch_depends_on_the_interface(iface, expected):
    from tmrl.cli import TM_HOOKS

    assert TM_HOOKS["benchmark"] == ("tmrl.tm.tools", "benchmark")
    override = json.dumps({"ENV": {"RTGYM_INTERFACE": iface}})
    out = subprocess.run([sys.executable, "-c", _CLI, "--benchmark", "-q", "-d", override], capture_output=True,
                         text=True, timeout=120, check=False)
    assert out.returncode == 0, out.stderr
    lines = [line[5:] for line in out.stdout.splitlines() if line.startswith("HOOK ")]
    assert [json.loads(line) for line in lines] == [expected]


def test_print_config_into_a_closed_pipe_exits_quietly():
    proc = subprocess.Popen([sys.executable, "-m", "tmrl", "--print-config"], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE)
    assert proc.stdout is not None and proc.stderr is not None
    # The reader is gone before the command prints (it is still starting), as with a `| head`
    # that has exited.
    proc.stdout.close()
    err = proc.stderr.read().decode()
    assert proc.wait(timeout=60) == 0, err
    assert "Traceback" not in err and "BrokenPipe" not in err and "Exception ignored" not in err
