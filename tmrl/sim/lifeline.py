"""The demo's processes live and die together: a stop signal to the demo stops its roles, and a
role whose parent is gone (killed, even with SIGKILL) stops too and takes the run folder with it.

Parent side (``python -m tmrl --demo``): :func:`stop_on_signals` turns SIGTERM and SIGHUP into
:class:`Stopped` (a ``KeyboardInterrupt``, like Ctrl-C), so that the same clean-up runs for every
signal that asks the demo to stop.

Child side (a role, started in a session of its own so that a Ctrl-C in the terminal reaches the
parent only): :func:`die_with_parent` asks Linux to send SIGTERM when the parent dies
(``prctl(PR_SET_PDEATHSIG)``) and starts a thread that watches the parent's process id, the
fallback where no such signal exists and a second line where it does. Once the parent is gone the
watch gives the role a few seconds to stop cleanly, then ends the process.
"""

from __future__ import annotations

import os
import signal
import sys
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import Any

__all__ = [
    "ORPHAN_GRACE",
    "STOP_SIGNALS",
    "Stopped",
    "die_with_parent",
    "exit_code",
    "ignore_stop_signals",
    "parent_gone",
    "signal_name",
    "stop_on_signals",
]

#: The signals that ask a process to stop cleanly (Ctrl-C, ``kill``, a closed terminal).
STOP_SIGNALS = tuple(getattr(signal, name) for name in ("SIGINT", "SIGTERM", "SIGHUP") if hasattr(signal, name))

#: Seconds a role whose parent died may take to stop before the watch ends it (the whole run must
#: be gone within 10 s of its parent's death).
ORPHAN_GRACE = 6.0


class Stopped(KeyboardInterrupt):
    """A stop signal arrived: stop like Ctrl-C. ``signum`` says which one."""

    def __init__(self, signum: int) -> None:
        super().__init__(signal.Signals(signum).name)
        self.signum = signum


def exit_code(err: BaseException) -> int:
    """The exit code of a process stopped by ``err``: 128 + the signal (130 for Ctrl-C)."""
    return 128 + getattr(err, "signum", signal.SIGINT)


def signal_name(err: BaseException) -> str:
    """``"Ctrl-C"``, ``"SIGTERM"`` or ``"SIGHUP"``: what stopped the process, for one line."""
    signum = getattr(err, "signum", signal.SIGINT)
    return "Ctrl-C" if signum == signal.SIGINT else signal.Signals(signum).name


def _raise_stopped(signum: int, frame: Any) -> None:
    # One signal is enough: a second one during the clean-up would cut it half-way.
    ignore_stop_signals()
    raise Stopped(signum)


def ignore_stop_signals() -> None:
    """Ignore SIGINT, SIGTERM and SIGHUP from now on (during a clean-up that must finish)."""
    if threading.current_thread() is not threading.main_thread():
        return
    for signum in STOP_SIGNALS:
        signal.signal(signum, signal.SIG_IGN)


@contextmanager
def stop_on_signals(force_sigint: bool = False) -> Iterator[None]:
    """Within the block, SIGTERM and SIGHUP raise :class:`Stopped`, SIGINT ``KeyboardInterrupt``;
    the previous handlers come back afterwards.

    A signal the process inherited as ignored stays ignored (``nohup`` ignores SIGHUP so that the
    command outlives its terminal; a shell ignores SIGINT for a background job), except SIGINT
    with ``force_sigint`` (a process whose parent stops it with SIGINT). Only the main thread can
    install handlers: elsewhere the block runs with the handlers as they are.
    """
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = {signum: signal.getsignal(signum) for signum in STOP_SIGNALS}
    try:
        for signum, handler in previous.items():
            if signum == signal.SIGINT:
                if force_sigint or handler is not signal.SIG_IGN:
                    signal.signal(signum, signal.default_int_handler)
            elif handler is not signal.SIG_IGN:
                signal.signal(signum, _raise_stopped)
        yield
    finally:
        for signum, handler in previous.items():
            signal.signal(signum, handler if handler is not None else signal.SIG_DFL)


def parent_gone(parent_pid: int) -> bool:
    """Whether the process that started this one (``parent_pid``) has died: this process was
    handed to another parent (PID 1 or a subreaper)."""
    return os.getppid() != parent_pid


def _set_parent_death_signal(signum: int) -> bool:
    """Linux: ask the kernel to send ``signum`` to this process when its parent dies."""
    if not sys.platform.startswith("linux"):
        return False
    try:
        import ctypes

        libc = ctypes.CDLL(None, use_errno=True)
        return libc.prctl(1, int(signum), 0, 0, 0) == 0  # 1: PR_SET_PDEATHSIG
    except (OSError, AttributeError):
        return False


def die_with_parent(parent_pid: int, on_orphaned: Callable[[], None] | None = None,
                    grace: float = ORPHAN_GRACE, interval: float = 0.5) -> threading.Thread:
    """Stop this process when ``parent_pid`` dies. Call it first thing in the child's main.

    The parent's death sends SIGTERM (Linux), which the child should handle as a clean stop; a
    daemon thread also checks ``interval`` times a second whether the parent changed, and if so
    sends SIGTERM itself, waits ``grace`` seconds, then calls ``on_orphaned`` (e.g. to remove
    the run folder) and ends the process with code 143.

    Returns:
        The watch thread (started).
    """
    _set_parent_death_signal(signal.SIGTERM)

    def watch() -> None:
        while not parent_gone(parent_pid):
            time.sleep(interval)
        try:
            os.kill(os.getpid(), signal.SIGTERM)
        except OSError:
            pass
        time.sleep(grace)
        try:
            if on_orphaned is not None:
                on_orphaned()
        finally:
            os._exit(128 + signal.SIGTERM)

    thread = threading.Thread(target=watch, name="tmrl-parent-watch", daemon=True)
    thread.start()
    return thread
