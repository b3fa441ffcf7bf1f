"""tmrl 0.7 code, configs and weights carry over: module paths and names, keyword aliases, visible
progress, weights import and export, the original's ``-d`` and ``--worker --test``, and scripts
written in the original tutorials' style, run unchanged."""

from __future__ import annotations

import importlib
import json
import logging
import math
import os
import pickle
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch
from gymnasium import spaces

from tmrl.errors import UserError

REPO = Path(__file__).resolve().parents[1]
SCRIPTS = Path(__file__).resolve().parent / "compat_scripts"

#: Every module and name that tmrl 0.7's tutorials (minimal Pendulum, minimal drone, full
#: tutorial), competition template and evaluation script, README and docs import or read, and
#: those of its pretrained-model workflows (TrackMania interfaces, preprocessors, tools).
ORIGINAL_NAMES: dict[str, list[str]] = {
    "tmrl": ["get_environment", "GenericGymEnv"],
    "tmrl.networking": ["Server", "RolloutWorker", "Trainer", "Buffer", "TrainerInterface"],
    "tmrl.util": ["partial", "prod", "cached_property", "collate_torch", "partial_to_dict", "dump", "load"],
    "tmrl.envs": ["GenericGymEnv"],
    "tmrl.actor": ["ActorModule", "TorchActorModule"],
    "tmrl.memory": ["Memory", "TorchMemory"],
    "tmrl.training": ["TrainingAgent"],
    "tmrl.training_offline": ["TrainingOffline", "TorchTrainingOffline"],
    "tmrl.custom.custom_algorithms": ["SpinupSacAgent", "REDQSACAgent"],
    "tmrl.custom.custom_models": [
        "SquashedGaussianMLPActor", "MLPActorCritic", "REDQMLPActorCritic", "MLPQFunction", "mlp",
        "LOG_STD_MAX", "LOG_STD_MIN", "VanillaCNN", "SquashedGaussianVanillaCNNActor", "VanillaCNNQFunction",
        "VanillaCNNActorCritic", "conv2d_out_dims", "num_flat_features",
    ],
    "tmrl.custom.custom_memories": [
        "GenericTorchMemory", "MemoryTM", "MemoryTMLidar", "MemoryTMLidarProgress", "MemoryTMFull",
        "get_local_buffer_sample_lidar", "get_local_buffer_sample_lidar_progress",
        "get_local_buffer_sample_tm20_imgs", "last_true_in_list",
    ],
    "tmrl.custom.custom_checkpoints": [
        "dump_run_instance_images_dataset", "load_run_instance_images_dataset", "update_run_instance",
    ],
    "tmrl.custom.utils.nn": ["copy_shared", "no_grad"],
    "tmrl.custom.tm.tm_gym_interfaces": ["TM2020Interface", "TM2020InterfaceLidar", "TM2020InterfaceLidarProgress"],
    "tmrl.custom.tm.tm_preprocessors": [
        "obs_preprocessor_tm_act_in_obs", "obs_preprocessor_tm_lidar_act_in_obs",
        "obs_preprocessor_tm_lidar_progress_act_in_obs", "sample_preprocessor_tm_lidar_act_in_obs",
    ],
    "tmrl.custom.tm.utils.compute_reward": ["RewardFunction"],
    "tmrl.custom.tm.utils.control_gamepad": [
        "control_gamepad", "gamepad_reset", "gamepad_save_replay_tm20", "gamepad_close_finish_pop_up_tm20",
    ],
    "tmrl.custom.tm.utils.control_keyboard": ["apply_control", "keyres"],
    "tmrl.custom.tm.utils.control_mouse": ["mouse_close_finish_pop_up_tm20", "mouse_save_replay_tm20"],
    "tmrl.custom.tm.utils.tools": ["TM2020OpenPlanetClient", "Lidar", "save_ghost"],
    "tmrl.custom.tm.utils.window": ["WindowInterface"],
    "tmrl.tools.check_environment": ["check_env_tm20lidar", "check_env_tm20full"],
    "tmrl.tools.record": ["record_reward_dist"],
    "tmrl.tools.save_replays": ["save_replays"],
    "tmrl.wrappers": ["AffineObservationWrapper", "Float64ToFloat32", "float64_to_float32", "float_to_float32"],
    "tmrl.config.config_constants": [
        "PASSWORD", "SECURITY", "PORT", "SERVER_IP_FOR_TRAINER", "SERVER_IP_FOR_WORKER", "WEIGHTS_FOLDER",
        "CHECKPOINTS_FOLDER", "DATASET_PATH", "TMRL_CONFIG", "CUDA_TRAINING", "CUDA_INFERENCE", "WANDB_RUN_ID",
        "WINDOW_WIDTH", "WINDOW_HEIGHT", "IMG_WIDTH", "IMG_HEIGHT", "GRAYSCALE", "IMG_HIST_LEN", "ACT_BUF_LEN",
        "RTGYM_VERSION", "RTGYM_INTERFACE", "MODEL_PATH_WORKER", "MODEL_PATH_TRAINER", "CHECKPOINT_PATH",
        "REWARD_PATH", "PRAGMA_LIDAR", "PRAGMA_PROGRESS", "SYSTEM", "RUN_NAME", "TMRL_FOLDER",
    ],
    "tmrl.config.config_objects": [
        "MEM", "MEMORY", "SAMPLE_COMPRESSOR", "OBS_PREPROCESSOR", "ENV_CLS", "CONFIG_DICT", "CONFIG_DICT_MODIFIERS",
        "POLICY", "TRAIN_MODEL", "AGENT", "TRAINER", "ALG_NAME", "ALG_CONFIG", "INT", "SAMPLE_PREPROCESSOR",
        "DUMP_RUN_INSTANCE_FN", "LOAD_RUN_INSTANCE_FN", "UPDATER_FN",
    ],
}


@pytest.mark.parametrize("module", sorted(ORIGINAL_NAMES))
def test_every_name_of_the_original_imports(module):
    mod = importlib.import_module(module)
    missing = [name for name in ORIGINAL_NAMES[module] if not hasattr(mod, name)]
    assert missing == [], f"{module} lacks {missing}"


def test_top_level_names_resolve_lazily():
    import tmrl
    from tmrl.envs import GenericGymEnv

    assert tmrl.GenericGymEnv is GenericGymEnv
    with pytest.raises(AttributeError):
        tmrl.no_such_name  # noqa: B018


def test_get_environment_builds_the_configured_environment_with_rtgym_wait(_isolated_data_folder):
    config = _isolated_data_folder / "config" / "config.json"
    config.parent.mkdir(parents=True)
    config.write_text(json.dumps({"ENV": {"RTGYM_INTERFACE": "SIMLIDAR", "SIM_FAST_MODE": True}}))
    out = subprocess.run(
        [sys.executable, "-c",
         "from tmrl import get_environment\n"
         "env = get_environment(); obs, info = env.reset()\n"
         "obs, rew, term, trunc, info = env.step(env.action_space.sample())\n"
         "env.unwrapped.wait(); env.wait()\n"
         "print(type(env.unwrapped).__name__, len(obs))"],
        capture_output=True, text=True, timeout=120, check=False,
    )
    assert out.returncode == 0, out.stderr
    assert out.stdout.split() == ["SimEnv", "4"]  # speed, lidars and the two actions of the buffer


# ------------------------------------------------------------------------------------------------
# keyword and attribute aliases


def test_imgs_obs_is_an_alias_of_hist_len_noted_once(caplog):
    import tmrl.driving.memories as memories

    memories._noted_imgs_obs = False
    caplog.set_level(logging.INFO, logger="tmrl")
    first = memories.ImageMemory(imgs_obs=3, act_buf_len=2, memory_size=8, batch_size=2, nb_steps=1)
    second = memories.LidarMemory(imgs_obs=2, act_buf_len=2, memory_size=8, batch_size=2, nb_steps=1)
    assert first.hist_len == 3 and second.hist_len == 2 and first.history_depth == 3
    notes = [r for r in caplog.records if "imgs_obs" in r.getMessage()]
    assert len(notes) == 1
    assert memories.ImageMemory(hist_len=5, act_buf_len=2, memory_size=8, batch_size=2, nb_steps=1).hist_len == 5
    with pytest.raises(UserError, match="disagree"):
        memories.ImageMemory(hist_len=4, imgs_obs=3, memory_size=8, batch_size=2, nb_steps=1)


def _write_config(folder: Path, content: dict[str, Any]) -> None:
    path = folder / "config" / "config.json"
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(content))


def _python(code: str, *args: str, timeout: float = 180, env: dict[str, str] | None = None) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-c", code, *args], capture_output=True, text=True, timeout=timeout,
                          check=False, env=env, stdin=subprocess.DEVNULL)


def test_config_objects_keeps_mem_and_the_original_modifiers(_isolated_data_folder):
    _write_config(_isolated_data_folder, {"ENV": {"RTGYM_INTERFACE": "SIMFULL",
                                                   "RTGYM_CONFIG": {"time_step_duration": 0.04}}})
    out = _python(
        "import json, tmrl.config.config_objects as o, tmrl.config.config_constants as c\n"
        "m = o.MEM(memory_size=8, batch_size=2, sample_preprocessor=None, dataset_path=c.DATASET_PATH,\n"
        "          imgs_obs=c.IMG_HIST_LEN, act_buf_len=c.ACT_BUF_LEN, crc_debug=False, nb_steps=1, device='cpu')\n"
        "print(json.dumps([o.MEM is o.MEMORY.func, type(m).__name__, m.hist_len,\n"
        "                  o.CONFIG_DICT_MODIFIERS['time_step_duration'], bool(c.SYSTEM)]))"
    )
    assert out.returncode == 0, out.stderr
    assert json.loads(out.stdout) == [True, "ImageMemory", 4, 0.04, True]


# ------------------------------------------------------------------------------------------------
# save_replays and wait() on the simulator


def _drive_to_the_finish(env: Any, max_steps: int = 3000) -> dict[str, Any]:
    from tmrl.sim.race import follow_centre_line

    env.reset()
    for _ in range(max_steps):
        _, _, terminated, truncated, info = env.step(follow_centre_line(env.unwrapped.race))
        if terminated or truncated:
            return info
    raise AssertionError("the centre-line driver did not finish the lap")


def test_the_simulator_saves_a_replay_of_every_completed_lap(tmp_path):
    from tmrl.sim.interfaces import SimLidarEnv

    folder = tmp_path / "replays"
    env = SimLidarEnv(track="oval", ep_max_length=5000, save_replays=str(folder))
    info = _drive_to_the_finish(env)
    assert info["lap_completed"], info
    saved = sorted(folder.glob("*.json"))
    assert [str(p) for p in saved] == [info["replay"]]
    record = json.loads(saved[0].read_text())
    assert record["track"] == "oval" and record["lap_time"] == pytest.approx(info["lap_time"])
    assert len(record["xy"]) > 100 and f"{info['lap_time']:.2f}s" in saved[0].name
    assert saved[0].with_suffix(".png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    quiet = SimLidarEnv(track="oval", ep_max_length=5000)  # off by default: nothing saved
    assert "replay" not in _drive_to_the_finish(quiet) and quiet.interface.replays is None


def test_the_evaluation_scripts_interface_kwargs_work_on_the_real_time_simulator(_isolated_data_folder):
    # tmrl 0.7's competition_eval.py replaces the interface keywords with {'save_replays': True}.
    _write_config(_isolated_data_folder, {"ENV": {"RTGYM_INTERFACE": "SIMLIDAR", "SIM_FAST_MODE": False}})
    out = _python(
        "import tmrl.config.config_constants as cfg, tmrl.config.config_objects as cfg_obj\n"
        "from tmrl.envs import GenericGymEnv\n"
        "config = cfg_obj.CONFIG_DICT\n"
        "config['interface_kwargs'] = {'save_replays': True}\n"
        "env = GenericGymEnv(id=cfg.RTGYM_VERSION, gym_kwargs={'config': config})\n"
        "env.reset(); env.step(env.action_space.sample()); env.wait()\n"
        "print(env.unwrapped.interface.replays is not None)"
    )
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "True"


# ------------------------------------------------------------------------------------------------
# visible progress without import side effects


SERVER_SCRIPT = (
    "import logging, sys\n"
    "{setup}\n"
    "from tmrl.networking import Server\n"
    "assert logging.getLogger('tmrl').handlers == []  # importing configured nothing\n"
    "s = Server(port=int(sys.argv[1]), password='progress-test-password', security=None)\n"
    "s.stop()\n"
)


@pytest.mark.parametrize("setup, shown", [("", True), ("logging.basicConfig(level=logging.WARNING)", False)])
def test_roles_show_progress_only_when_the_script_configured_no_logging(port_factory, setup, shown):
    out = _python(SERVER_SCRIPT.format(setup=setup), str(port_factory()))
    assert out.returncode == 0, out.stderr
    assert ("INFO tmrl.networking: server listening on port" in out.stderr) is shown, out.stderr


def test_an_unchanged_tutorial_script_prints_its_training_progress(_isolated_data_folder, port_factory):
    _write_config(_isolated_data_folder, {"PASSWORD": "tutorial-style-password"})
    out = subprocess.run([sys.executable, str(SCRIPTS / "minimal_pendulum.py"), str(port_factory())],
                         capture_output=True, text=True, timeout=300, check=False, stdin=subprocess.DEVNULL)
    assert out.returncode == 0, out.stderr[-3000:]
    rounds = [line for line in out.stderr.splitlines() if "tmrl.metrics: epoch 0 round" in line]
    assert len(rounds) == 2, out.stderr[-3000:]
    assert "loss_critic" in rounds[0] and "upd/s" in rounds[0]


@pytest.mark.posix
def test_a_competition_style_script_runs_as_server_trainer_and_worker(_isolated_data_folder, port_factory):
    _write_config(_isolated_data_folder, {
        "PASSWORD": "competition-style-password", "PORT": port_factory(), "MEMORY_SIZE": 5000, "BATCH_SIZE": 32,
        "ENV": {"RTGYM_INTERFACE": "SIMLIDAR", "SIM_FAST_MODE": True, "RTGYM_CONFIG": {"ep_max_length": 100}},
    })
    script = str(SCRIPTS / "competition_style.py")
    procs = {}
    try:
        procs["server"] = subprocess.Popen([sys.executable, script, "--server"], stderr=subprocess.PIPE, text=True)
        procs["worker"] = subprocess.Popen([sys.executable, script, "--worker"], stderr=subprocess.PIPE, text=True)
        trainer = subprocess.run([sys.executable, script, "--trainer"], capture_output=True, text=True, timeout=300,
                                 check=False, stdin=subprocess.DEVNULL)
    finally:
        for proc in procs.values():
            proc.send_signal(signal.SIGINT)
        logs = {name: proc.communicate(timeout=30)[1] for name, proc in procs.items()}
    assert trainer.returncode == 0, trainer.stderr[-3000:]
    # the original's keywords were taken, the trainer trained two rounds on the worker's samples
    assert "imgs_obs is tmrl 0.7's name" in trainer.stderr
    assert "shapes are fixed by the first batch" in trainer.stderr
    rounds = [line for line in trainer.stderr.splitlines() if "tmrl.metrics: epoch 0 round" in line]
    assert len(rounds) == 2 and "rejected" not in trainer.stderr, trainer.stderr[-3000:]
    assert "train episode 0:" in logs["worker"]


# ------------------------------------------------------------------------------------------------
# weights: tmrl 0.7's .tmod files


def _linear(gen: torch.Generator, n_out: int, n_in: int) -> tuple[torch.Tensor, torch.Tensor]:
    return torch.randn(n_out, n_in, generator=gen) / math.sqrt(n_in), torch.randn(n_out, generator=gen) * 0.1


def original_mlp_actor_state(n_in: int, seed: int = 0) -> dict[str, torch.Tensor]:
    """A state_dict laid out as tmrl 0.7's SquashedGaussianMLPActor saves it (net = Linear, ReLU,
    Linear, ReLU; mu_layer; log_std_layer)."""
    gen = torch.Generator().manual_seed(seed)
    state = {}
    for name, (n_out, n) in {"net.0": (256, n_in), "net.2": (256, 256), "mu_layer": (3, 256),
                             "log_std_layer": (3, 256)}.items():
        state[f"{name}.weight"], state[f"{name}.bias"] = _linear(gen, n_out, n)
    return state


def original_mlp_action(state: dict[str, torch.Tensor], obs: tuple[torch.Tensor, ...]) -> torch.Tensor:
    """tmrl 0.7's deterministic MLP action: the observation elements concatenated in order."""
    x = torch.cat(obs, -1)
    h = torch.relu(x @ state["net.0.weight"].T + state["net.0.bias"])
    h = torch.relu(h @ state["net.2.weight"].T + state["net.2.bias"])
    return torch.tanh(h @ state["mu_layer.weight"].T + state["mu_layer.bias"])


def original_cnn_actor_state(seed: int = 0) -> dict[str, torch.Tensor]:
    """A state_dict laid out as tmrl 0.7's SquashedGaussianVanillaCNNActor saves it for 4 x 64 x 64
    images: net.conv1..4, net.mlp (Linear, ReLU, Linear), mu_layer, log_std_layer."""
    gen = torch.Generator().manual_seed(seed)
    state = {}
    for i, (c_out, c_in, k) in enumerate([(64, 4, 8), (64, 64, 4), (128, 64, 4), (128, 128, 4)], start=1):
        state[f"net.conv{i}.weight"] = torch.randn(c_out, c_in, k, k, generator=gen) / math.sqrt(c_in * k * k)
        state[f"net.conv{i}.bias"] = torch.randn(c_out, generator=gen) * 0.1
    for name, (n_out, n) in {"net.mlp.0": (256, 128 + 9), "net.mlp.2": (256, 256), "mu_layer": (3, 256),
                             "log_std_layer": (3, 256)}.items():
        state[f"{name}.weight"], state[f"{name}.bias"] = _linear(gen, n_out, n)
    return state


def original_cnn_action(state: dict[str, torch.Tensor], obs: tuple[torch.Tensor, ...]) -> torch.Tensor:
    """tmrl 0.7's deterministic CNN action: convolutions, then (speed, gear, rpm, features, actions)."""
    speed, gear, rpm, images, act1, act2 = obs
    x = images
    for i in range(1, 5):
        x = torch.relu(torch.nn.functional.conv2d(x, state[f"net.conv{i}.weight"], state[f"net.conv{i}.bias"], stride=2))
    x = torch.cat((speed, gear, rpm, x.flatten(1), act1, act2), -1)
    h = torch.relu(x @ state["net.mlp.0.weight"].T + state["net.mlp.0.bias"])
    h = h @ state["net.mlp.2.weight"].T + state["net.mlp.2.bias"]  # no activation after the last layer
    return torch.tanh(h @ state["mu_layer.weight"].T + state["mu_layer.bias"])


def _lidar_obs(n: int = 5) -> tuple[torch.Tensor, ...]:
    gen = torch.Generator().manual_seed(1)
    return (torch.rand(n, 1, generator=gen) * 300, torch.rand(n, 76, generator=gen) * 400,
            torch.rand(n, 3, generator=gen) * 2 - 1, torch.rand(n, 3, generator=gen) * 2 - 1)


def _full_obs(n: int = 4) -> tuple[torch.Tensor, ...]:
    gen = torch.Generator().manual_seed(2)
    return (torch.rand(n, 1, generator=gen) * 0.3, torch.rand(n, 1, generator=gen) * 0.6, torch.rand(n, 1, generator=gen),
            torch.rand(n, 4, 64, 64, generator=gen), torch.rand(n, 3, generator=gen) * 2 - 1,
            torch.rand(n, 3, generator=gen) * 2 - 1)


ACT = spaces.Box(-1.0, 1.0, (3,), np.float32)
LIDAR_SPACE = spaces.Tuple((spaces.Box(0, 1000, (1,), np.float32), spaces.Box(0, np.inf, (4, 19), np.float32), ACT, ACT))
FULL_SPACE = spaces.Tuple((spaces.Box(0, 1000, (1,), np.float32), spaces.Box(0, 6, (1,), np.float32),
                           spaces.Box(0, np.inf, (1,), np.float32), spaces.Box(0, 255, (4, 64, 64), np.uint8), ACT, ACT))


def test_imported_lidar_weights_act_as_the_original_actor():
    from tmrl.driving.models import LidarActor
    from tmrl.legacy_weights import export_state, import_state

    theirs = original_mlp_actor_state(83)
    actor = LidarActor(LIDAR_SPACE, ACT)
    actor.load_state_dict(import_state(theirs, actor))
    obs = _lidar_obs()
    with torch.no_grad():
        ours, _ = actor(obs, test=True)
    torch.testing.assert_close(ours, original_mlp_action(theirs, obs), rtol=1e-4, atol=1e-5)
    back = export_state(actor)
    assert sorted(back) == sorted(theirs)
    for key in theirs:
        torch.testing.assert_close(back[key], theirs[key], rtol=1e-6, atol=1e-6)


def test_imported_cnn_weights_act_as_the_original_actor():
    from tmrl.driving.models import SquashedGaussianCNNActor
    from tmrl.legacy_weights import export_state, import_state

    theirs = original_cnn_actor_state()
    actor = SquashedGaussianCNNActor(FULL_SPACE, ACT)
    actor.load_state_dict(import_state(theirs, actor))
    obs = _full_obs()
    with torch.no_grad():
        ours, _ = actor(obs, test=True)
    torch.testing.assert_close(ours, original_cnn_action(theirs, obs), rtol=1e-4, atol=1e-5)
    back = export_state(actor)
    assert sorted(back) == sorted(theirs) and all(torch.equal(back[k], theirs[k]) for k in theirs)


class _TouchOnUnpickle:
    def __init__(self, path: Path):
        self.path = path

    def __reduce__(self):
        return (open, (str(self.path), "w"))


@pytest.fixture
def lidar_run(_isolated_data_folder, tmp_path):
    """A data folder configured for the simulator's lidar interface (TM20LIDAR's observations)."""
    _write_config(_isolated_data_folder, {"RUN_NAME": "imported", "ENV": {"RTGYM_INTERFACE": "SIMLIDAR"}})
    env = dict(os.environ)
    return {"env": env, "data": _isolated_data_folder, "tmp": tmp_path,
            "worker_weights": _isolated_data_folder / "weights" / "imported.tmod"}


def _cli(ctx: dict[str, Any], *args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "tmrl", *args], capture_output=True, text=True, env=ctx["env"],
                          timeout=180, check=False, stdin=subprocess.DEVNULL)


def _one_error_line(out: subprocess.CompletedProcess) -> str:
    assert out.returncode == 2, (out.stdout, out.stderr)
    assert "Traceback" not in out.stderr
    lines = [line for line in out.stderr.splitlines() if line.startswith("tmrl: error: ")]
    assert len(lines) == 1, out.stderr
    return lines[0]


WORKER_ACTION = (
    "import sys, torch\n"
    "from tmrl.roles import worker_from_config\n"
    "w = worker_from_config(standalone=True)\n"
    "obs = torch.load(sys.argv[1])\n"
    "with torch.no_grad():\n"
    "    a, _ = w.actor(obs, test=True)\n"
    "torch.save(a, sys.argv[2])\n"
)


def test_a_tmrl07_weights_file_is_imported_and_drives_the_worker(lidar_run):
    theirs = original_mlp_actor_state(83, seed=3)
    src = lidar_run["tmp"] / "pretrained.tmod"
    torch.save(theirs, src)  # exactly what tmrl 0.7's actor writes
    out = _cli(lidar_run, "--import-weights", str(src))
    assert out.returncode == 0, out.stderr
    assert lidar_run["worker_weights"].is_file() and str(lidar_run["worker_weights"]) in out.stdout
    # the worker that --worker/--test runs loads them and acts as the original actor would
    obs_file, act_file = lidar_run["tmp"] / "obs.pt", lidar_run["tmp"] / "act.pt"
    obs = _lidar_obs()
    torch.save(obs, obs_file)
    run = _python(WORKER_ACTION, str(obs_file), str(act_file), env=lidar_run["env"])
    assert run.returncode == 0, run.stderr
    torch.testing.assert_close(torch.load(act_file), original_mlp_action(theirs, obs), rtol=1e-4, atol=1e-5)
    # and exported back, tmrl 0.7 would find its own tensors under its own names
    exported = lidar_run["tmp"] / "for-tmrl07.tmod"
    out = _cli(lidar_run, "--export-weights", str(lidar_run["worker_weights"]), "--out", str(exported))
    assert out.returncode == 0, out.stderr
    back = torch.load(exported, weights_only=True)
    assert list(back) == list(theirs)
    for key in theirs:
        torch.testing.assert_close(back[key], theirs[key], rtol=1e-6, atol=1e-6)


def test_a_weights_file_with_a_pickled_object_is_refused_without_running_it(lidar_run):
    marker = lidar_run["tmp"] / "ran"
    src = lidar_run["tmp"] / "evil.tmod"
    state = original_mlp_actor_state(83)
    state["payload"] = _TouchOnUnpickle(marker)
    src.write_bytes(pickle.dumps(state))
    line = _one_error_line(_cli(lidar_run, "--import-weights", str(src)))
    assert "holds more than tensors" in line and "never runs" in line
    assert not marker.exists() and not lidar_run["worker_weights"].exists()


@pytest.mark.parametrize("mutate, expected", [
    (lambda s: s.update({"net.0.weight": s["net.0.weight"][:, :80]}), "'net.0.weight' has shape (256, 80)"),
    (lambda s: s.pop("mu_layer.bias"), "lacks 'mu_layer.bias'"),
    (lambda s: s.update({"extra.weight": torch.zeros(2)}), "unexpected 'extra.weight'"),
    (lambda s: s["net.2.bias"].__setitem__(0, float("nan")), "NaN"),
    (lambda s: s.update({"epoch": 3}), "entry 'epoch' is not a named tensor"),  # data the restricted loader allows
])
def test_weights_that_do_not_fit_are_refused_in_one_line_and_nothing_is_written(lidar_run, mutate, expected):
    state = original_mlp_actor_state(83)
    mutate(state)
    src = lidar_run["tmp"] / "other.tmod"
    torch.save(state, src)
    assert expected in _one_error_line(_cli(lidar_run, "--import-weights", str(src)))
    assert not lidar_run["worker_weights"].exists()


def test_cnn_weights_do_not_fit_a_lidar_run(lidar_run):
    src = lidar_run["tmp"] / "cnn.tmod"
    torch.save(original_cnn_actor_state(), src)
    assert "do not fit the configured actor" in _one_error_line(_cli(lidar_run, "--import-weights", str(src)))


# ------------------------------------------------------------------------------------------------
# the original's -d and --worker --test


def test_rtgym_keys_given_to_d_reach_the_environment_configuration(lidar_run):
    out = _cli(lidar_run, "--print-config", "-d", '{"benchmark": true, "time_step_duration": 0.1, "RUN_NAME": "x"}')
    assert out.returncode == 0, out.stderr
    cfg = json.loads(out.stdout)
    assert cfg["RUN_NAME"] == "x"
    assert cfg["ENV"]["RTGYM_CONFIG"]["benchmark"] is True and cfg["ENV"]["RTGYM_CONFIG"]["time_step_duration"] == 0.1
    assert "unknown_key" in _one_error_line(_cli(lidar_run, "--print-config", "-d", '{"unknown_key": 1}'))


@pytest.mark.posix
def test_worker_test_runs_a_standalone_exploring_worker(lidar_run):
    _write_config(lidar_run["data"], {"RUN_NAME": "imported", "RW_MAX_SAMPLES_PER_EPISODE": 20,
                                      "ENV": {"RTGYM_INTERFACE": "SIMLIDAR"}})
    proc = subprocess.Popen([sys.executable, "-m", "tmrl", "--worker", "--test"], stderr=subprocess.PIPE, text=True,
                            env=lidar_run["env"], stdin=subprocess.DEVNULL)
    seen: list[str] = []
    try:
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline:
            line = proc.stderr.readline()
            if not line:
                break
            seen.append(line)
            if "train episode 0:" in line:
                break
    finally:
        proc.send_signal(signal.SIGINT)
        rest = proc.communicate(timeout=30)[1]
    text = "".join(seen) + rest
    assert any("train episode 0:" in line and "0 samples sent" in line for line in seen), text
    assert "connecting to the server" not in text  # standalone: no server, nothing sent
    assert proc.returncode == 130


# ------------------------------------------------------------------------------------------------
# trainers given neither the workers' preprocessor nor their compressor (tmrl 0.7's scripts)


def _payload(obs_shape: tuple[int, ...], n: int = 6, value: float = 0.5, src: int = 3, seq: int = 0) -> dict:
    from tmrl.networking import Buffer, pack_buffer

    buf = Buffer()
    for i in range(n):
        act = None if i == 0 else np.full(3, 0.1, np.float32)
        buf.append_sample((act, (np.full(obs_shape, value, np.float32),), 1.0, False, i == n - 1, {}))
    return pack_buffer(buf, src, seq)


def test_a_pinned_schema_takes_the_first_good_layout_and_refuses_any_other():
    from tmrl.networking import unpack_buffer
    from tmrl.spaces import PinnedSampleSchema, SampleRejected

    schema = PinnedSampleSchema(ACT)
    with pytest.raises(SampleRejected, match="non-finite"):
        unpack_buffer(_payload((4,), value=float("nan")), schema=schema)
    assert not schema.pinned  # a bad first batch fixes nothing
    with pytest.raises(SampleRejected, match="empty array"):
        unpack_buffer(_payload((0, 5)), schema=schema)
    assert len(unpack_buffer(_payload((4,)), schema=schema)) == 6 and schema.pinned
    with pytest.raises(SampleRejected, match=r"has shape \(5,\) where the run expects \(4,\)"):
        unpack_buffer(_payload((5,), seq=1), schema=schema)
    bad_action = _payload((4,), seq=2)
    bad_action["cols"][0] = ("N", np.array([True, False, False, False, False, False]),
                             ("A", np.full((5, 3), 7.0, np.float32)))
    with pytest.raises(SampleRejected, match="outside the action space"):
        unpack_buffer(bad_action, schema=schema)


def test_a_memory_that_refuses_a_buffer_costs_a_counter_not_the_trainer(caplog):
    from tmrl.memory import GenericTorchMemory
    from tmrl.networking import Buffer
    from tmrl.training_offline import TorchTrainingOffline
    from tmrl.util import partial

    class PickyMemory(GenericTorchMemory):
        def append_buffer(self, buffer: Any) -> None:
            raise IndexError("a user memory that cannot decompress this sample")

    class OneBuffer:
        def retrieve_buffer(self) -> Buffer:
            buf = Buffer()
            buf.append_sample((None, np.zeros(3, np.float32), 0.0, False, False, {}))
            return buf

    from tmrl.algorithms.sac import SACAgent

    training = TorchTrainingOffline(env_cls=(spaces.Box(-1, 1, (3,), np.float32), ACT),
                                    memory_cls=partial(PickyMemory, memory_size=16, batch_size=4),
                                    training_agent_cls=SACAgent, device="cpu")
    assert training.update_buffer(OneBuffer()) == 0 and training.update_buffer(OneBuffer()) == 0
    assert training.memory_errors == 2 and training.total_samples == 0
    assert sum("refused 1 samples" in r.getMessage() for r in caplog.records) == 1  # traceback once, then counted


def test_cuda_inference_without_a_gpu_drives_on_the_cpu_with_one_line(_isolated_data_folder):
    """CUDA_INFERENCE true on a machine where PyTorch sees no GPU: the worker still starts (its
    policy on the CPU) and says so, instead of a traceback from torch."""
    _write_config(_isolated_data_folder, {"CUDA_INFERENCE": True, "ENV": {"RTGYM_INTERFACE": "SIMLIDAR"}})
    code = ("import torch\n"
            "assert not torch.cuda.is_available()\n"
            "from tmrl.roles import worker_from_config\n"
            "w = worker_from_config(standalone=True)\n"
            "print('device', w.device, next(w.actor.parameters()).device)\n")
    out = _python(code, env=dict(os.environ))
    assert out.returncode == 0 and "Traceback" not in out.stderr, out.stderr[-2000:]
    assert "device cpu cpu" in out.stdout
    assert out.stderr.count("CUDA_INFERENCE is true but PyTorch sees no CUDA device") == 1, out.stderr[-2000:]


@pytest.mark.parametrize("seed", [3, None])
def test_seed_fixes_the_initial_weights_of_a_role(_isolated_data_folder, seed):
    """SEED seeds the generators before a role builds its actor: two workers started with SEED 3
    begin with the same weights; with SEED null they do not."""
    _write_config(_isolated_data_folder, {"SEED": seed, "ENV": {"RTGYM_INTERFACE": "SIMLIDAR"}})
    code = ("from tmrl.roles import worker_from_config\n"
            "w = worker_from_config(standalone=True)\n"
            "print(repr(sum(float(p.double().sum()) for p in w.actor.parameters())))\n")
    sums = []
    for _ in range(2):
        out = _python(code, env=dict(os.environ))
        assert out.returncode == 0, out.stderr[-2000:]
        sums.append(out.stdout.strip().splitlines()[-1])
    assert (sums[0] == sums[1]) is (seed is not None), sums
