"""Two PCs, one password: a worker or trainer whose password the server refuses says so in one line
naming PASSWORD and exits with the user-error code (2) within 10 s of connecting, never "still
waiting". Real processes: ``python -m tmrl --server`` and the role, on 127.0.0.1."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]


def _lines(proc: subprocess.Popen, sink: list[tuple[float, str]]) -> threading.Thread:
    """Collect ``proc``'s stderr lines with the monotonic time each was read."""

    def read() -> None:
        for line in proc.stderr:
            sink.append((time.monotonic(), line.rstrip("\n")))

    t = threading.Thread(target=read, daemon=True)
    t.start()
    return t


@pytest.fixture
def server(tmp_path, port_factory, _isolated_data_folder):
    env = dict(os.environ, PYTHONPATH=str(REPO))
    subprocess.run([sys.executable, "-m", "tmrl", "--install", "--env", "simlidar"], env=env, check=True,
                   capture_output=True)
    cfg_file = _isolated_data_folder / "config" / "config.json"
    cfg = json.loads(cfg_file.read_text())
    cfg["PORT"] = port_factory()
    cfg_file.write_text(json.dumps(cfg))
    proc = subprocess.Popen([sys.executable, "-m", "tmrl", "--server"], env=env, stdout=subprocess.DEVNULL,
                            stderr=subprocess.PIPE, text=True)
    lines: list[tuple[float, str]] = []
    reader = _lines(proc, lines)
    deadline = time.monotonic() + 60
    while not any("server running" in line for _, line in lines):
        assert proc.poll() is None and time.monotonic() < deadline, lines
        reader.join(0.1)
    yield env, lines
    proc.terminate()
    proc.wait(timeout=30)


@pytest.mark.parametrize("role", ["worker", "trainer"])
def test_a_wrong_password_is_one_line_and_exits_with_the_user_error_code(server, role):
    env, server_lines = server
    proc = subprocess.Popen([sys.executable, "-m", "tmrl", f"--{role}", "-d", '{"PASSWORD": "not-the-servers"}'],
                            env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    lines: list[tuple[float, str]] = []
    reader = _lines(proc, lines)
    try:
        rc = proc.wait(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
    reader.join(10)
    text = "\n".join(line for _, line in lines)
    assert rc == 2, text
    connecting = next(t for t, line in lines if "connecting to the server" in line)
    assert lines[-1][0] - connecting < 10.0, text  # from the connection attempt to the exit
    errors = [line for _, line in lines if line.startswith("tmrl: error:")]
    assert len(errors) == 1 and lines[-1][1] == errors[0], text
    assert "PASSWORD" in errors[0] and "refused" in errors[0] and "wrong password" in errors[0]
    assert "still waiting" not in text and "retrying" not in text
    assert any("wrong password" in line for _, line in server_lines)  # the server saw it
