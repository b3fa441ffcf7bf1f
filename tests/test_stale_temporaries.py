"""Temporary weights files left by a killed process are removed when a trainer or a worker next
starts beside them (found by the chaos soak: a trainer killed while it wrote its copy of the
weights left ``.trainer.tmod.<pid>-<id>.tmp``, one per such kill, never removed). Files of a
process that still runs, and files that are not those temporaries, stay."""

from __future__ import annotations

import os
import subprocess
import sys

import gymnasium
import pytest

from tmrl.distributed.weights import WeightsInstaller, remove_stale_temporaries
from tmrl.spaces import describe_spaces

pytestmark = pytest.mark.posix  # pids are probed with os.kill(pid, 0), a POSIX idiom


def _dead_pid() -> int:
    proc = subprocess.Popen([sys.executable, "-c", "pass"])
    proc.wait()  # reaped: its pid names no process now (reuse within this test is not a concern)
    return proc.pid


def _layout(folder, name="trainer.tmod"):
    dead, alive = _dead_pid(), os.getpid()
    stale = [folder / f".{name}.{dead}-140260777387712.tmp", folder / f".{name}.{dead}-7f3a2c.incoming"]
    kept = [folder / f".{name}.{alive}-1.tmp",        # this process: may be writing it right now
            folder / f".other.tmod.{dead}-1.tmp",      # another file's temporaries: not ours to judge
            folder / f".{name}.notapid-1.tmp", folder / name, folder / f".{name}.{dead}-1.bak"]
    for f in stale + kept:
        f.write_bytes(b"x")
    return stale, kept


def test_only_the_temporaries_of_dead_processes_go(tmp_path):
    stale, kept = _layout(tmp_path)
    assert remove_stale_temporaries(tmp_path / "trainer.tmod") == 2
    assert not any(f.exists() for f in stale) and all(f.exists() for f in kept)
    assert remove_stale_temporaries(tmp_path / "missing-folder" / "trainer.tmod") == 0


def test_a_worker_starting_beside_them_removes_them(tmp_path):
    stale, kept = _layout(tmp_path, "worker.tmod")
    env = gymnasium.make("Pendulum-v1")
    WeightsInstaller(describe_spaces(env.observation_space, env.action_space), "cpu", tmp_path / "worker.tmod",
                     str(tmp_path / "hist"), 0, None)
    assert not any(f.exists() for f in stale) and all(f.exists() for f in kept)


def test_a_trainer_starting_beside_them_removes_them(tmp_path, port_factory):
    from tmrl.distributed.trainer_interface import TrainerInterface

    stale, kept = _layout(tmp_path)
    iface = TrainerInterface(server_ip="127.0.0.1", server_port=port_factory(), password="pw", security=None,
                             model_path=str(tmp_path / "trainer.tmod"), keys_dir=str(tmp_path / "keys"),
                             sign_weights=False)
    try:
        assert not any(f.exists() for f in stale) and all(f.exists() for f in kept)
    finally:
        iface.close(5.0)
