"""What Linux, Windows and macOS do differently, answered in one place.

TrackMania runs on Windows, so a worker does too, often beside the server and the trainer; trainers
also run on Linux and macOS. Every role asks this module, and reads the same on every system:

- **Stopping a child and dying with a parent** (:class:`Child`, :func:`watch_lifeline`). A parent
  holds its child's standard input as a *lifeline*: one byte on it asks the child to stop cleanly
  (like Ctrl-C), and its end of file, which every system delivers when the parent dies however it
  died, tells the child it is orphaned. No POSIX signal, process group or parent-death signal is
  needed, so the same mechanism runs everywhere; the tests run it with the POSIX names removed.
  Programs that cannot watch a pipe (``nats-server``) are started by :func:`start_guarded`.
- **Files another process holds** (:func:`replace`, :func:`remove`, :func:`remove_tree`,
  :func:`read_bytes`, :func:`when_free`). Windows refuses to replace, rename or delete a file that
  a reader, an antivirus, a backup tool or a spreadsheet has open (a sharing violation); these
  retry with a short backoff, then say so in one exception or return value, never more.
- **Signals** (:data:`STOP_SIGNALS`, :func:`interrupt_main`), **a vanished peer**
  (:func:`keep_alive`) and **names Windows forbids** (:func:`name_problem`).

Decisions are made from what the running Python offers, not only from ``sys.platform``:
:data:`POSIX` is true where process groups and POSIX signals exist. Code outside this module
never calls ``os.killpg``, ``os.getppid``, ``signal.SIGKILL`` and the other POSIX-only names
itself (tests/test_portability.py checks it).
"""

from __future__ import annotations

import contextlib
import logging
import os
import shutil
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any, TypeVar

__all__ = [
    "BUSY_DELAYS",
    "LIFELINE_ENV",
    "LINUX",
    "MACOS",
    "ORPHAN_GRACE",
    "POSIX",
    "STOP_SIGNALS",
    "WINDOWS",
    "Child",
    "FileBusy",
    "Lifeline",
    "interrupt_main",
    "keep_alive",
    "name_problem",
    "new_group_kwargs",
    "parent_changed",
    "parent_pid",
    "read_bytes",
    "remove",
    "remove_tree",
    "replace",
    "set_parent_death_signal",
    "start_guarded",
    "stop_guarded",
    "watch_lifeline",
    "when_free",
]

logger = logging.getLogger(__name__)

T = TypeVar("T")

WINDOWS = sys.platform == "win32"
MACOS = sys.platform == "darwin"
LINUX = sys.platform.startswith("linux")
#: Process groups and POSIX signals exist (``os.killpg``, ``SIGKILL``, ``SIGHUP``): Linux and macOS.
POSIX = hasattr(os, "killpg") and hasattr(signal, "SIGKILL") and hasattr(signal, "SIGHUP")

#: The signals that ask a process to stop cleanly where they exist: Ctrl-C, ``kill`` or a service
#: manager (SIGTERM), a closed terminal (SIGHUP, POSIX), Ctrl-Break (SIGBREAK, Windows).
STOP_SIGNALS: tuple[int, ...] = tuple(
    getattr(signal, name) for name in ("SIGINT", "SIGTERM", "SIGHUP", "SIGBREAK") if hasattr(signal, name)
)


# ================================================================================================
# stopping children, dying with a parent

#: Environment variable set for a child whose standard input is its lifeline (:class:`Child`).
LIFELINE_ENV = "TMRL_LIFELINE"
#: The byte a parent writes on the lifeline to ask its child to stop.
_STOP_BYTE = b"S"
#: Seconds an orphaned child may take to stop cleanly before it ends itself (the whole run must be
#: gone within 10 s of its parent's death).
ORPHAN_GRACE = 6.0


def new_group_kwargs() -> dict[str, Any]:
    """``subprocess.Popen`` arguments that put a child in a process group of its own, so that a
    Ctrl-C typed in the terminal reaches the parent only, which then stops the child in order: a
    new session on POSIX, a new process group on Windows (which also turns Ctrl-C off in it)."""
    if WINDOWS:
        return {"creationflags": getattr(subprocess, "CREATE_NEW_PROCESS_GROUP", 0x200)}
    if POSIX:
        return {"start_new_session": True}
    return {}


class Child:
    """A child process tied to this one by a lifeline on its standard input.

    The child calls :func:`watch_lifeline` first thing: then :meth:`ask_stop` stops it like Ctrl-C
    would, on every system, and it stops by itself (and calls its clean-up) when this process dies.

    Args:
        cmd: the command line.
        env: its environment (default: this process's), to which :data:`LIFELINE_ENV` is added.
        stdout, stderr: as for ``subprocess.Popen``.
        own_group: start it in a process group of its own (:func:`new_group_kwargs`).
    """

    def __init__(self, cmd: Sequence[str], env: dict[str, str] | None = None, stdout: Any = None,
                 stderr: Any = None, own_group: bool = True) -> None:
        env = dict(os.environ if env is None else env)
        env[LIFELINE_ENV] = "1"
        self.own_group = own_group and POSIX
        self.proc = subprocess.Popen(list(cmd), stdin=subprocess.PIPE, stdout=stdout, stderr=stderr, env=env,
                                     **(new_group_kwargs() if own_group else {}))

    @property
    def pid(self) -> int:
        """The child's process id."""
        return self.proc.pid

    @property
    def returncode(self) -> int | None:
        """Its exit code once it has exited, else None."""
        return self.proc.returncode

    def poll(self) -> int | None:
        """Its exit code if it has exited, else None."""
        return self.proc.poll()

    def wait(self, timeout: float | None = None) -> int:
        """Wait for it to exit (``subprocess.TimeoutExpired`` after ``timeout`` seconds)."""
        return self.proc.wait(timeout)

    def ask_stop(self) -> None:
        """Ask the child to stop cleanly (it stops as on Ctrl-C), then let go of the lifeline. Never
        blocks: the pipe holds nothing else, and a child that is gone is simply gone."""
        stdin = self.proc.stdin
        if stdin is None or stdin.closed:
            return
        with contextlib.suppress(OSError, ValueError):
            stdin.write(_STOP_BYTE)
            stdin.flush()
        with contextlib.suppress(OSError, ValueError):
            stdin.close()

    def kill(self) -> None:
        """End the child at once, with what it started in its group (POSIX); elsewhere the child
        only: the processes it started watch their own lifelines and follow within a second."""
        if self.own_group and self.proc.poll() is None:
            with contextlib.suppress(ProcessLookupError, PermissionError):
                os.killpg(self.proc.pid, signal.SIGKILL)
        elif self.proc.poll() is None:
            with contextlib.suppress(OSError):
                self.proc.kill()
        with contextlib.suppress(OSError, ValueError):
            if self.proc.stdin is not None:
                self.proc.stdin.close()


def stop_children(children: Sequence[Child], grace: float) -> None:
    """Ask every child to stop, newest first (a child that started late depends on the ones
    before it), give them ``grace`` seconds together, then end what is left and reap everything.
    On POSIX what a child left in its group (its network process) goes too."""
    for child in reversed(children):
        if child.poll() is None:
            child.ask_stop()
    deadline = time.monotonic() + grace
    for child in reversed(children):
        with contextlib.suppress(subprocess.TimeoutExpired):
            child.wait(max(0.0, deadline - time.monotonic()))
        child.kill()  # the child's group on POSIX, even when the child itself has exited
        with contextlib.suppress(subprocess.TimeoutExpired):
            child.wait(5.0)


class Lifeline:
    """The child's side of :class:`Child`: what arrived on the lifeline.

    Attributes:
        stop_asked: the parent asked this process to stop.
        orphaned: the parent died (the lifeline closed without a stop request).
    """

    def __init__(self) -> None:
        self.stop_asked = threading.Event()
        self.orphaned = threading.Event()


def interrupt_main() -> None:
    """Raise ``KeyboardInterrupt`` in the main thread soon, as Ctrl-C does. On POSIX a signal to
    the main thread also wakes it from a blocking call; elsewhere the main thread sees it at its
    next Python instruction (it never waits without a timeout: see DESIGN's rule)."""
    main = threading.main_thread()
    if POSIX and hasattr(signal, "pthread_kill") and main.ident is not None:
        with contextlib.suppress(OSError, ValueError):
            signal.pthread_kill(main.ident, signal.SIGINT)
            return
    import _thread

    _thread.interrupt_main()


def watch_lifeline(on_orphaned: Callable[[], None] | None = None, grace: float = ORPHAN_GRACE,
                   exit_code: int = 143) -> Lifeline | None:
    """In a child started by :class:`Child`: a thread reads the lifeline. A stop request raises
    ``KeyboardInterrupt`` in the main thread (make sure SIGINT has Python's default handler). The
    parent's death does the same, then, after ``grace`` seconds, calls ``on_orphaned`` (e.g. to
    remove a run folder nobody else will) and ends the process with ``exit_code``, whatever the
    main thread is doing.

    Returns:
        What arrived, as it arrives; None when this process has no lifeline (its parent did not set
        :data:`LIFELINE_ENV`), so nothing is watched.
    """
    if os.environ.pop(LIFELINE_ENV, "") != "1":  # popped: a grandchild has a lifeline of its own or none
        return None
    state = Lifeline()
    try:
        fd = sys.stdin.fileno() if sys.stdin is not None else 0
    except (OSError, ValueError, AttributeError):
        fd = 0

    def watch() -> None:
        while True:
            try:
                data = os.read(fd, 64)
            except OSError:
                data = b""
            if not data:
                break
            if _STOP_BYTE in data and not state.stop_asked.is_set():
                state.stop_asked.set()
                interrupt_main()
        if state.stop_asked.is_set():
            return  # the parent let go after asking: a normal stop
        state.orphaned.set()
        interrupt_main()
        time.sleep(grace)
        try:
            if on_orphaned is not None:
                on_orphaned()
        finally:
            os._exit(exit_code)

    threading.Thread(target=watch, name="tmrl-lifeline", daemon=True).start()
    return state


def parent_pid() -> int:
    """This process's parent's id now."""
    return os.getppid()


def parent_changed(original: int) -> bool:
    """Whether this process's parent is no longer ``original``: on POSIX the parent died and the
    process was handed to another one. Never true on Windows, which keeps a dead parent's id: the
    lifeline (or the pipe a process already reads) is what tells there."""
    return os.getppid() != original


def set_parent_death_signal(signum: int | None = None) -> bool:
    """Linux: ask the kernel to send ``signum`` (default SIGTERM) to this process when the thread
    that started it ends. Returns whether it is armed (False on every other system: use a lifeline)."""
    if not (LINUX and POSIX):
        return False
    try:
        import ctypes

        libc = ctypes.CDLL(None, use_errno=True)
        return libc.prctl(1, int(signal.SIGTERM if signum is None else signum), 0, 0, 0) == 0  # PR_SET_PDEATHSIG
    except (OSError, AttributeError):
        return False


# --- programs that cannot watch a pipe ---------------------------------------------------------


def _linux_death_hook() -> Callable[[], Any] | None:
    """A function run in the child between fork and exec that arms its parent-death signal
    (resolved here, in the parent: the child runs a bare C call)."""
    if not (LINUX and POSIX):
        return None
    try:
        import ctypes

        prctl = ctypes.CDLL(None, use_errno=True).prctl
    except (OSError, AttributeError):
        return None
    sigterm = int(signal.SIGTERM)
    return lambda: prctl(1, sigterm)  # PR_SET_PDEATHSIG = 1


class _WindowsJob:
    """A Windows job object that ends every process in it when its last handle closes, which
    happens when this process exits, however it exits."""

    _handle: Any = None
    _lock = threading.Lock()

    @classmethod
    def assign(cls, proc: subprocess.Popen) -> bool:
        import ctypes
        from ctypes import wintypes

        kernel32 = ctypes.WinDLL("kernel32", use_last_error=True)  # type: ignore[attr-defined,unused-ignore]
        with cls._lock:
            if cls._handle is None:
                class IoCounters(ctypes.Structure):
                    _fields_ = [(n, ctypes.c_ulonglong) for n in ("reads", "writes", "others", "read_bytes",
                                                                    "write_bytes", "other_bytes")]

                class BasicLimits(ctypes.Structure):
                    _fields_ = [("per_process_time", ctypes.c_int64), ("per_job_time", ctypes.c_int64),
                                ("flags", wintypes.DWORD), ("min_ws", ctypes.c_size_t),
                                ("max_ws", ctypes.c_size_t), ("processes", wintypes.DWORD),
                                ("affinity", ctypes.c_size_t), ("priority", wintypes.DWORD),
                                ("scheduling", wintypes.DWORD)]

                class ExtendedLimits(ctypes.Structure):
                    _fields_ = [("basic", BasicLimits), ("io", IoCounters), ("process_memory", ctypes.c_size_t),
                                ("job_memory", ctypes.c_size_t), ("peak_process", ctypes.c_size_t),
                                ("peak_job", ctypes.c_size_t)]

                kernel32.CreateJobObjectW.restype = wintypes.HANDLE
                kernel32.CreateJobObjectW.argtypes = (ctypes.c_void_p, wintypes.LPCWSTR)
                kernel32.SetInformationJobObject.argtypes = (wintypes.HANDLE, ctypes.c_int, ctypes.c_void_p,
                                                             wintypes.DWORD)
                handle = kernel32.CreateJobObjectW(None, None)
                if not handle:
                    return False
                limits = ExtendedLimits()
                limits.basic.flags = 0x2000  # JOB_OBJECT_LIMIT_KILL_ON_JOB_CLOSE
                if not kernel32.SetInformationJobObject(handle, 9, ctypes.byref(limits), ctypes.sizeof(limits)):
                    return False  # 9: JobObjectExtendedLimitInformation
                cls._handle = handle
            kernel32.AssignProcessToJobObject.argtypes = (wintypes.HANDLE, wintypes.HANDLE)
            return bool(kernel32.AssignProcessToJobObject(cls._handle, int(proc._handle)))  # type: ignore[attr-defined]


def start_guarded(cmd: Sequence[str], **popen: Any) -> subprocess.Popen:
    """Start a program that cannot watch a lifeline (``nats-server``) so that it never outlives
    this process: Linux arms its parent-death signal, Windows puts it in a job object that ends
    it when this process exits, and elsewhere (macOS) a small guard process between the two
    watches this process's lifeline and stops the program cleanly when it closes. Stop it with
    :func:`stop_guarded`. The program runs in a process group of its own.

    Args:
        cmd: the command line.
        popen: more ``subprocess.Popen`` arguments (not ``stdin``).
    """
    if WINDOWS:
        proc = subprocess.Popen(list(cmd), stdin=subprocess.DEVNULL, **new_group_kwargs(), **popen)
        try:
            if not _WindowsJob.assign(proc):
                logger.debug("could not put %s in a job object", cmd[0])
        except (OSError, AttributeError, ValueError):
            logger.debug("could not put %s in a job object", cmd[0], exc_info=True)
        return proc
    hook = _linux_death_hook()
    if hook is not None:
        return subprocess.Popen(list(cmd), stdin=subprocess.DEVNULL, preexec_fn=hook,  # noqa: PLW1509
                                **new_group_kwargs(), **popen)
    guard = [sys.executable, "-m", "tmrl.platform", "--guard", *cmd]
    env = dict(popen.pop("env", None) or os.environ)
    root = str(Path(__file__).resolve().parents[1])  # this tmrl, wherever the caller's path points
    env["PYTHONPATH"] = root + (os.pathsep + env["PYTHONPATH"] if env.get("PYTHONPATH") else "")
    return subprocess.Popen(guard, stdin=subprocess.PIPE, env=env, **new_group_kwargs(), **popen)


def stop_guarded(proc: subprocess.Popen, timeout: float) -> int:
    """Stop a program started by :func:`start_guarded` cleanly (POSIX: SIGTERM; Windows:
    Ctrl-Break to its process group, which Go programs such as ``nats-server`` take as an
    interrupt; a guarded one: through its guard), and end it after ``timeout`` seconds.
    Returns its exit code."""
    if proc.poll() is None:
        if proc.stdin is not None:  # the guard: it stops the program, then exits with its code
            with contextlib.suppress(OSError, ValueError):
                proc.stdin.write(_STOP_BYTE)
                proc.stdin.flush()
                proc.stdin.close()
        elif WINDOWS:
            try:
                proc.send_signal(getattr(signal, "CTRL_BREAK_EVENT", 1))
            except (OSError, ValueError):
                proc.terminate()
        else:
            with contextlib.suppress(OSError):
                proc.terminate()  # SIGTERM
    try:
        return proc.wait(timeout)
    except subprocess.TimeoutExpired:
        if timeout > 0:
            logger.warning("%s did not stop within %.0f s; ending it", proc.args[0] if proc.args else "a child", timeout)
    if POSIX:  # its group: the program and, where there is one, its guard
        with contextlib.suppress(ProcessLookupError, PermissionError):
            os.killpg(proc.pid, signal.SIGKILL)
    with contextlib.suppress(OSError):
        proc.kill()
    return _reap(proc)


def _reap(proc: subprocess.Popen) -> int:
    """The exit code of a process just killed (waited for in slices: Ctrl-C still reaches the
    waiting thread on Windows)."""
    while True:
        try:
            return proc.wait(1.0)
        except subprocess.TimeoutExpired:
            continue


def _guard_main(cmd: list[str]) -> int:
    """The guard of :func:`start_guarded`: run ``cmd``, stop it cleanly when the lifeline (this
    process's standard input) asks or closes, and exit with its code."""
    with contextlib.suppress(ValueError, OSError):
        signal.signal(signal.SIGINT, signal.SIG_IGN)  # the parent decides when the program stops
    proc = subprocess.Popen(cmd, stdin=subprocess.DEVNULL)
    done = threading.Event()

    def watch() -> None:
        with contextlib.suppress(OSError):
            while True:
                data = os.read(0, 64)
                if not data or _STOP_BYTE in data:
                    break
        done.set()

    threading.Thread(target=watch, daemon=True).start()
    with contextlib.suppress(ValueError, OSError):
        signal.signal(signal.SIGTERM, lambda *_: done.set())
    while proc.poll() is None and not done.wait(0.2):
        pass
    if proc.poll() is None:
        with contextlib.suppress(OSError):
            proc.terminate()
        try:
            proc.wait(10.0)
        except subprocess.TimeoutExpired:
            proc.kill()
    return _reap(proc)


# ================================================================================================
# files that another process holds

#: Waits between the attempts at a file another process holds, seconds (about 2 s in all).
BUSY_DELAYS = (0.005, 0.01, 0.02, 0.04, 0.08, 0.15, 0.25, 0.4, 0.5, 0.5)


class FileBusy(PermissionError):
    """A file stayed held by another process (or unwritable) through every retry."""


def _busy(err: OSError) -> bool:
    """A sharing violation: Windows' ``PermissionError`` (errors 5, 32, 33), or an emulation of it."""
    return isinstance(err, PermissionError) or getattr(err, "winerror", None) in (5, 32, 33)


def when_free(fn: Callable[..., T], *args: Any, what: str = "") -> T:
    """Call ``fn(*args)``, again after each of :data:`BUSY_DELAYS` while it fails because another
    process holds a file.

    Raises:
        FileBusy: still held after the last delay (one line naming ``what`` or the file).
        OSError: any other failure, at once.
    """
    for delay in (*BUSY_DELAYS, None):
        try:
            return fn(*args)
        except OSError as err:
            if not _busy(err):
                raise
            if delay is None:
                target = what or (str(args[-1]) if args else getattr(fn, "__name__", "a file"))
                raise FileBusy(err.errno or 13, f"{target} is held by another process (an antivirus, a backup or "
                                                f"sync tool, an open editor); tried for "
                                                f"{sum(BUSY_DELAYS):.0f} s") from None
            time.sleep(delay)
    raise AssertionError("unreachable")


def replace(src: str | os.PathLike[str], dst: str | os.PathLike[str]) -> None:
    """``os.replace(src, dst)``: atomic on every system, retried while another process holds
    either file. Raises :class:`FileBusy` when it stays held."""
    when_free(os.replace, src, dst, what=str(dst))


def remove(path: str | os.PathLike[str]) -> bool:
    """Delete a file, retrying while another process holds it. Returns whether it is gone (a
    missing file counts as gone); a file still held is left, with a debug line, never an error."""
    try:
        when_free(os.unlink, path, what=str(path))
    except FileNotFoundError:
        pass
    except OSError as err:
        logger.debug("could not remove %s: %s", path, err)
        return False
    return True


def remove_tree(path: str | os.PathLike[str]) -> bool:
    """Delete a folder and everything in it, retrying each entry that another process holds.
    Returns whether the folder is gone."""
    def retry(func: Callable[..., Any], target: str, _info: Any) -> None:
        try:
            when_free(func, target)
        except FileNotFoundError:
            pass
        except OSError as err:
            logger.debug("could not remove %s: %s", target, err)

    for _ in range(3):
        if not os.path.lexists(path):
            return True
        try:
            shutil.rmtree(path, onerror=retry)  # onerror: the name every supported Python knows
        except OSError as err:
            logger.debug("could not remove %s: %s", path, err)
    return not os.path.lexists(path)


def read_bytes(path: str | os.PathLike[str]) -> bytes:
    """The bytes of a file, retrying while another process holds it (Windows refuses to open a
    file being replaced). Raises ``FileNotFoundError`` for a missing file, :class:`FileBusy`
    for one held throughout."""
    return when_free(Path(path).read_bytes, what=str(path))


# ================================================================================================
# signals, sockets, names


def keep_alive(sock: Any, idle: int = 15, interval: int = 4, count: int = 5) -> bool:
    """Make a TCP socket notice a peer whose machine vanished (no FIN, no RST) within a minute on
    every system: probes after ``idle`` seconds of silence, every ``interval`` seconds, ``count``
    of them (Linux, macOS: 35 s with the defaults; Windows always sends 10: 55 s). Returns whether
    the timing could be set (the system's defaults, two hours, apply otherwise)."""
    import socket

    try:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_KEEPALIVE, 1)
        if WINDOWS and hasattr(socket, "SIO_KEEPALIVE_VALS"):
            sock.ioctl(socket.SIO_KEEPALIVE_VALS, (1, idle * 1000, interval * 1000))
            return True
        idle_option = getattr(socket, "TCP_KEEPIDLE", None)
        if idle_option is None and MACOS:
            idle_option = getattr(socket, "TCP_KEEPALIVE", 0x10)  # macOS's name for the idle time
        if idle_option is None:
            return False
        sock.setsockopt(socket.IPPROTO_TCP, idle_option, idle)
        for name, value in (("TCP_KEEPINTVL", interval), ("TCP_KEEPCNT", count)):
            if hasattr(socket, name):
                sock.setsockopt(socket.IPPROTO_TCP, getattr(socket, name), value)
        return True
    except (AttributeError, OSError, ValueError):
        return False


#: Names Windows reserves for devices, in any case and with any extension (``con.txt`` too).
RESERVED_NAMES = frozenset(
    ["CON", "PRN", "AUX", "NUL", "CONIN$", "CONOUT$"] + [f"{p}{i}" for p in ("COM", "LPT") for i in range(1, 10)]
    + [f"{p}{c}" for p in ("COM", "LPT") for c in "\u00b9\u00b2\u00b3"]
)
_FORBIDDEN = '<>:"/\\|?*'


def name_problem(name: str) -> str | None:
    """Why ``name`` cannot be a file or folder name on every system, or None when it can. A config
    written on Linux must work on Windows, so Windows' rules apply everywhere: none of
    ``< > : " / \\ | ? *`` nor control characters, no reserved device name (``CON``, ``NUL``,
    ``COM1`` ..., with or without an extension), no trailing dot or space, not empty, ``.`` or ``..``."""
    if not isinstance(name, str) or not name.strip():
        return "it is empty"
    if name in (".", ".."):
        return f"{name!r} names a folder, not a file"
    for ch in name:
        if ch in _FORBIDDEN:
            what = "a colon (on Windows it writes a hidden alternate stream)" if ch == ":" else f"the character {ch!r}"
            return f"it contains {what}, which Windows forbids in file names"
        if ord(ch) < 32:
            return f"it contains the control character {ch!r}, which Windows forbids in file names"
    if name[-1] in ". ":
        return "it ends with a dot or a space, which Windows drops from file names"
    stem = name.split(".", 1)[0].rstrip(" ").upper()
    if stem in RESERVED_NAMES:
        return f"{stem} is a device name that Windows reserves (with any extension)"
    return None


if __name__ == "__main__":  # the guard of start_guarded
    if len(sys.argv) > 2 and sys.argv[1] == "--guard":
        sys.exit(_guard_main(sys.argv[2:]))
    sys.exit("usage: python -m tmrl.platform --guard PROGRAM [ARGS...]")
