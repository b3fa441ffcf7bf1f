"""The README's first command as Windows would run it, emulated on Linux (tests/emulation).

Every process of the run (the demo, its three roles, their three network processes) starts with:
- Windows' stop path: no ``os.killpg``, no ``SIGKILL``/``SIGHUP``, a ``Popen.send_signal`` that
  refuses SIGINT, a ``getppid`` that never changes, no ``os.set_blocking``, no ``select.poll``;
- and, in the first test, files that another process holds: ``os.replace``, ``os.rename`` and
  ``os.unlink`` fail with ``PermissionError`` one time in five.

The demo must still finish with exit 0, its weights and PNGs written, no role dead, nothing of the
run left; killed outright, its processes must still all go, with the run folder, within 10 s.
The processes of a run are found through their environment (``TMPDIR``, a folder of the test's,
with psutil). The emulation itself needs Linux: the module is marked ``linux``.
"""

from __future__ import annotations

import os
import re
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest
from process_support import marked

pytestmark = [pytest.mark.timeout(300), pytest.mark.linux]  # emulates Windows on Linux

HERE = Path(__file__).resolve().parent
GONE_WITHIN = 10.0


class EmulatedRun:
    """One ``python -m tmrl --demo`` with Windows emulated in every process."""

    def __init__(self, tmp_path: Path, emulate: str) -> None:
        self.tmpdir = tmp_path / "tmp"
        self.tmpdir.mkdir()
        self.reports = tmp_path / "reports"
        self.reports.mkdir()
        self.out = tmp_path / "out"
        self.env = dict(os.environ, TMPDIR=str(self.tmpdir), PYTHONUNBUFFERED="1", TMRL_DATA=str(tmp_path / "data"),
                        TMRL_EMULATE=emulate, TMRL_EMULATE_REPORT=str(self.reports),
                        PYTHONPATH=os.pathsep.join([str(HERE / "emulation"), str(HERE.parent),
                                                    os.environ.get("PYTHONPATH", "")]))
        self.lines: list[str] = []
        self.proc: subprocess.Popen | None = None

    def start(self, *args: str) -> subprocess.Popen:
        self.proc = subprocess.Popen([sys.executable, "-m", "tmrl", "--demo", "--out", str(self.out), *args],
                                     env=self.env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, cwd=self.tmpdir.parent)
        threading.Thread(target=lambda: self.lines.extend(raw.decode(errors="replace") for raw in self.proc.stdout),
                         daemon=True).start()
        return self.proc

    @property
    def text(self) -> str:
        return "".join(self.lines)

    def left(self) -> tuple[list[int], list[str]]:
        return marked(str(self.tmpdir)), sorted(p.name for p in self.tmpdir.glob("tmrl-*"))

    def wait_gone(self, within: float) -> float:
        t0 = time.monotonic()
        while True:
            procs, folders = self.left()
            if not procs and not folders:
                return time.monotonic() - t0
            if time.monotonic() - t0 > within:
                raise AssertionError(f"after {within:.0f} s: processes {procs}, run folders {folders}\n{self.text[-3000:]}")
            time.sleep(0.05)

    def kill_everything(self) -> None:
        for pid in marked(str(self.tmpdir)):
            try:
                os.kill(pid, 9)
            except ProcessLookupError:
                pass
        if self.proc is not None and self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait()


@pytest.fixture
def emulated(tmp_path):
    runs: list[EmulatedRun] = []

    def make(emulate: str) -> EmulatedRun:
        folder = tmp_path / f"run{len(runs)}"
        folder.mkdir()
        runs.append(EmulatedRun(folder, emulate))
        return runs[-1]

    yield make
    for run in runs:
        run.kill_everything()


def test_the_demo_on_emulated_windows_with_held_files_finishes_whole(emulated):
    run = emulated("windows,locks")
    proc = run.start("--minutes", "1")
    assert proc.wait(240) == 0, run.text[-4000:]
    out = run.text
    finished = re.search(r"tmrl demo finished after (\d+) s", out)
    assert finished, out[-4000:]
    # the roles were stopped (and the outputs written) within 10 s of the end of the budget
    assert int(finished.group(1)) <= 60 + GONE_WITHIN, out[-4000:]
    assert "Traceback" not in out, out[-4000:]
    for name in ("weights.safetensors", "learning_curve.png", "best_lap.png"):
        assert (run.out / name).stat().st_size > 0, name
    for role in ("server", "trainer", "worker"):  # no role died, none stopped with a traceback
        text = (run.out / "logs" / f"{role}.log").read_text(errors="replace")
        assert "Traceback" not in text and "Fatal Python error" not in text, f"{role}.log:\n{text[-3000:]}"
    assert run.wait_gone(1.0) <= 1.0  # nothing of the run left once the demo has exited
    # the emulation ran in every process of the run (the demo, 3 roles, 3 network processes) and
    # refused files there: each process reports how many calls it failed
    counts = [int(p.read_text()) for p in run.reports.glob("*.locks")]
    assert len(counts) >= 7 and sum(counts) >= 20, counts


def test_the_demo_killed_outright_on_emulated_windows_leaves_nothing(emulated):
    """TerminateProcess (SIGKILL here) of the demo: its roles see their lifelines close (getppid
    tells nothing on Windows), stop, remove the run folder, and their network processes follow."""
    run = emulated("windows")
    proc = run.start("--minutes", "30")
    deadline = time.monotonic() + 150
    while not (any(run.tmpdir.glob("tmrl-demo-*/worker.json")) and len(run.left()[0]) >= 7):
        assert proc.poll() is None and time.monotonic() < deadline, run.text[-3000:]
        time.sleep(0.1)
    proc.kill()
    proc.wait()
    took = run.wait_gone(GONE_WITHIN)
    print(f"[emulated windows] demo killed: all gone in {took:.2f} s")
