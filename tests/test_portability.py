"""Windows and macOS, checked on Linux (docs/testing.md, "On every OS").

- The two ``ast`` rules of tests/portability_rules.py, proven on planted code, then run on the
  repository: no POSIX-only call outside ``tmrl/platform.py`` or a platform branch (tmrl/,
  examples/, bench/; tests/ behind the linux and posix markers), and no untimed blocking wait that
  Ctrl-C cannot interrupt on Windows (tmrl/, examples/).
- Under the Windows emulation of tests/emulation (``TMRL_EMULATE=windows``: the POSIX-only names
  of ``os``, ``signal`` and ``select`` gone), every module of the package imports and pytest
  collects every test module with no error.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest
from portability_rules import Finding, posix_only_uses, python_files, untimed_waits

REPO = Path(__file__).resolve().parents[1]
TESTS = REPO / "tests"
EMULATION = TESTS / "emulation"

PLATFORM_MODULE = "tmrl/platform.py"
"""The one module where POSIX-only calls belong (the platform differences, in one place)."""

LEAD_FILES = ("tmrl/sim/", "tmrl/roles.py", "tmrl/cli.py", "tmrl/transport/", PLATFORM_MODULE)
"""Files whose platform work is under way elsewhere (issue 48's stop path, parent watch, NATS)."""

_LEAD_FIXES_PENDING: set[tuple[str, str]] = set()
# (file, rule) pairs the POSIX-only rule finds in LEAD_FILES, each removed with its fix. Empty since
# tmrl.platform landed: the eight it found before (demo.py's start_new_session, send_signal(SIGINT),
# os.killpg and SIGKILL; os.getppid in sim/lifeline.py and transport/_netcommon.py; start_new_session
# and preexec_fn in transport/_nats_server.py) all moved into tmrl/platform.py.
"""POSIX-only uses waiting for their fix in the lead's files: to be emptied, never grown."""

_LEAD_FIXES_PENDING_WAITS: set[tuple[str, str]] = set()
# (file, the call's line as written) the untimed-wait rule finds in LEAD_FILES, each removed with its
# fix. Empty since tmrl.platform waits in slices after a kill: before it, the rule found demo.py's
# p.wait(), _nats_server.py's self._started.wait(), proc.wait() and code = proc.wait(), and
# _process.py's self.proc.wait(); then tmrl/platform.py's two return proc.wait() after a kill.
"""Untimed waits waiting for their fix in the lead's files: to be emptied, never grown."""

DELIBERATE_WAITS: dict[tuple[str, str], str] = {
    # (file, the call's line as written) -> why it is no untimed wait on a main thread
    ("tmrl/realtime/env.py", "self.wait()"): "RealTimeEnv.wait(), rtgym's pause: it waits through receive()",
    ("tmrl/realtime/env.py",
     'self._call_interface(lambda itf: itf.wait() if callable(getattr(itf, "wait", None)) else None)'):
        "the interface's wait() (rtgym's pause hook), called through receive()",
    ("tmrl/realtime/runner.py", "job = self.jobs.get()"):
        "the time-step thread (a daemon) waits for its next job; the main thread waits in receive()",
}
"""Calls the untimed-wait rule flags that are not blocking waits on a main thread, with the reason."""


def _posix_findings() -> list[Finding]:
    found = []
    for path in python_files("tmrl", "examples", "bench"):
        if path.relative_to(REPO).as_posix() != PLATFORM_MODULE:
            found += posix_only_uses(path)
    return found


def _report(findings: list[Finding]) -> str:
    return "\n".join(str(f) for f in findings)


# --------------------------------------------------------------------------------------------------
# the rules on the repository


def test_no_posix_only_call_outside_the_platform_module_or_a_platform_branch():
    findings = _posix_findings()
    new = [f for f in findings if (f.path, f.rule) not in _LEAD_FIXES_PENDING]
    assert not new, (
        "POSIX-only calls (Windows has none of these): move them into tmrl/platform.py, or behind an "
        "explicit platform branch (tests/portability_rules.py says which):\n" + _report(new))
    fixed = _LEAD_FIXES_PENDING - {(f.path, f.rule) for f in findings}
    assert not fixed, f"fixed: remove from _LEAD_FIXES_PENDING (tests/test_portability.py): {sorted(fixed)}"


def test_pending_fixes_are_in_the_lead_files_only():
    for path, _ in _LEAD_FIXES_PENDING | _LEAD_FIXES_PENDING_WAITS:
        assert path.startswith(LEAD_FILES), path


def test_tests_use_posix_only_calls_only_behind_the_linux_or_posix_marker():
    found = []
    for path in python_files("tests"):
        if EMULATION in path.parents or path.name == "portability_rules.py":
            continue  # the emulation and the rule name POSIX-only things by design
        found += posix_only_uses(path, tests=True)
    assert not found, ("POSIX-only calls in tests: mark the test @pytest.mark.posix or @pytest.mark.linux, "
                       "or use tests/process_support.py (psutil):\n" + _report(found))


def test_no_untimed_wait_that_ctrl_c_cannot_interrupt_on_windows():
    found = [f for path in python_files("tmrl", "examples") for f in untimed_waits(path)]
    keys = {(f.path, f.code) for f in found}
    new = [f for f in found if (f.path, f.code) not in _LEAD_FIXES_PENDING_WAITS and (f.path, f.code)
           not in DELIBERATE_WAITS]
    assert not new, ("untimed waits (on Windows, Ctrl-C waits until they end): give them a timeout and loop, "
                     "or sleep in a loop (tmrl.realtime.clock.receive does):\n" + _report(new))
    stale = (_LEAD_FIXES_PENDING_WAITS | set(DELIBERATE_WAITS)) - keys
    assert not stale, f"no longer found: remove from _LEAD_FIXES_PENDING_WAITS or DELIBERATE_WAITS: {sorted(stale)}"


# --------------------------------------------------------------------------------------------------
# the rules on planted code


def _scan(tmp_path: Path, source: str, *, name: str = "tmrl/planted.py", tests: bool = False) -> list[Finding]:
    path = tmp_path / name
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(textwrap.dedent(source), encoding="utf-8")
    return posix_only_uses(path, tests=tests, root=tmp_path)


def test_a_planted_killpg_is_found_with_its_file_line_and_rule(tmp_path):
    found = _scan(tmp_path, """\
        import os, signal

        def stop(proc):
            os.killpg(proc.pid, signal.SIGTERM)
        """)
    assert [str(f) for f in found] == ["tmrl/planted.py:4: os.killpg (POSIX only): os.killpg(proc.pid, signal.SIGTERM)"]


@pytest.mark.parametrize("source,rules", [
    ("os.getppid()", ["os.getppid (POSIX only)"]),
    ("signal.signal(signal.SIGHUP, h)", ["signal.SIGHUP (POSIX only)"]),
    ("x = [signal.SIGKILL, signal.SIGSTOP, signal.SIGUSR1, signal.SIGUSR2]", ["signal.SIGKILL (POSIX only)",
     "signal.SIGSTOP (POSIX only)", "signal.SIGUSR1 (POSIX only)", "signal.SIGUSR2 (POSIX only)"]),
    ("from signal import SIGKILL", ["signal.SIGKILL (POSIX only)"]),
    ("p.send_signal(signal.SIGINT)", ["send_signal(SIGINT) (Popen refuses it on Windows)"]),
    ("subprocess.Popen(cmd, start_new_session=True)", ["start_new_session= (POSIX only)"]),
    ("open(f'/proc/{pid}/stat')", ["/proc path (Linux only)"]),
    ("os.listdir('/proc')", ["/proc path (Linux only)"]),
    ("import fcntl", ["import fcntl (no such module on Windows)"]),
    ("os.getloadavg(); select.poll()", ["os.getloadavg (POSIX only)", "select.poll (POSIX only)"]),
    # portable: what Windows has, a constant that says no, a name read with a default
    ("p.send_signal(signal.SIGTERM); os.kill(pid, signal.SIGTERM)", []),
    ("subprocess.Popen(cmd, start_new_session=False)", []),
    ("sig = getattr(signal, 'SIGKILL', None)", []),
    ("def parent_died():\n    '''/proc/self/status tells (a docstring may name it).'''", []),
])
def test_the_posix_only_rule_on_one_line(tmp_path, source, rules):
    assert [f.rule for f in _scan(tmp_path, "import os, select, signal, subprocess\n" + source + "\n")] == rules


@pytest.mark.parametrize("source", [
    """\
    if sys.platform.startswith("linux"):
        import fcntl
    """,
    """\
    if os.name == "nt":
        proc.terminate()
    else:
        os.killpg(proc.pid, signal.SIGKILL)
    """,
    """\
    def stop(proc):
        if not platform.POSIX:
            return proc.terminate()
        os.killpg(proc.pid, signal.SIGKILL)
    """,
    """\
    if hasattr(os, "killpg"):
        os.killpg(pid, signal.SIGTERM)
    """,
    """\
    try:
        import fcntl
    except ImportError:
        fcntl = None
    """,
    """\
    try:
        import termios
    except ModuleNotFoundError:
        termios = None
    """,
    """\
    try:
        stop = os.killpg
    except AttributeError:
        stop = None
    """,
    """\
    dead = LINUX and os.getppid() == 1
    """,
    """\
    sig = signal.SIGKILL if WINDOWS is False else signal.SIGTERM
    """,
])
def test_a_platform_branch_allows_posix_only_calls(tmp_path, source):
    assert _scan(tmp_path, "import os, signal, sys\n" + textwrap.dedent(source)) == []


def test_a_branch_on_something_else_does_not(tmp_path):
    found = _scan(tmp_path, """\
        import os, signal
        if verbose:
            os.killpg(pid, signal.SIGTERM)
        try:
            import fcntl
        except OSError:
            pass
        """)
    assert [f.rule for f in found] == ["os.killpg (POSIX only)", "import fcntl (no such module on Windows)"]


def test_in_tests_the_markers_are_platform_branches_for_bodies_only(tmp_path):
    test_module = """\
        import os, signal, pytest

        @pytest.mark.posix
        def test_marked():
            os.kill(pid, signal.SIGKILL)

        @pytest.mark.parametrize("sig", [signal.SIGHUP])
        @pytest.mark.linux
        def test_marked_but_collected_everywhere(sig):
            open("/proc/self/status")

        def test_unmarked():
            os.killpg(pid, signal.SIGTERM)

        @pytest.mark.linux
        class TestMarked:
            def test_in_a_marked_class(self):
                os.getppid()
        """
    found = _scan(tmp_path, test_module, name="tests/test_planted.py", tests=True)
    assert [(f.line, f.rule) for f in found] == [(7, "signal.SIGHUP (POSIX only)"), (13, "os.killpg (POSIX only)")]
    # outside tests/ a marker means nothing; a module marked as a whole keeps its import-time code
    assert len(_scan(tmp_path, test_module, name="tmrl/planted.py")) == 5
    module = "import os, signal, pytest\npytestmark = pytest.mark.linux\nNAMES = {signal.SIGHUP: 'hup'}\n" \
             "def helper():\n    return os.listdir('/proc')\n"
    assert [f.line for f in _scan(tmp_path, module, name="tests/test_whole.py", tests=True)] == [3]


@pytest.mark.parametrize("source,flagged", [
    ("threading.Event().wait()", True),
    ("thread.join()", True),
    ("item = jobs.get()", True),
    ("lock.acquire()", True),
    ("out, err = proc.communicate()", True),
    ("item = jobs.get(block=True)", True),
    ("item = jobs.get(True)", True),
    ("thread.join(None)", True),
    ("event.wait(timeout=None)", True),
    ("event.wait(0.5)", False),
    ("event.wait(1)", False),
    ("thread.join(timeout=1)", False),
    ("item = jobs.get(timeout=0.2)", False),
    ("item = jobs.get(block=False)", False),
    ("lock.acquire(blocking=False)", False),
    ("value = d.get('key')", False),
    ("','.join(parts)", False),
    ("async def f():\n    await event.wait()", False),
])
def test_the_wait_rule_on_one_line(tmp_path, source, flagged):
    path = tmp_path / "planted.py"
    path.write_text(source + "\n", encoding="utf-8")
    found = untimed_waits(path, root=tmp_path)
    assert bool(found) == flagged, found
    if flagged:
        assert found[0].line == 1 and "without a timeout" in found[0].rule


# --------------------------------------------------------------------------------------------------
# the Windows emulation: every module imports, every test collects


def emulated(env: dict[str, str] | None = None) -> dict[str, str]:
    """This process's environment with the Windows emulation of tests/emulation switched on."""
    env = dict(os.environ if env is None else env)
    env["PYTHONPATH"] = os.pathsep.join(filter(None, [str(EMULATION), str(REPO), env.get("PYTHONPATH", "")]))
    env["TMRL_EMULATE"] = "windows"
    return env


IMPORT_ALL = """
import importlib, json, os, pkgutil, traceback
import tmrl
failed = {}
names = [m.name for m in pkgutil.walk_packages(tmrl.__path__, "tmrl.", onerror=lambda name: None)]
for name in ["tmrl", *names]:
    try:
        importlib.import_module(name)
    except BaseException as e:  # noqa: BLE001 (every failure is reported, with its kind)
        failed[name] = [type(e).__name__, getattr(e, "name", None), str(e)]
print(json.dumps({"modules": len(names) + 1, "killpg": hasattr(os, "killpg"), "failed": failed}))
"""

OPTIONAL = {"mss", "vgamepad", "cv2", "wandb", "nats", "Xlib", "matplotlib"}
"""Optional packages (the trackmania, wandb and nats extras): a module may fail for their absence."""


def _import_all(env: dict[str, str]) -> dict:
    out = subprocess.run([sys.executable, "-c", IMPORT_ALL], env=env, cwd=REPO, capture_output=True, text=True,
                         timeout=300, check=False)
    assert out.returncode == 0, out.stderr[-3000:]
    return json.loads(out.stdout.strip().splitlines()[-1])


def test_every_module_imports_under_the_windows_emulation():
    plain_env = {k: v for k, v in os.environ.items() if k != "TMRL_EMULATE"}  # (even when run emulated)
    plain = _import_all(dict(plain_env, PYTHONPATH=os.pathsep.join(filter(None, [str(REPO),
                                                                                 os.environ.get("PYTHONPATH")]))))
    windows = _import_all(emulated())
    assert plain["killpg"] and not windows["killpg"]  # the emulation did take effect
    assert windows["modules"] == plain["modules"] > 100
    for name, (kind, missing, msg) in plain["failed"].items():  # here, for a reason of its own
        assert kind in ("ImportError", "ModuleNotFoundError") and (missing or "").split(".")[0] in OPTIONAL, \
            f"{name}: {kind}: {msg}"
    only_windows = {name: why for name, why in windows["failed"].items() if name not in plain["failed"]}
    assert not only_windows, f"modules that fail to import without POSIX names: {only_windows}"


def test_every_test_module_collects_under_the_windows_emulation():
    out = subprocess.run([sys.executable, "-m", "pytest", "--collect-only", "-q", "-p", "no:cacheprovider", "tests"],
                         env=emulated(), cwd=REPO, capture_output=True, text=True, timeout=600, check=False)
    text = out.stdout + out.stderr
    assert out.returncode == 0 and " error" not in text.splitlines()[-1], text[-5000:]
    collected = {line.split("::", 1)[0] for line in out.stdout.splitlines() if "::" in line}
    modules = {p.relative_to(REPO).as_posix() for p in TESTS.glob("test_*.py")}
    assert modules - collected == set(), "test modules that collected no test"  # none quietly skipped


def test_marked_tests_skip_off_their_platform_with_the_allowed_reason_even_in_ci():
    # a posix module, a linux module: run under the emulation with CI=true, they skip and pass
    env = dict(emulated(), CI="true")
    out = subprocess.run([sys.executable, "-m", "pytest", "-q", "-rs", "-p", "no:cacheprovider",
                          "tests/test_stale_temporaries.py", "tests/test_stop_signals.py"],
                         env=env, cwd=REPO, capture_output=True, text=True, timeout=300, check=False)
    assert out.returncode == 0, out.stdout[-3000:]
    assert "failed" not in out.stdout and " passed" not in out.stdout, out.stdout[-3000:]
    assert "needs POSIX (signals, process groups, file modes or paths): not on Windows (allowed in CI" in out.stdout
    assert "needs Linux (/proc, prctl, inotify, Xvfb or uinput) (allowed in CI" in out.stdout
