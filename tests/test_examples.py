"""The examples run as documented (more of them are covered by the test file of the module each
one shows: examples/custom_memory.py in test_memory.py, examples/realtime_drone.py in
test_realtime_drone.py)."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def test_pendulum_example_test_mode_runs_without_a_display(tmp_path):
    env = {k: v for k, v in os.environ.items() if k not in ("DISPLAY", "WAYLAND_DISPLAY")}
    out = subprocess.run([sys.executable, str(ROOT / "examples" / "pendulum_distributed.py"), "--test"],
                         capture_output=True, text=True, timeout=180, env=env, cwd=tmp_path, check=False)
    assert out.returncode == 0, out.stderr[-2000:]
    assert "Traceback" not in out.stderr
    assert "no window" in out.stdout
    assert sum(line.startswith("test episode ") for line in out.stdout.splitlines()) == 5
