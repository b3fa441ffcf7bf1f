"""The tutorial's console (issue 40), with examples/tutorial.py as a real subprocess:

- under load (here: 2 ms time steps, which a worker sharing its process with a trainer cannot
  keep), late time steps make at most one line per 10 s, never a warning with its source line;
- Ctrl-C during the run in one process prints the summary of what ran, draws its plot and exits
  with 130;
- ``--plot`` without matplotlib stops at once, in one line naming ``pip install matplotlib``.
"""

from __future__ import annotations

import datetime
import itertools
import os
import re
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest
from conftest import free_port

pytestmark = pytest.mark.timeout(240)

ROOT = Path(__file__).resolve().parents[1]
SCRIPT = ROOT / "examples" / "tutorial.py"
LATE = re.compile(r"^(\d\d:\d\d:\d\d) tmrl\.realtime: (\d+) time steps? ran late")


def env_for(data: Path, **extra: str) -> dict:
    env = dict(os.environ, TMRL_DATA=str(data), MPLBACKEND="Agg", PYTHONUNBUFFERED="1", **extra)
    env.pop("DISPLAY", None)
    return env


@pytest.mark.posix
def test_under_load_one_line_per_10_s_then_ctrl_c_writes_the_summary_and_the_plot(tmp_path):
    png = tmp_path / "returns.png"
    proc = subprocess.Popen([sys.executable, str(SCRIPT), "--minutes", "10", "--time-step", "0.002",
                             "--port", str(free_port()), "--plot", str(png)],
                            env=env_for(tmp_path / "data"), cwd=tmp_path, stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True)
    lines: list[str] = []
    reader = threading.Thread(target=lambda: lines.extend(proc.stdout), daemon=True)
    reader.start()
    try:
        # two summary lines about late time steps: the run has lasted more than one interval
        deadline = time.monotonic() + 120
        while sum(bool(LATE.match(line)) for line in list(lines)) < 2:
            assert proc.poll() is None and time.monotonic() < deadline, "".join(lines)[-3000:]
            time.sleep(0.1)
        proc.send_signal(signal.SIGINT)
        assert proc.wait(timeout=60) == 130
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    reader.join(10)
    out = "".join(lines)
    late = [LATE.match(line) for line in lines if LATE.match(line)]
    times = [datetime.datetime.strptime(m.group(1), "%H:%M:%S") for m in late]
    gaps = [(b - a).total_seconds() % 86400 for a, b in itertools.pairwise(times)]
    # one line at the first late step, then at most one per 10 s (whole seconds on the clock),
    # the last one when the run stops
    assert all(gap >= 9 for gap in gaps[:-1]), out[-3000:]
    assert "TimeStepTimeoutWarning" not in out and "warnings.warn" not in out and "env.step(" not in out, out[-3000:]
    assert re.search(r"^stopped \(Ctrl-C\) after \d+ episodes$", out, re.MULTILINE), out[-3000:]
    assert re.search(r"^summary: \d+ episodes; mean return", out, re.MULTILINE), out[-3000:]
    assert png.read_bytes().startswith(b"\x89PNG\r\n\x1a\n")
    assert "Traceback" not in out, out[-3000:]


def test_plot_without_matplotlib_stops_before_the_run_in_one_line(tmp_path):
    fake = tmp_path / "no_matplotlib" / "matplotlib"
    fake.mkdir(parents=True)
    (fake / "__init__.py").write_text("raise ImportError(\"No module named 'matplotlib'\")\n")
    t0 = time.monotonic()
    done = subprocess.run([sys.executable, str(SCRIPT), "--plot", str(tmp_path / "r.png"), "--port", str(free_port())],
                          env=env_for(tmp_path / "data", PYTHONPATH=str(fake.parent)), cwd=tmp_path,
                          capture_output=True, text=True, timeout=120, check=False)
    assert done.returncode == 2, done.stdout[-2000:] + done.stderr[-2000:]
    assert done.stderr.strip().splitlines() == [
        "tutorial.py: --plot needs matplotlib, which is not installed: pip install matplotlib"]
    assert "interface check" not in done.stdout  # nothing ran
    assert time.monotonic() - t0 < 60
