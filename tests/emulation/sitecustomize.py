"""Make a Python process on Linux behave, where tmrl can tell, like one on Windows.

There is no Windows machine here, so the tests run tmrl's real code through what Windows does
differently. Python imports this module at start-up when its folder is on ``PYTHONPATH``; it does
nothing unless ``TMRL_EMULATE`` names what to emulate (comma-separated), and every process started
below inherits both variables, so a whole demo run (the demo, its roles, their network processes)
is emulated at once:

- ``windows``: the POSIX-only names of ``os``, ``signal`` and ``select`` are gone (``os.killpg``,
  ``os.set_blocking``, ``signal.SIGKILL``/``SIGHUP``/``SIGUSR*``, ``select.poll``/``epoll``, ...);
  ``os.getppid`` returns the parent of the process's start forever (Windows never hands an orphan
  to another parent); ``Popen.send_signal`` refuses every signal but SIGTERM as Windows' does,
  ``terminate``/``kill`` end the process at once (``TerminateProcess``), and ``start_new_session``
  and ``preexec_fn`` are refused or ignored as there.
- ``locks``: ``os.replace``, ``os.rename``, ``os.unlink`` and ``os.remove`` fail with
  ``PermissionError`` (a sharing violation: another process holds the file) one time in
  ``TMRL_EMULATE_LOCK_ODDS`` (default 5), as an antivirus, a backup tool or a reader does there.

The failures are random but repeatable: each process seeds its generator from
``TMRL_EMULATE_SEED`` (default 0) and its process id.
"""

from __future__ import annotations

import os
import sys

#: POSIX-only names that Windows' ``os`` lacks: process groups, sessions, non-blocking pipes,
#: affinity and file modes, what tmrl could reach for. What CPython's own POSIX subprocess module
#: needs to start and reap children stays, and so do the user ids that third-party POSIX code
#: (platformdirs' unix paths) reads at import: on Windows that code never runs.
OS_NAMES = (
    "killpg", "getpgid", "getpgrp", "setpgrp", "setpgid", "setsid", "getsid", "set_blocking",
    "get_blocking", "sched_getaffinity", "sched_setaffinity", "fchmod", "fchown", "nice", "mkfifo",
    "openpty", "forkpty", "pipe2", "getloadavg",
)
#: POSIX-only names of ``signal``.
SIGNAL_NAMES = (
    "SIGKILL", "SIGHUP", "SIGSTOP", "SIGCONT", "SIGUSR1", "SIGUSR2", "SIGQUIT", "SIGPIPE", "SIGALRM",
    "SIGCHLD", "SIGTSTP", "SIGTTIN", "SIGTTOU", "SIGWINCH", "SIGXCPU", "SIGXFSZ", "SIGVTALRM",
    "SIGPROF", "SIGIO", "SIGPWR", "SIGSYS", "SIGURG", "SIGTRAP", "SIGBUS", "SIGPOLL", "SIGRTMIN",
    "SIGRTMAX", "pthread_kill", "pthread_sigmask", "sigwait", "sigwaitinfo", "sigtimedwait",
    "sigpending", "setitimer", "getitimer", "alarm", "pause", "siginterrupt", "ITIMER_REAL",
    "ITIMER_VIRTUAL", "ITIMER_PROF", "pidfd_send_signal",
)
#: POSIX-only names of ``select`` (Windows has ``select.select`` only).
SELECT_NAMES = ("poll", "epoll", "kqueue", "kevent", "devpoll", "PIPE_BUF", "POLLIN", "POLLOUT",
                "POLLHUP", "POLLERR", "POLLNVAL", "POLLPRI", "EPOLLIN", "EPOLLOUT")


def _emulate_windows() -> None:
    import select
    import signal

    real_kill, real_sigkill, real_sigterm = os.kill, signal.SIGKILL, signal.SIGTERM
    for module, names in ((os, OS_NAMES), (signal, SIGNAL_NAMES), (select, SELECT_NAMES)):
        for name in names:
            if hasattr(module, name):
                delattr(module, name)
    import subprocess  # after the names are gone: its selectors then choose as on Windows

    parent = os.getppid()
    os.getppid = lambda: parent  # Windows keeps the id of a parent that died

    def terminate(self: subprocess.Popen) -> None:  # TerminateProcess: no clean-up in the child
        if self.returncode is None:
            try:
                real_kill(self.pid, real_sigkill)
            except ProcessLookupError:
                pass

    def send_signal(self: subprocess.Popen, sig: int) -> None:
        if sig == real_sigterm:
            terminate(self)
        else:  # CTRL_C_EVENT / CTRL_BREAK_EVENT need a console this emulation does not have
            raise ValueError(f"Unsupported signal: {sig}")

    init = subprocess.Popen.__init__

    def popen_init(self: subprocess.Popen, *args: object, **kwargs: object) -> None:
        if kwargs.get("preexec_fn") is not None:
            raise ValueError("preexec_fn is not supported on Windows platforms")
        kwargs.pop("start_new_session", None)  # ignored on Windows
        kwargs.pop("process_group", None)
        init(self, *args, **kwargs)

    subprocess.Popen.__init__ = popen_init  # type: ignore[method-assign]
    subprocess.Popen.send_signal = send_signal  # type: ignore[method-assign]
    subprocess.Popen.terminate = terminate  # type: ignore[method-assign]
    subprocess.Popen.kill = terminate  # type: ignore[method-assign]


def _emulate_locks() -> None:
    import random

    odds = max(1, int(os.environ.get("TMRL_EMULATE_LOCK_ODDS", "5")))
    rng = random.Random(f"{os.environ.get('TMRL_EMULATE_SEED', '0')}-{os.getpid()}")
    counts = {"failed": 0}

    def locked(real):  # type: ignore[no-untyped-def]
        def call(*args, **kwargs):  # type: ignore[no-untyped-def]
            if rng.randrange(odds) == 0:
                counts["failed"] += 1
                raise PermissionError(13, "The process cannot access the file because it is being used by "
                                          "another process (emulated)", str(args[0]) if args else None)
            return real(*args, **kwargs)

        call.__name__ = real.__name__
        return call

    for name in ("replace", "rename", "unlink", "remove"):
        setattr(os, name, locked(getattr(os, name)))
    report = os.environ.get("TMRL_EMULATE_REPORT")
    if report:  # each process says how many calls it failed, for the tests to check the emulation ran
        import atexit

        def write_count() -> None:
            with open(os.path.join(report, f"{os.getpid()}.locks"), "w", encoding="utf-8") as f:
                f.write(str(counts["failed"]))

        atexit.register(write_count)


_MODES = {mode.strip() for mode in os.environ.get("TMRL_EMULATE", "").split(",") if mode.strip()}
if "windows" in _MODES:
    _emulate_windows()
if "locks" in _MODES:
    _emulate_locks()
del _MODES
_ = sys  # the module must stay import-only: nothing else runs here
