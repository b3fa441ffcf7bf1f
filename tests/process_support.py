"""Test support: look at and act on other processes the same way on Linux, Windows and macOS
(not a test module). Built on psutil, which reads /proc on Linux and asks the system elsewhere:
tests that need these never read /proc or send POSIX-only signals themselves."""

from __future__ import annotations

import os

import psutil


def alive(pid: int) -> bool:
    """Whether ``pid`` runs (a zombie, dead but not yet reaped by its parent, does not)."""
    try:
        return psutil.Process(pid).status() != psutil.STATUS_ZOMBIE
    except psutil.NoSuchProcess:
        return False


def children(pid: int | None = None, *, command_holds: str | None = None) -> list[int]:
    """The live direct children of ``pid`` (default: this process), only those whose command line
    holds ``command_holds`` when given."""
    found = []
    try:
        kids = psutil.Process(os.getpid() if pid is None else pid).children()
    except psutil.NoSuchProcess:
        return []
    for kid in kids:
        try:
            if kid.status() == psutil.STATUS_ZOMBIE:
                continue
            if command_holds is not None and command_holds not in " ".join(kid.cmdline()):
                continue
        except (psutil.NoSuchProcess, psutil.AccessDenied):
            continue
        found.append(kid.pid)
    return found


def marked(marker: str) -> list[int]:
    """Live processes (this one excepted) whose command line or environment holds ``marker``."""
    found = []
    for proc in psutil.process_iter():
        if proc.pid == os.getpid():
            continue
        try:
            if proc.status() == psutil.STATUS_ZOMBIE:
                continue
            if marker in " ".join(proc.cmdline()) or any(marker in f"{k}={v}" for k, v in proc.environ().items()):
                found.append(proc.pid)
        except (psutil.NoSuchProcess, psutil.AccessDenied, psutil.ZombieProcess, OSError):
            continue
    return found


def command_line(pid: int) -> str:
    """``pid``'s command line, "?" when it is gone."""
    try:
        return " ".join(psutil.Process(pid).cmdline())
    except (psutil.NoSuchProcess, psutil.AccessDenied):
        return "?"


def rss_bytes(pid: int) -> int:
    """``pid``'s resident memory."""
    return psutil.Process(pid).memory_info().rss


def freeze(pid: int) -> None:
    """Stop ``pid`` from running until :func:`thaw` (SIGSTOP on POSIX, a suspend on Windows)."""
    psutil.Process(pid).suspend()


def thaw(pid: int) -> None:
    """Let a frozen ``pid`` run again."""
    psutil.Process(pid).resume()


def kill(pid: int) -> None:
    """End ``pid`` at once, without its clean-up (SIGKILL on POSIX, TerminateProcess on Windows);
    nothing when it is already gone."""
    try:
        psutil.Process(pid).kill()
    except psutil.NoSuchProcess:
        pass


def kill_tree(pid: int) -> None:
    """End ``pid`` and every process below it at once (the role and its network processes)."""
    try:
        top = psutil.Process(pid)
        tree = [top, *top.children(recursive=True)]
    except psutil.NoSuchProcess:
        return
    for proc in tree:
        try:
            proc.kill()
        except psutil.NoSuchProcess:
            pass


def tcp_states(port: int) -> list[str]:
    """States (``ESTABLISHED``, ``CLOSE_WAIT``, ...) of the TCP sockets on local port ``port``
    held by this process or a process below it, listening ones excluded."""
    states = []
    me = psutil.Process()
    for proc in [me, *me.children(recursive=True)]:
        try:
            conns = proc.net_connections(kind="tcp")
        except (psutil.NoSuchProcess, psutil.AccessDenied):
            continue
        states += [c.status for c in conns if c.laddr and c.laddr.port == port and c.status != psutil.CONN_LISTEN]
    return states
