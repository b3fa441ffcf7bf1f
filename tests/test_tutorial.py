"""examples/tutorial.py, the script of docs/tutorial.md, runs as the page says: the interface passes
the checker, all three parts in one process learn for a short budget and leave data-only weights,
a checkpoint and a metrics CSV, and the three parts also run as three processes. Its replay memory
never builds a transition across two episodes and forgets the oldest samples."""

from __future__ import annotations

import csv
import json
import os
import re
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from conftest import free_port
from test_examples_usage import load_example, ok  # the other examples' helpers

from tmrl.networking import Buffer

ROOT = Path(__file__).resolve().parents[1]
SCRIPT = ROOT / "examples" / "tutorial.py"
EPISODE = re.compile(r"^episode (\d+): return +(-?[\d.]+) in (\d+) steps \(weights version (\d+)\)$", re.MULTILINE)


def load_tutorial():
    return load_example("tutorial.py")


def env_for(data: Path) -> dict:
    env = dict(os.environ, TMRL_DATA=str(data), MPLBACKEND="Agg", PYTHONUNBUFFERED="1")
    env.pop("DISPLAY", None)
    return env


def run(*args: str, data: Path, timeout: float = 240) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, str(SCRIPT), *args], env=env_for(data), cwd=data.parent,
                          capture_output=True, text=True, timeout=timeout, check=False)


def test_the_interface_passes_the_checker(tmp_path):
    assert "interface check: passed" in ok(run("--check", data=tmp_path / "data", timeout=120))


def test_all_in_one_trains_and_leaves_weights_checkpoint_and_metrics(tmp_path):
    data = tmp_path / "data"
    out = ok(run("--minutes", "0.05", "--port", str(free_port()), "--plot", str(tmp_path / "returns.png"),
                 data=data))
    assert "interface check: passed" in out
    episodes = EPISODE.findall(out)
    assert len(episodes) >= 10, out[-2000:]
    assert all(int(steps) <= 50 for _, _, steps, _ in episodes)  # EPISODE_STEPS
    assert max(int(version) for *_, version in episodes) >= 1, "the worker never received weights"
    summary = re.search(r"^summary: (\d+) episodes", out, re.MULTILINE)
    assert summary and int(summary.group(1)) == len(episodes)
    assert (tmp_path / "returns.png").read_bytes().startswith(b"\x89PNG\r\n\x1a\n")

    tutorial = load_tutorial()
    weights = data / "weights" / "tutorial_drone_trainer.json"
    state = json.loads(weights.read_text(encoding="utf-8"))  # plain JSON numbers: nothing to execute
    actor = tutorial.DroneActor(*tutorial.drone_spaces()).load(weights, "cpu")
    assert torch.equal(actor.mean.weight, torch.tensor(state["mean.weight"]))
    obs_space, act_space = tutorial.drone_spaces()
    action = actor.act_(obs_space.sample(), test=True)  # what the worker calls
    assert act_space.contains(action.astype(np.float32))

    assert (data / "checkpoints" / "tutorial_drone_t").exists()
    with open(data / "logs" / "tutorial_drone" / "metrics.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    assert rows and float(rows[-1]["total_updates"]) > 0


def test_weights_with_a_non_number_are_refused(tmp_path):
    tutorial = load_tutorial()
    actor = tutorial.DroneActor(*tutorial.drone_spaces())
    path = tmp_path / "w.json"
    actor.save(path)
    path.write_text(path.read_text().replace("]", ", NaN]", 1))
    from tmrl.actor import WeightsError

    with pytest.raises(WeightsError, match="NaN"):
        actor.load(path, "cpu")


def sample(position, target, terminated=False, truncated=False, act=(0.0, 0.0)):
    obs = [np.array(position, np.float32), np.array(target, np.float32)]
    return np.array(act, np.float32), obs, -1.0, terminated, truncated, {}


def _buffer(*samples):
    buffer = Buffer(maxlen=100)
    for s in samples:
        buffer.append_sample(s)
    return buffer


def test_memory_never_joins_two_episodes_and_forgets_the_oldest():
    tutorial = load_tutorial()
    memory = tutorial.TutorialMemory(memory_size=9, batch_size=2, nb_steps=1, device="cpu")
    # episode A: a reset sample then three steps, the last one terminal
    memory.append(_buffer(*(sample((i, 0), (9, 9), terminated=i == 3, act=(i, i)) for i in range(4))))
    assert len(memory) == 3
    for item in range(len(memory)):
        prev_obs, act, _, new_obs, *_ = memory.get_transition(item)
        assert new_obs[0][0] == prev_obs[0][0] + 1 and act[0] == new_obs[0][0]
    # episode B, cut by the end of its buffer (neither terminal nor truncated), then episode C
    memory.append(_buffer(*(sample((10 + i, 0), (5, 5), act=(10 + i, 0)) for i in range(3))))
    memory.append(_buffer(*(sample((20 + i, 0), (4, 4), act=(20 + i, 0)) for i in range(3))))
    # 10 samples, 9 kept: A's reset sample is forgotten; no transition from A to B nor from B to C
    assert len(memory.data) == 9
    starts = sorted(memory.get_transition(i)[0][0][0] for i in range(len(memory)))
    assert starts == [1, 2, 10, 11, 20, 21]
    batch = memory.sample()
    assert batch.obs[0].shape == (2, 2) and batch.act.shape == (2, 2)


@pytest.mark.posix
def test_three_parts_as_three_processes(tmp_path):
    data = tmp_path / "data"
    port = str(free_port())
    popen = {"env": env_for(data), "cwd": tmp_path, "stdout": subprocess.PIPE, "stderr": subprocess.PIPE, "text": True}
    server = subprocess.Popen([sys.executable, str(SCRIPT), "--server", "--port", port], **popen)
    worker = trainer = None
    try:
        worker = subprocess.Popen([sys.executable, str(SCRIPT), "--worker", "--port", port], **popen)
        trainer = subprocess.run([sys.executable, str(SCRIPT), "--trainer", "--minutes", "0.05", "--port", port],
                                 env=env_for(data), cwd=tmp_path, capture_output=True, text=True, timeout=240,
                                 check=False)
        assert "trainer done" in ok(trainer)
        assert (data / "weights" / "tutorial_drone_trainer.json").is_file()
        worker.send_signal(signal.SIGINT)  # Ctrl-C
        w_out, w_err = worker.communicate(timeout=30)
        assert worker.returncode == 130 and "stopped (Ctrl-C)" in w_out, w_err[-3000:]
        episodes = EPISODE.findall(w_out)
        assert episodes and max(int(v) for *_, v in episodes) >= 1, w_out[-2000:]
        assert (data / "weights" / "tutorial_drone_worker.json").is_file()  # the weights it received
        server.send_signal(signal.SIGINT)
        s_out, s_err = server.communicate(timeout=30)
        assert server.returncode == 130 and "stopped (Ctrl-C)" in s_out, s_err[-3000:]
    finally:
        for proc in (server, worker):
            if proc is not None and proc.poll() is None:
                proc.kill()
                proc.communicate()
