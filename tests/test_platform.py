"""tmrl.platform: what Linux, Windows and macOS do differently, answered in one place.

Windows is not here: its behaviour is emulated at the boundary (tests/emulation: the POSIX names
gone, Windows' Popen signals; a ``PermissionError`` where Windows raises a sharing violation; a
socket that records its options), and the module's real code runs through it.
"""

from __future__ import annotations

import json
import os
import socket
import subprocess
import sys
import textwrap
import time
from pathlib import Path
from typing import Any

import process_support
import pytest

from tmrl import platform

HERE = Path(__file__).resolve().parent
EMULATION = HERE / "emulation"


EMULATE = [pytest.param("", id="native"),
           pytest.param("windows", id="emulated-windows", marks=pytest.mark.linux)]
"""Run natively, and with Windows emulated (tests/emulation: a Linux tool)."""


def _env(emulate: str = "") -> dict[str, str]:
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    env["PYTHONPATH"] = os.pathsep.join(p for p in [str(EMULATION), str(HERE.parent), env.get("PYTHONPATH", "")] if p)
    if emulate:
        env["TMRL_EMULATE"] = emulate
    else:
        env.pop("TMRL_EMULATE", None)
    return env


# ------------------------------------------------------------------------------------------------
# names Windows forbids


@pytest.mark.parametrize("name", ["a:b", "CON", "x?", "run.", "con.txt", "NUL", "com1.log", "LPT9", "a<b", 'a"b',
                                  "a|b", "a*b", "run ", "tab\there", ".", "..", "", "   "])
def test_a_name_that_windows_refuses_is_refused_everywhere(name):
    assert platform.name_problem(name) is not None


@pytest.mark.parametrize("name", ["SAC_4_imgs_pretrained", "my run", "run.v2", "console", "CONNECT", "nullable",
                                  "com10", "a-b_c.d", "\u00e9t\u00e9"])
def test_a_name_every_system_accepts_passes(name):
    assert platform.name_problem(name) is None


@pytest.mark.parametrize("value", ["a:b", "CON", "x?", "run."])
def test_run_name_that_windows_refuses_is_one_line_on_linux_too(value, tmp_path):
    override = json.dumps({"RUN_NAME": value})
    proc = subprocess.run([sys.executable, "-m", "tmrl", "--print-config"], env=dict(_env(), TMRL_CONFIG_OVERRIDE=override),
                          capture_output=True, text=True, timeout=120, cwd=tmp_path)
    assert proc.returncode == 2, proc.stderr
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in proc.stderr, proc.stderr
    assert "RUN_NAME" in lines[0] and "cannot name a file on every system" in lines[0], lines[0]
    assert json.dumps(value) in lines[0] or repr(value) in lines[0], lines[0]


def test_nats_stream_and_bucket_names_are_checked_as_file_names():
    from tmrl.config.loader import load_config
    from tmrl.errors import UserError

    for key in ("STREAM", "BUCKET"):
        with pytest.raises(UserError, match=f"NATS.{key}.*cannot name a file on every system"):
            load_config(overrides={"NATS": {key: "AUX"}})


# ------------------------------------------------------------------------------------------------
# files that another process holds


@pytest.fixture
def fast_retries(monkeypatch):
    monkeypatch.setattr(platform, "BUSY_DELAYS", (0.0,) * 5)


def _held(monkeypatch, name: str, times: int) -> dict[str, int]:
    """``os.<name>`` raises Windows' sharing violation (a ``PermissionError``) ``times`` times."""
    real = getattr(os, name)
    state = {"left": times, "calls": 0}

    def call(*args: Any, **kwargs: Any) -> Any:
        state["calls"] += 1
        if state["left"] > 0:
            state["left"] -= 1
            raise PermissionError(13, "being used by another process (emulated)", str(args[0]))
        return real(*args, **kwargs)

    monkeypatch.setattr(os, name, call)
    return state


def test_replace_waits_for_a_file_another_process_holds(tmp_path, fast_retries, monkeypatch):
    (tmp_path / "new").write_text("new")
    (tmp_path / "old").write_text("old")
    state = _held(monkeypatch, "replace", 4)
    platform.replace(tmp_path / "new", tmp_path / "old")
    assert (tmp_path / "old").read_text() == "new" and state["calls"] == 5


def test_replace_gives_up_in_one_error_and_loses_nothing(tmp_path, fast_retries, monkeypatch):
    (tmp_path / "new").write_text("new")
    (tmp_path / "old").write_text("old")
    state = _held(monkeypatch, "replace", 100)
    with pytest.raises(platform.FileBusy) as err:
        platform.replace(tmp_path / "new", tmp_path / "old")
    assert state["calls"] == 6 and "old is held by another process" in str(err.value)
    assert "\n" not in str(err.value)
    assert (tmp_path / "old").read_text() == "old" and (tmp_path / "new").read_text() == "new"


def test_a_missing_file_is_not_retried(tmp_path, fast_retries, monkeypatch):
    calls = []
    real = os.replace
    monkeypatch.setattr(os, "replace", lambda *a: (calls.append(a), real(*a)))
    with pytest.raises(FileNotFoundError):
        platform.replace(tmp_path / "missing", tmp_path / "there")
    assert len(calls) == 1


def test_remove_and_remove_tree_retry_and_never_raise(tmp_path, fast_retries, monkeypatch):
    (tmp_path / "f").write_text("x")
    _held(monkeypatch, "unlink", 3)
    assert platform.remove(tmp_path / "f") and not (tmp_path / "f").exists()
    assert platform.remove(tmp_path / "never-there")
    tree = tmp_path / "tree"
    (tree / "a" / "b").mkdir(parents=True)
    for k in range(5):
        (tree / "a" / f"{k}.txt").write_text("x")
        (tree / "a" / "b" / f"{k}.txt").write_text("x")
    _held(monkeypatch, "unlink", 4)
    assert platform.remove_tree(tree) and not tree.exists()
    (tmp_path / "held").write_text("x")
    _held(monkeypatch, "unlink", 100)
    assert platform.remove(tmp_path / "held") is False and (tmp_path / "held").exists()


def test_read_bytes_waits_for_a_file_being_replaced(tmp_path, fast_retries, monkeypatch):
    path = tmp_path / "status.json"
    path.write_bytes(b"{}")
    real = Path.read_bytes
    state = {"left": 3}

    def read(self: Path) -> bytes:
        if state["left"]:
            state["left"] -= 1
            raise PermissionError(13, "delete pending (emulated)", str(self))
        return real(self)

    monkeypatch.setattr(Path, "read_bytes", read)
    assert platform.read_bytes(path) == b"{}"


def test_atomic_writes_go_through_the_retried_replace(tmp_path, fast_retries, monkeypatch):
    from tmrl.util import atomic_write_text

    state = _held(monkeypatch, "replace", 3)
    atomic_write_text(tmp_path / "x.json", "{}")
    assert (tmp_path / "x.json").read_text() == "{}" and state["calls"] == 4
    _held(monkeypatch, "replace", 100)
    with pytest.raises(platform.FileBusy):
        atomic_write_text(tmp_path / "x.json", "[]")
    assert (tmp_path / "x.json").read_text() == "{}"
    assert [p.name for p in tmp_path.iterdir()] == ["x.json"]  # no temporary file left


def test_metrics_rows_wait_in_memory_while_a_spreadsheet_holds_the_csv(tmp_path, monkeypatch, caplog):
    """Windows: a spreadsheet that has metrics.csv open refuses the trainer's append. The rows wait
    (said once), the trainer does not, and they are all written once the file is free."""
    import builtins

    from tmrl.metrics import MetricsLogger

    log = MetricsLogger("run", folder=tmp_path, console=False, tensorboard=False)
    log.log_round({"round": 1, "loss_critic": 0.5})
    real_open = builtins.open
    held = {"on": True}

    def open_(file: Any, mode: str = "r", *args: Any, **kwargs: Any) -> Any:
        if held["on"] and str(file).endswith("metrics.csv") and "a" in mode:
            raise PermissionError(13, "The process cannot access the file (emulated)", str(file))
        return real_open(file, mode, *args, **kwargs)

    monkeypatch.setattr(builtins, "open", open_)
    with caplog.at_level("WARNING", logger="tmrl.metrics"):
        for k in (2, 3, 4):
            log.log_round({"round": k, "loss_critic": 0.5})
    assert sum("held by another program" in r.getMessage() for r in caplog.records) == 1
    held["on"] = False
    log.log_round({"round": 5, "loss_critic": 0.5})
    rows = (tmp_path / "logs" / "run" / "metrics.csv").read_text().splitlines()
    assert rows[0].startswith("round") and [r.split(",")[0] for r in rows[1:]] == ["1", "2", "3", "4", "5"]


# ------------------------------------------------------------------------------------------------
# a vanished peer: keepalive within a minute on every system


class _Sock:
    """A socket's option calls, recorded (the seam: what the system would be told)."""

    def __init__(self) -> None:
        self.options: dict[tuple[int, int], int] = {}
        self.ioctls: list[tuple[Any, Any]] = []

    def setsockopt(self, level: int, option: int, value: int) -> None:
        self.options[(level, option)] = value

    def ioctl(self, code: Any, value: Any) -> None:
        self.ioctls.append((code, value))


@pytest.mark.linux  # (macOS has no TCP_KEEPIDLE: the next test)
def test_keepalive_notices_a_vanished_peer_within_a_minute_on_linux():
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        assert platform.keep_alive(s)
        assert s.getsockopt(socket.SOL_SOCKET, socket.SO_KEEPALIVE) == 1
        idle = s.getsockopt(socket.IPPROTO_TCP, socket.TCP_KEEPIDLE)
        interval = s.getsockopt(socket.IPPROTO_TCP, socket.TCP_KEEPINTVL)
        count = s.getsockopt(socket.IPPROTO_TCP, socket.TCP_KEEPCNT)
    assert idle + interval * count <= 60


def test_keepalive_on_macos_uses_its_idle_option(monkeypatch):
    monkeypatch.setattr(platform, "MACOS", True)
    monkeypatch.delattr(socket, "TCP_KEEPIDLE")  # macOS has TCP_KEEPALIVE (0x10) instead
    sock = _Sock()
    assert platform.keep_alive(sock)
    idle = sock.options[(socket.IPPROTO_TCP, getattr(socket, "TCP_KEEPALIVE", 0x10))]
    total = idle + sock.options[(socket.IPPROTO_TCP, socket.TCP_KEEPINTVL)] * sock.options[
        (socket.IPPROTO_TCP, socket.TCP_KEEPCNT)]
    assert sock.options[(socket.SOL_SOCKET, socket.SO_KEEPALIVE)] == 1 and total <= 60


def test_keepalive_on_windows_sets_its_timings_in_one_call(monkeypatch):
    monkeypatch.setattr(platform, "WINDOWS", True)
    monkeypatch.setattr(socket, "SIO_KEEPALIVE_VALS", 0x98000004, raising=False)
    sock = _Sock()
    assert platform.keep_alive(sock)
    [(code, (on, idle_ms, interval_ms))] = sock.ioctls
    assert code == 0x98000004 and on == 1
    assert idle_ms / 1000 + 10 * interval_ms / 1000 <= 60  # Windows always sends 10 probes


# ------------------------------------------------------------------------------------------------
# stopping a child, dying with a parent: the lifeline, natively and with Windows emulated

_CHILD = textwrap.dedent("""
    import os, signal, sys, time
    from pathlib import Path
    from tmrl import platform

    out = Path(sys.argv[1])
    stubborn = sys.argv[2] == "stubborn"

    def put(name, text):  # whole or not at all: the test reads as soon as the name appears
        (out / (name + ".part")).write_text(text)
        os.replace(out / (name + ".part"), out / name)

    signal.signal(signal.SIGINT, signal.default_int_handler)
    state = platform.watch_lifeline(on_orphaned=lambda: put("orphan-cleanup", "done"), grace=1.0)
    put("ready", "watching" if state is not None else "no lifeline")
    while True:
        try:
            while True:
                time.sleep(0.05)
        except KeyboardInterrupt:
            put("interrupted", "orphaned" if state.orphaned.is_set() else "asked")
            if not stubborn:
                sys.exit(0)
""")

_PARENT = textwrap.dedent("""
    import sys, time
    from tmrl import platform

    child = platform.Child([sys.executable, "-c", sys.argv[1], sys.argv[2], sys.argv[3]])
    print(child.pid, flush=True)
    while True:
        time.sleep(0.1)
""")


def _wait_file(path: Path, timeout: float) -> str:
    deadline = time.monotonic() + timeout
    while not path.exists():
        if time.monotonic() > deadline:
            raise AssertionError(f"{path.name} did not appear within {timeout} s")
        time.sleep(0.02)
    return path.read_text()


def _gone(pid: int, timeout: float) -> bool:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if not process_support.alive(pid):  # a zombie (its parent gone, not yet reaped) counts as gone
            return True
        time.sleep(0.05)
    return False


@pytest.mark.parametrize("emulate", EMULATE)
def test_a_child_asked_to_stop_stops_like_ctrl_c(tmp_path, monkeypatch, emulate):
    for key, value in _env(emulate).items():
        monkeypatch.setenv(key, value)
    if not emulate:
        monkeypatch.delenv("TMRL_EMULATE", raising=False)
    child = platform.Child([sys.executable, "-c", _CHILD, str(tmp_path), "polite"])
    try:
        assert _wait_file(tmp_path / "ready", 60) == "watching"
        child.ask_stop()
        assert child.wait(10) == 0
        assert (tmp_path / "interrupted").read_text() == "asked"
        assert not (tmp_path / "orphan-cleanup").exists()
    finally:
        child.kill()


def test_stop_children_ends_a_child_that_ignores_the_request(tmp_path, monkeypatch):
    monkeypatch.setenv("PYTHONPATH", _env()["PYTHONPATH"])
    child = platform.Child([sys.executable, "-c", _CHILD, str(tmp_path), "stubborn"])
    assert _wait_file(tmp_path / "ready", 60) == "watching"
    t0 = time.monotonic()
    platform.stop_children([child], grace=1.0)
    assert child.poll() is not None and time.monotonic() - t0 < 5.0
    assert (tmp_path / "interrupted").read_text() == "asked"


@pytest.mark.parametrize("stubborn", [False, True], ids=["stops", "stubborn"])
@pytest.mark.parametrize("emulate", EMULATE)
def test_a_child_whose_parent_is_killed_stops_and_cleans_up(tmp_path, emulate, stubborn):
    """The parent killed outright (SIGKILL here, TerminateProcess on Windows): the lifeline closes,
    the child stops as on Ctrl-C; one that does not stop is ended after the grace, its clean-up
    done. With Windows emulated, getppid never changes: only the lifeline can tell."""
    parent = subprocess.Popen([sys.executable, "-c", _PARENT, _CHILD, str(tmp_path),
                               "stubborn" if stubborn else "polite"], env=_env(emulate), stdout=subprocess.PIPE,
                              text=True)
    try:
        child_pid = int(parent.stdout.readline())
        assert _wait_file(tmp_path / "ready", 60) == "watching"
        parent.kill()
        parent.wait(10)
        assert _wait_file(tmp_path / "interrupted", 10) == "orphaned"
        if stubborn:
            assert _wait_file(tmp_path / "orphan-cleanup", 10) == "done"
        assert _gone(child_pid, 10)
    finally:
        if parent.poll() is None:
            parent.kill()


def test_a_process_started_without_a_lifeline_watches_nothing(monkeypatch):
    monkeypatch.delenv(platform.LIFELINE_ENV, raising=False)
    assert platform.watch_lifeline() is None


# ------------------------------------------------------------------------------------------------
# macOS: --device auto takes Apple's GPU where PyTorch has it


def test_device_auto_takes_mps_on_a_mac_and_cuda_first(monkeypatch):
    import torch

    from tmrl.errors import UserError
    from tmrl.util import resolve_device

    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    monkeypatch.setattr(torch.backends.mps, "is_available", lambda: True)
    assert resolve_device("auto") == "mps" and resolve_device("MPS") == "mps"
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    assert resolve_device("auto") == "cuda"
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    monkeypatch.setattr(torch.backends.mps, "is_available", lambda: False)
    assert resolve_device("auto") == "cpu"
    with pytest.raises(UserError, match="--device mps: .*no usable Metal backend"):
        resolve_device("mps")
