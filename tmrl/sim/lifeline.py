"""The demo's processes live and die together: a stop request or signal to the demo stops its roles,
and a role whose parent is gone (killed, even with SIGKILL or Windows' TerminateProcess) stops too
and takes the run folder with it.

Parent side (``python -m tmrl --demo``): :func:`stop_on_signals` turns SIGTERM, SIGHUP (POSIX) and
Ctrl-Break (Windows) into :class:`Stopped` (a ``KeyboardInterrupt``, like Ctrl-C), so that the same
clean-up runs for every signal that asks the demo to stop. The roles are
:class:`tmrl.platform.Child` processes: the demo stops them through their lifeline, never with a
POSIX signal.

Child side (a role, in a process group of its own so that a Ctrl-C in the terminal reaches the
parent only): :func:`tmrl.platform.watch_lifeline` turns the parent's stop request into a
``KeyboardInterrupt`` and the parent's death into a clean stop, the run folder's removal and the
process's end within :data:`~tmrl.platform.ORPHAN_GRACE` seconds, on every system.
"""

from __future__ import annotations

import signal
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

from tmrl import platform

__all__ = [
    "STOP_SIGNALS",
    "Stopped",
    "exit_code",
    "ignore_stop_signals",
    "signal_name",
    "stop_on_signals",
]

#: The signals that ask a process to stop cleanly where they exist (Ctrl-C, ``kill``, a closed
#: terminal, Ctrl-Break).
STOP_SIGNALS = platform.STOP_SIGNALS


class Stopped(KeyboardInterrupt):
    """A stop signal arrived: stop like Ctrl-C. ``signum`` says which one."""

    def __init__(self, signum: int) -> None:
        super().__init__(signal.Signals(signum).name)
        self.signum = signum


def exit_code(err: BaseException) -> int:
    """The exit code of a process stopped by ``err``: 128 + the signal (130 for Ctrl-C)."""
    return 128 + getattr(err, "signum", signal.SIGINT)


def signal_name(err: BaseException) -> str:
    """``"Ctrl-C"``, ``"SIGTERM"``, ``"SIGHUP"`` or ``"Ctrl-Break"``: what stopped the process,
    for one line."""
    signum = getattr(err, "signum", signal.SIGINT)
    if signum == signal.SIGINT:
        return "Ctrl-C"
    if signum == getattr(signal, "SIGBREAK", None):
        return "Ctrl-Break"
    return signal.Signals(signum).name


def _raise_stopped(signum: int, frame: Any) -> None:
    # One signal is enough: a second one during the clean-up would cut it half-way.
    ignore_stop_signals()
    raise Stopped(signum)


def ignore_stop_signals() -> None:
    """Ignore the stop signals from now on (during a clean-up that must finish)."""
    if threading.current_thread() is not threading.main_thread():
        return
    for signum in STOP_SIGNALS:
        signal.signal(signum, signal.SIG_IGN)


@contextmanager
def stop_on_signals(force_sigint: bool = False) -> Iterator[None]:
    """Within the block, SIGTERM, SIGHUP and SIGBREAK (where they exist) raise :class:`Stopped`,
    SIGINT ``KeyboardInterrupt``; the previous handlers come back afterwards.

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
