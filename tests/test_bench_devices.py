"""``--device`` of the benchmarks that build a trainer (trainer_speed, pendulum_learning,
track_learning): resolved once in the parent, handed to every side's child, named in the record
and in the first printed line; a side that fails on the device is a figure with its error. No
benchmark is run here (the other sides' installs are not needed: their children are stood in for).
"""

from __future__ import annotations

import argparse
import functools
import json
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from bench import harness, pendulum_learning, trainer_speed
from bench import track_learning as tl
from tmrl.errors import UserError
from tmrl.util import resolve_device

HAS_GPU = torch.cuda.is_available()


# --- resolution -------------------------------------------------------------------------------------


def test_auto_is_the_gpu_when_there_is_one_and_cpu_is_always_cpu():
    mps = torch.backends.mps.is_available()
    assert resolve_device("auto") == ("cuda" if HAS_GPU else "mps" if mps else "cpu")
    assert resolve_device("cpu") == resolve_device(" CPU ") == "cpu"


@pytest.mark.parametrize("name", ["gpu", "cuda:x", "metal", ""])
def test_an_unknown_device_is_one_line_naming_the_option_and_the_choices(name):
    with pytest.raises(UserError) as err:
        resolve_device(name, option="--train-device")
    assert "\n" not in str(err.value) and "--train-device" in str(err.value)
    assert "auto, cpu, cuda, cuda:N, mps" in str(err.value)


def test_mps_is_apples_gpu_where_there_is_one_and_one_line_elsewhere():
    if torch.backends.mps.is_available():  # a Mac whose PyTorch has Metal
        assert resolve_device("mps", option="--train-device") == "mps"
        return
    with pytest.raises(UserError) as err:
        resolve_device("mps", option="--train-device")
    text = str(err.value)
    assert "\n" not in text and text.startswith("--train-device mps: PyTorch") and "use --train-device cpu" in text


def test_a_gpu_this_machine_lacks_is_one_line_naming_the_option_and_the_fix():
    missing = f"cuda:{torch.cuda.device_count()}"  # one past the last GPU (cuda:0 without any)
    with pytest.raises(UserError) as err:
        resolve_device(missing)
    text = str(err.value)
    assert "\n" not in text and text.startswith(f"--device {missing}: PyTorch") and "use --device cpu" in text


def test_the_benchmarks_refuse_a_device_in_their_parsers_one_line(capsys):
    parser = argparse.ArgumentParser(prog="python -m bench x")
    harness.add_device_argument(parser, "cpu")
    with pytest.raises(SystemExit) as stop:
        harness.resolve_device(parser, "gpu")
    assert stop.value.code == 2
    assert "python -m bench x: error: --device 'gpu' is not a device" in capsys.readouterr().err
    assert parser.parse_args([]).device == "cpu"


# --- the record ---------------------------------------------------------------------------------------


def test_the_record_and_its_first_line_name_the_device(tmp_path, capsys):
    rec = harness.Recorder("unit", {"batch": 1, **harness.device_settings("cpu")}, out_dir=tmp_path)
    rec.close()
    assert capsys.readouterr().out.splitlines()[0].startswith("unit on cpu: load average")
    assert json.loads(rec.path.read_text().splitlines()[0])["settings"]["device"] == "cpu"
    harness.Recorder("plain", {"batch": 1}, out_dir=tmp_path).close()  # a benchmark without --device
    assert capsys.readouterr().out.startswith("plain: load average")


@pytest.mark.gpu
def test_a_gpu_record_names_the_gpu():
    settings = harness.device_settings("cuda")
    assert settings["device"] == "cuda" and settings["gpu"] == torch.cuda.get_device_name(0)
    assert settings["torch"] == torch.__version__ and settings["cuda"] == torch.version.cuda


# --- trainer_speed: every side's child gets the device ----------------------------------------------------


def test_every_side_of_trainer_speed_is_started_on_the_device(monkeypatch):
    started = []

    class Child:
        def __init__(self, side, module, *args):
            started.append((side.name, module, args))

    fake = harness.Side("x", sys.executable, {}, str(REPO))
    monkeypatch.setattr(harness, "ChildWorker", Child)
    monkeypatch.setattr(harness, "tmrl_side", lambda anchor: harness.Side("tmrl", fake.python, {}, fake.cwd))
    monkeypatch.setattr(harness, "sb3_side", lambda where: harness.Side("sb3", fake.python, {}, fake.cwd))
    args = argparse.Namespace(threads=2, no_tmrl=False, anchor_dir="-", no_sb3=False, sb3_dir="-", before=None,
                              glibc_defaults_for_tmrl=True)
    workers = trainer_speed._workers(args, "cuda:1")
    assert list(workers) == ["ours", "tmrl", "tmrl (glibc defaults)", "sb3"]
    for name, module, child_args in started:
        assert module == "trainer_speed" and child_args[child_args.index("--device") + 1] == "cuda:1", name
        assert child_args[child_args.index("--threads") + 1] == "2", name


def _serve(monkeypatch, argv: list[str]):
    """trainer_speed's child built with ``argv``: its request handler (the child's stdin loop is not run)."""
    handlers = []
    monkeypatch.setattr(trainer_speed.harness, "serve", handlers.append)
    monkeypatch.setattr(trainer_speed, "_reuse_freed_memory", lambda: True)
    trainer_speed.child_main(argv)
    return handlers[0]


def test_the_child_builds_each_side_on_its_device_and_a_failure_is_an_answer(monkeypatch):
    built = []

    def build(side, algo, variant="", device="cpu"):
        built.append((side, algo, device))
        if algo == "redq":  # what tmrl 0.7.1's REDQ-SAC does on CUDA
            raise RuntimeError("Found dtype Double but expected Float")
        return "memory", "agent", "a memory"

    monkeypatch.setattr(trainer_speed, "_build", build)
    monkeypatch.setattr(trainer_speed, "_measure_agent", lambda memory, agent, mode, seconds, slow, device: {
        "updates_per_s": 1.0, "device": device})
    handle = _serve(monkeypatch, ["--side", "tmrl", "--device", "cuda"])
    assert handle({"case": "pendulum", "algo": "sac", "mode": "full", "seconds": 1})["device"] == "cuda"
    failed = handle({"case": "pendulum", "algo": "redq", "mode": "full", "seconds": 1})
    assert failed == {"error": "RuntimeError: Found dtype Double but expected Float"}
    assert handle({"case": "pendulum", "algo": "redq", "mode": "agent", "seconds": 1}) == failed  # not rebuilt
    assert built == [("tmrl", "sac", "cuda"), ("tmrl", "redq", "cuda")]


def test_the_sb3_child_builds_its_model_on_the_device(monkeypatch):
    seen = []
    monkeypatch.setattr(trainer_speed, "_sb3_model", lambda device="cpu": seen.append(device) or "model")
    monkeypatch.setattr(trainer_speed, "_measure_sb3", lambda model, seconds, device="cpu": {"on": device})
    handle = _serve(monkeypatch, ["--side", "sb3", "--device", "cuda"])
    assert handle({"case": "pendulum", "algo": "sac", "mode": "full", "seconds": 1}) == {"on": "cuda"}
    assert seen == ["cuda"]


def test_a_side_that_fails_is_recorded_without_a_figure_and_the_others_go_on(tmp_path, capsys):
    class Worker:
        def __init__(self, answer):
            self.answer = answer

        def ask(self, request):
            return self.answer

    ok = {"updates_per_s": 50.0, "cpu_ms_per_update": 1.0, "sample_share": 0.1, "threads": 1}
    workers = {"ours": Worker(ok), "tmrl": Worker({"error": "RuntimeError: dtype Double"})}
    rec = harness.Recorder("unit", {"device": "cuda"}, out_dir=tmp_path)
    args = argparse.Namespace(rounds=1, seconds=0.1, bf16=False, host_memory=False)
    trainer_speed._run_rounds(args, [("tmfull", "sac", "full")], workers, rec)
    rec.close()
    got = {r["side"]: r for r in rec.records}
    assert got["ours"]["value"] == 50.0
    assert got["tmrl"]["value"] is None and got["tmrl"]["error"] == "RuntimeError: dtype Double"
    assert "tmrl failed: RuntimeError: dtype Double" in capsys.readouterr().out


def test_the_floor_and_the_timing_run_on_the_device_given():
    assert trainer_speed.floor_ms([(1, 8, 8, 8), (2, 4, 8, 8)], 0.01, "cpu") > 0
    calls = []
    res = trainer_speed._measure(calls.append, 0.0, 1, 3, device="cpu")
    assert len(calls) == 4 and res["updates_per_s"] > 0  # one warm-up step, then at least 3 updates


# --- pendulum_learning and track_learning -----------------------------------------------------------------


class _Done:
    returncode = 0

    def __init__(self, stdout: str) -> None:
        self.stdout = stdout


def _fake_children(monkeypatch, module, out_dir: Path, result: dict[str, Any]) -> list[dict[str, Any]]:
    """Each child run's keyword arguments (the runs return ``result``); records go to ``out_dir``."""
    seen: list[dict[str, Any]] = []
    real_run = module.subprocess.run

    def fake_run(cmd, **kwargs):  # the child runs only; anything else (git, for the record) really runs
        if "--run" not in cmd:
            return real_run(cmd, **kwargs)
        seen.append(json.loads(cmd[cmd.index("--run") + 1]))
        return _Done(json.dumps(result))

    monkeypatch.setattr(module.harness, "Recorder", functools.partial(module.harness.Recorder, out_dir=out_dir))
    monkeypatch.setattr(module.subprocess, "run", fake_run)
    return seen


def _record(tmp_path: Path, bench: str) -> dict[str, Any]:
    return json.loads(next(tmp_path.glob(f"{bench}-*.jsonl")).read_text().splitlines()[0])


def test_pendulum_learning_runs_on_the_device_it_is_given(tmp_path, monkeypatch, capsys):
    seen = _fake_children(monkeypatch, pendulum_learning, tmp_path,
                          {"curve": [(100, -500.0)], "wall_s": 1.0, "updates": 1, "updates_per_s": 1.0})
    pendulum_learning.main(["--orders", "simultaneous", "--seeds", "1", "--steps", "100", "--device", "auto"])
    assert [k["device"] for k in seen] == [resolve_device("auto")]
    assert _record(tmp_path, "pendulum_learning")["settings"]["device"] == resolve_device("auto")
    assert capsys.readouterr().out.startswith(f"pendulum_learning on {resolve_device('auto')}: ")
    seen.clear()
    pendulum_learning.main(["--orders", "simultaneous", "--seeds", "1", "--steps", "100"])
    assert [k["device"] for k in seen] == ["cpu"]  # the published figures' device by default


def test_track_learning_trains_on_the_gpu_when_there_is_one_and_says_so_first(tmp_path, monkeypatch, capsys):
    seen = _fake_children(monkeypatch, tl, tmp_path,
                          {"episodes": [], "tests": [], "wall_s": 1.0, "updates": 0, "steps": 4, "updates_per_s": 0.0})
    tl.main(["--agents", "SAC", "--tracks", "classic", "--seeds", "1", "--steps", "400", "--jobs", "1"])
    want = "cuda" if HAS_GPU else "cpu"
    assert [k["device"] for k in seen] == [want]
    assert capsys.readouterr().out.startswith(f"track_learning on {want}")
    assert _record(tmp_path, "track_learning")["settings"]["device"] == want
    seen.clear()
    tl.main(["--agents", "SAC", "--tracks", "classic", "--seeds", "1", "--steps", "400", "--jobs", "1",
             "--device", "cpu"])
    assert [k["device"] for k in seen] == ["cpu"]


def test_track_learning_takes_the_gpu_by_default_where_pytorch_sees_one(tmp_path, monkeypatch, capsys):
    # a GPU as PyTorch would report one (the run itself is stood in for)
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    monkeypatch.setattr(torch.cuda, "device_count", lambda: 1)
    monkeypatch.setattr(tl.harness, "device_settings", lambda device: {"device": device, "gpu": "Stand-in GPU"})
    seen = _fake_children(monkeypatch, tl, tmp_path,
                          {"episodes": [], "tests": [], "wall_s": 1.0, "updates": 0, "steps": 4, "updates_per_s": 0.0})
    tl.main(["--agents", "SAC", "--tracks", "classic", "--seeds", "1", "--steps", "400", "--jobs", "1"])
    assert [k["device"] for k in seen] == ["cuda"]
    assert capsys.readouterr().out.startswith("track_learning on cuda (Stand-in GPU): load average")


@pytest.mark.parametrize("module", [pendulum_learning, tl], ids=["pendulum_learning", "track_learning"])
def test_a_run_builds_its_memory_and_its_agent_on_its_device(module, monkeypatch):
    seen: dict[str, Any] = {}
    real_parts, real_agent = module._parts, module._agent

    class Built(Exception):
        pass

    def parts(*args, **kwargs):
        out = real_parts(*args, **kwargs)
        seen["memory"] = out["memory"].device
        return out

    def agent(*args, **kwargs):
        seen["agent"] = torch.device(real_agent(*args, **kwargs).device).type
        raise Built  # built: the run itself is not driven (nothing computes on meta)

    monkeypatch.setattr(module, "_parts", parts)
    monkeypatch.setattr(module, "_agent", agent)
    common = {"env_name": "pendulum", "seed": 0, "steps": 10, "start_steps": 5, "eval_every": 10, "batch_size": 4,
              "append_every": 2, "device": "meta"}  # meta stands in for a GPU
    with pytest.raises(Built):
        if module is tl:
            tl.run(label="SAC", utd=1, **common)
        else:
            pendulum_learning.run(order="simultaneous", eval_episodes=1, threads=torch.get_num_threads(), **common)
    assert seen == {"memory": "meta", "agent": "meta"}


def test_merge_refuses_records_of_two_devices(tmp_path):
    for name, settings in (("cpu.jsonl", {"budgets": {"classic": 10}}),  # before --device: a CPU record
                           ("gpu.jsonl", {"budgets": {"classic": 10}, "device": "cuda", "gpu": "NVIDIA H100"})):
        (tmp_path / name).write_text(json.dumps({"kind": "run", "bench": "track_learning", "settings": settings}) + "\n")
    with pytest.raises(SystemExit, match=r"gpu.jsonl was recorded on cuda and .*cpu.jsonl on cpu: merge the records "
                                         "of one device at a time"):
        tl.load_results([tmp_path / "cpu.jsonl", tmp_path / "gpu.jsonl"])
    tl.load_results([tmp_path / "gpu.jsonl", tmp_path / "gpu.jsonl"])  # one device: fine


def test_the_n_step_screen_draws_its_batches_on_the_memorys_device():
    import gymnasium

    from tmrl.memory import GenericTorchMemory

    class Buf:
        def __init__(self):
            self.memory = [(None if t == 0 else np.array([0.5], np.float32), np.array([0.0, t, 0.0], np.float32),
                            1.0, t == 9, False, {}) for t in range(10)]
            self.sources, self.stat_train_return, self.stat_test_return = None, 0.0, 0.0
            self.stat_train_steps = self.stat_test_steps = 0

        def __len__(self):
            return len(self.memory)

    env = gymnasium.make("Pendulum-v1")
    agent = tl._agent("REDQSAC-UTD4-CAP-NS3-R250", (env.observation_space, env.action_space), "pendulum", 4, "meta")
    memory = GenericTorchMemory(device="meta", nb_steps=1, memory_size=100, batch_size=4)  # meta stands in for a GPU
    memory.append(Buf())
    tl._n_step_targets(agent, memory, 3)
    batch = memory.sample()
    assert {t.device.type for t in (*batch.obs, batch.act, batch.rew, *batch.next_obs, batch.terminated)} == {"meta"}
    assert all(t.device.type == "meta" for t in agent.model.parameters())
