"""Stop means stop, for every signal (issue 40): ``python -m tmrl --demo`` stopped by SIGINT,
SIGTERM or SIGHUP, or its process killed with SIGKILL, and the three command-line roles of the
Quick start stopped by SIGINT, SIGTERM or SIGHUP: within 10 s no process of the run is left and
the demo's run folder (``$TMPDIR/tmrl-demo-*``) is gone.

Every run gets its own ``TMPDIR``; the processes of a run are found through it, in their
environment (``/proc/PID/environ``): the demo, its roles and the network processes below them
all inherit it. Each run stops as soon as its roles are up (each role has started its network
process), so that the test costs the start-up only.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

pytestmark = [pytest.mark.timeout(240), pytest.mark.linux]  # POSIX signals, and /proc

GONE_WITHIN = 10.0
START_TIMEOUT = 150.0  # a loaded 2-core CI machine imports torch three times at once


def run_processes(marker: str) -> list[int]:
    """Live processes (not zombies) whose environment holds ``marker``."""
    needle = marker.encode()
    found = []
    for entry in os.listdir("/proc"):
        if not entry.isdigit() or int(entry) == os.getpid():
            continue
        try:
            with open(f"/proc/{entry}/environ", "rb") as f:
                if needle not in f.read():
                    continue
            with open(f"/proc/{entry}/stat") as f:
                if f.read().rsplit(")", 1)[1].split()[0] == "Z":
                    continue
        except OSError:
            continue
        found.append(int(entry))
    return found


def cmdline(pid: int) -> str:
    try:
        with open(f"/proc/{pid}/cmdline", "rb") as f:
            return f.read().replace(b"\0", b" ").decode(errors="replace")
    except OSError:
        return ""


def network_processes(marker: str) -> list[int]:
    return [p for p in run_processes(marker) if "tmrl.transport._netproc" in cmdline(p)]



_DEFAULT_SIGNALS_THEN_TMRL = (
    "import os, signal, sys\n"
    "for name in ('SIGINT', 'SIGTERM', 'SIGHUP'):\n"
    "    signal.signal(getattr(signal, name), signal.SIG_DFL)\n"
    "os.execv(sys.executable, [sys.executable, '-m', 'tmrl', *sys.argv[1:]])\n"
)
"""``python -c`` this, then tmrl's arguments: SIGINT, SIGTERM and SIGHUP back to their default
action, then ``python -m tmrl`` in the same process (exec keeps a default action default)."""

class Run:
    """The processes started by one test, with their output collected in the background."""

    def __init__(self, tmp_path: Path) -> None:
        self.tmpdir = tmp_path / "tmp"
        self.tmpdir.mkdir()
        self.marker = str(self.tmpdir)
        self.env = dict(os.environ, TMPDIR=self.marker, PYTHONUNBUFFERED="1", TMRL_DATA=str(tmp_path / "data"))
        self.cwd = tmp_path
        self.procs: list[subprocess.Popen] = []
        self.output: dict[int, list[str]] = {}

    def start(self, *args: str, env: dict[str, str] | None = None) -> subprocess.Popen:
        # A session of its own, as a command typed in its own terminal: a signal sent to it
        # reaches that process only.
        # Its signals as a terminal gives them: a suite started under `nohup` (SIGHUP ignored) or
        # as a background job (SIGINT ignored) would pass those on, and tmrl keeps an ignored
        # signal ignored, as it should.
        proc = subprocess.Popen([sys.executable, "-c", _DEFAULT_SIGNALS_THEN_TMRL, *args], stdout=subprocess.PIPE,
                                stderr=subprocess.STDOUT, env={**self.env, **(env or {})}, cwd=self.cwd,
                                start_new_session=True)
        lines: list[str] = []
        self.output[proc.pid] = lines
        self.procs.append(proc)
        threading.Thread(target=lambda: lines.extend(raw.decode(errors="replace") for raw in proc.stdout),
                         daemon=True).start()
        return proc

    def text(self, proc: subprocess.Popen) -> str:
        return "".join(self.output[proc.pid])

    def wait_until(self, what: str, condition, timeout: float = START_TIMEOUT) -> None:
        deadline = time.monotonic() + timeout
        while not condition():
            dead = [p for p in self.procs if p.poll() is not None]
            if dead or time.monotonic() > deadline:
                logs = "\n".join(f"--- {' '.join(map(str, p.args[2:]))} (exit {p.poll()}):\n{self.text(p)[-3000:]}"
                                 for p in self.procs)
                raise AssertionError(f"{what}: not reached ({'a process exited' if dead else 'timeout'})\n{logs}")
            time.sleep(0.1)

    def assert_all_gone(self, how: str) -> float:
        """Wait up to :data:`GONE_WITHIN` seconds for every process of the run and every
        ``tmrl-*`` folder in its TMPDIR to be gone; returns how long it took."""
        t0 = time.monotonic()
        while True:
            for p in self.procs:
                p.poll()  # reap the ones we started
            left = run_processes(self.marker)
            folders = sorted(p.name for p in self.tmpdir.glob("tmrl-*"))
            if not left and not folders:
                return time.monotonic() - t0
            if time.monotonic() - t0 > GONE_WITHIN:
                logs = "\n".join(f"--- {' '.join(map(str, p.args[2:]))} (exit {p.poll()}):\n{self.text(p)[-3000:]}"
                                 for p in self.procs)
                raise AssertionError(f"{how}: after {GONE_WITHIN:.0f} s, processes left "
                                     f"{[(p, cmdline(p)[:120]) for p in left]}, run folders left {folders}\n{logs}")
            time.sleep(0.05)

    def kill_everything(self) -> None:
        for pid in run_processes(self.marker):
            try:
                os.kill(pid, signal.SIGKILL)
            except ProcessLookupError:
                pass
        for p in self.procs:
            if p.poll() is None:
                p.kill()
            p.wait()


@pytest.fixture
def run(tmp_path):
    r = Run(tmp_path)
    yield r
    r.kill_everything()


NAMES = {"SIGINT": "Ctrl-C", "SIGTERM": "SIGTERM", "SIGHUP": "SIGHUP"}  # (names: collected on Windows too)


# ------------------------------------------------------------------------------------------------
# the demo


@pytest.mark.parametrize("name", ["SIGINT", "SIGTERM", "SIGHUP", "SIGKILL"])
def test_the_demo_and_all_its_processes_stop_and_leave_no_run_folder(name, run, tmp_path):
    sig = getattr(signal, name)
    threads = ["--threads", "2"] if sig == signal.SIGINT else []  # the demo's --threads reaches its roles
    demo = run.start("--demo", "--minutes", "30", "--out", str(tmp_path / "out"), *threads)
    # up: the run folder exists and each of the three roles has started its network process
    run.wait_until("the demo's three roles up",
                   lambda: len(network_processes(run.marker)) == 3 and any(run.tmpdir.glob("tmrl-demo-*")))
    assert len(run_processes(run.marker)) == 7  # the demo, three roles, three network processes
    os.kill(demo.pid, sig)
    took = run.assert_all_gone(f"--demo after {signal.Signals(sig).name}")
    if sig != signal.SIGKILL:
        assert demo.wait() == 128 + sig
        out = run.text(demo)
        assert f"tmrl demo stopped ({NAMES[name]})" in out, out[-3000:]
        assert "Traceback" not in out, out[-3000:]
        logs = tmp_path / "out" / "logs"  # the logs are kept with the outputs
        assert (logs / "worker.log").exists()
        expected = "2 PyTorch threads (TMRL_THREADS" if threads else "1 PyTorch thread (OMP_NUM_THREADS"
        assert f"trainer: {expected}" in (logs / "trainer.log").read_text()
        for role in ("server", "trainer", "worker"):  # each role stopped cleanly
            text = (logs / f"{role}.log").read_text(errors="replace")
            assert "Traceback" not in text and "Fatal Python error" not in text, f"{role}.log:\n{text[-3000:]}"
    print(f"[stop] --demo {signal.Signals(sig).name}: all gone in {took:.2f} s")


# ------------------------------------------------------------------------------------------------
# the command-line roles of the Quick start, each in its own terminal


def _quick_start_override(port: int) -> str:
    return json.dumps({
        "PORT": port, "TLS": False, "PASSWORD": "stop-signals-test", "ENVIRONMENT_STEPS_BEFORE_TRAINING": 10**9,
        "ENV": {"RTGYM_INTERFACE": "GYM", "GYM_ID": "Pendulum-v1"},
    })


UP = {"server": "server running on port", "trainer": "waiting for samples",
      "worker": "waiting for the trainer's first weights"}


@pytest.mark.parametrize("name", ["SIGINT", "SIGTERM", "SIGHUP"])
def test_the_three_command_line_roles_stop_on_every_signal(name, run, port_factory):
    sig = getattr(signal, name)
    env = {"TMRL_CONFIG_OVERRIDE": _quick_start_override(port_factory())}
    run.env.pop("OMP_NUM_THREADS", None)  # the roles size their threads themselves (issue 40)
    run.env.pop("TMRL_THREADS", None)
    roles = {role: run.start(f"--{role}", *(["--threads", "2"] if role == "trainer" else []), env=env)
             for role in ("server", "trainer", "worker")}
    run.wait_until("the three roles up", lambda: len(network_processes(run.marker)) == 3
                   and all(UP[role] in run.text(p) for role, p in roles.items()))
    for proc in roles.values():
        os.kill(proc.pid, sig)
    took = run.assert_all_gone(f"--server, --trainer and --worker after {signal.Signals(sig).name}")
    for role, proc in roles.items():
        out = run.text(proc)
        assert proc.wait() == 128 + sig, f"--{role}: exit {proc.returncode}\n{out[-3000:]}"
        assert f"tmrl: {role} stopped ({NAMES[name]})" in out, out[-3000:]
        assert "Traceback" not in out, out[-3000:]
    # threads per role: --threads for the trainer, the worker's share of the cores by default
    assert "trainer: 2 PyTorch threads (TMRL_THREADS" in run.text(roles["trainer"])
    assert "worker: 1 PyTorch thread (" in run.text(roles["worker"]) and " cores;" in run.text(roles["worker"])
    print(f"[stop] --server/--trainer/--worker {signal.Signals(sig).name}: all gone in {took:.2f} s")


# ------------------------------------------------------------------------------------------------
# nohup: a SIGHUP ignored when the command starts stays ignored (the command outlives its terminal)


def test_an_ignored_sighup_stays_ignored_and_the_handlers_come_back():
    from tmrl.roles import _interrupt_on_sigterm
    from tmrl.sim.lifeline import Stopped, stop_on_signals

    saved = {s: signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)}
    try:
        signal.signal(signal.SIGHUP, signal.SIG_IGN)  # what nohup does
        with stop_on_signals():
            assert signal.getsignal(signal.SIGHUP) is signal.SIG_IGN
            assert callable(signal.getsignal(signal.SIGTERM))
        _interrupt_on_sigterm()
        assert signal.getsignal(signal.SIGHUP) is signal.SIG_IGN
        signal.signal(signal.SIGHUP, signal.SIG_DFL)
        with stop_on_signals():
            with pytest.raises(Stopped) as stopped:
                signal.raise_signal(signal.SIGHUP)
            assert stopped.value.signum == signal.SIGHUP
        assert signal.getsignal(signal.SIGHUP) is signal.SIG_DFL  # restored
    finally:
        for s, handler in saved.items():
            signal.signal(s, handler)
