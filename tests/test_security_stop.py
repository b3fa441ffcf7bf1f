"""Stop means stop (issue 15, defect 4): each role, in each state where it used to hang (held back
by the server, in the middle of a broadcast, reconnecting), gets SIGTERM or Ctrl-C and is gone
within 5 s with no child process left; when the role's process is killed (SIGKILL), its network
processes are gone within 5 s too.

Roles run as real subprocesses: ``python -m tmrl`` for the reconnecting states, and this file as
a script (``python tests/test_security_stop.py ROLE STATE JSON``) for states that need a server
with small bounds or a big broadcast; the script stops like ``tmrl.roles`` does.
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
from typing import Any

import numpy as np
import pytest

HERE = Path(__file__).resolve()
sys.path.insert(0, str(HERE.parent))

pytestmark = [pytest.mark.timeout(120), pytest.mark.linux]  # POSIX signals, fork, and /proc

PW = "stop-test-password"
BIG = 32 * 2**20  # a broadcast that takes a moment to cross


def descendants(pid: int) -> list[int]:
    """Live processes below ``pid`` (from /proc)."""
    children: dict[int, list[int]] = {}
    for entry in os.listdir("/proc"):
        if not entry.isdigit():
            continue
        try:
            with open(f"/proc/{entry}/stat") as f:
                fields = f.read().rsplit(")", 1)[1].split()
        except OSError:
            continue
        if fields[0] != "Z":
            children.setdefault(int(fields[1]), []).append(int(entry))
    out, todo = [], [pid]
    while todo:
        for c in children.get(todo.pop(), []):
            out.append(c)
            todo.append(c)
    return out


def alive(pid: int) -> bool:
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().rsplit(")", 1)[1].split()[0] != "Z"
    except OSError:
        return False


class Role:
    """A role in a subprocess of its own session; its stdout gives JSON progress lines."""

    def __init__(self, args: list[str], cwd: Path, env: dict[str, str] | None = None):
        self.log = open(cwd / f"role-{time.monotonic_ns()}.log", "wb")
        self.proc = subprocess.Popen(
            args, stdout=subprocess.PIPE, stderr=self.log, cwd=str(cwd), env=env, start_new_session=True
        )
        self.lines: list[dict] = []
        self._reader = threading.Thread(target=self._read, daemon=True)
        self._reader.start()

    def _read(self) -> None:
        for raw in self.proc.stdout:
            try:
                self.lines.append(json.loads(raw))
            except ValueError:
                pass

    def wait_line(self, key: str, timeout: float = 60.0) -> dict:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            for line in self.lines:
                if key in line:
                    return line
            if self.proc.poll() is not None:
                break
            time.sleep(0.05)
        raise AssertionError(f"no {key!r} line from the role (log: {self.log.name}): {self.log_text()[-2000:]}")

    def wait_children(self, n: int, timeout: float = 60.0) -> list[int]:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            found = descendants(self.proc.pid)
            if len(found) >= n:
                return found
            time.sleep(0.05)
        raise AssertionError(f"the role started fewer than {n} network processes")

    def log_text(self) -> str:
        self.log.flush()
        return Path(self.log.name).read_text(errors="replace")

    def cleanup(self) -> None:
        for pid in [self.proc.pid, *descendants(self.proc.pid)]:
            try:
                os.kill(pid, signal.SIGKILL)
            except ProcessLookupError:
                pass
        self.proc.wait()
        self.log.close()


def assert_gone_within(role: Role, pids: list[int], seconds: float, how: str) -> float:
    """Wait until the role's process (unless it was SIGKILLed) and ``pids`` are gone."""
    t0 = time.monotonic()
    while time.monotonic() - t0 < seconds:
        if role.proc.poll() is not None and not any(alive(p) for p in pids):
            return time.monotonic() - t0
        time.sleep(0.02)
    left = [p for p in pids if alive(p)]
    raise AssertionError(
        f"{how}: still running after {seconds} s (role exit {role.proc.poll()}, children left {left}); "
        f"log: {role.log_text()[-3000:]}"
    )


@pytest.fixture
def roles():
    made: list[Role] = []
    yield made
    for r in made:
        r.cleanup()


@pytest.fixture
def closing():
    objs: list[Any] = []
    yield objs
    for o in reversed(objs):
        (o.stop if hasattr(o, "stop") else o.close)()


def script(role: str, state: str, **args: Any) -> list[str]:
    return [sys.executable, str(HERE), role, state, json.dumps(args)]


# ------------------------------------------------------------------------------------------------
# states that need the test to play the other roles


def _relay(port: int, **kw: Any) -> Any:
    from tmrl.transport import RelayServer

    return RelayServer(port, PW, security=None, **kw)


def _setup(state: str, role: str, port: int, closing: list, tmp_path: Path) -> list[str]:
    """Start what the test plays around ``role`` in ``state``; returns the role's command."""
    from tmrl.transport import TrainerLink, WorkerLink

    if role == "worker" and state == "held":
        closing.append(_relay(port, max_consumables=2))  # no trainer: the relay holds workers back
        return script("worker", state, port=port, tmp=str(tmp_path))
    if role == "worker" and state == "receiving":
        closing.append(_relay(port))
        trainer = TrainerLink("127.0.0.1", port, PW, security=None)
        closing.append(trainer)
        cmd = script("worker", state, port=port, tmp=str(tmp_path))

        def broadcast_when_connected() -> None:
            trainer.wait_connected(30)
            for _ in range(50):
                try:
                    trainer.broadcast_weights(b"\0" * BIG)
                except (ConnectionError, RuntimeError):
                    return

        threading.Thread(target=broadcast_when_connected, daemon=True).start()
        return cmd
    if role == "trainer" and state == "broadcasting":
        closing.append(_relay(port))
        worker = WorkerLink("127.0.0.1", port, PW, security=None)  # a receiver that never reads
        closing.append(worker)
        return script("trainer", state, port=port, tmp=str(tmp_path))
    if role == "server" and state == "holding":
        cmd = script("server", state, port=port, tmp=str(tmp_path))

        def flood() -> None:
            link = WorkerLink("127.0.0.1", port, PW, security=None)
            closing.append(link)
            link.wait_connected(30)
            try:
                for _ in range(1000):
                    link.send_samples(np.zeros(2**18, np.float32))
            except (ConnectionError, RuntimeError):
                pass

        threading.Thread(target=flood, daemon=True).start()
        return cmd
    if role == "server" and state == "broadcasting":
        cmd = script("server", state, port=port, tmp=str(tmp_path))

        def broadcast() -> None:
            trainer = TrainerLink("127.0.0.1", port, PW, security=None)
            worker = WorkerLink("127.0.0.1", port, PW, security=None)
            closing.extend([trainer, worker])
            trainer.wait_connected(30)
            try:
                for _ in range(50):
                    trainer.broadcast_weights(b"\0" * BIG)
            except (ConnectionError, RuntimeError):
                pass

        threading.Thread(target=broadcast, daemon=True).start()
        return cmd
    raise AssertionError((role, state))


CASES = [
    ("worker", "held", "stopped"),
    ("worker", "receiving", "stopped"),
    ("trainer", "broadcasting", "stopped"),
    ("server", "holding", "stopped"),
    ("server", "broadcasting", "stopped"),
]


@pytest.mark.parametrize("role,state,ready", CASES)
@pytest.mark.parametrize("name", ["SIGTERM", "SIGKILL"])  # (names: collected on Windows too, where no SIGKILL is)
def test_a_role_stops_within_5_s_in_every_state(role, state, ready, name, tmp_path, port_factory, roles, closing):
    sig = getattr(signal, name)
    port = port_factory()
    cmd = _setup(state, role, port, closing, tmp_path)
    r = Role(cmd, tmp_path)
    roles.append(r)
    r.wait_line("ready")
    kids = r.wait_children(1)
    r.wait_line(state)  # the role says it is in that state (and stays in it a moment)
    time.sleep(0.5)
    kids = descendants(r.proc.pid) or kids
    os.kill(r.proc.pid, sig)
    took = assert_gone_within(r, kids, 5.0, f"{role} {state} after {signal.Signals(sig).name}")
    if sig == signal.SIGTERM:
        assert r.proc.returncode == 143
        assert f"tmrl: {role} stopped (SIGTERM)" in r.log_text()
    print(f"[stop] {role} {state} {signal.Signals(sig).name}: gone in {took:.2f} s")


def _netprocs(pids: list[int]) -> list[int]:
    out = []
    for pid in pids:
        try:
            with open(f"/proc/{pid}/cmdline", "rb") as f:
                if b"tmrl.transport._netproc" in f.read():
                    out.append(pid)
        except OSError:
            pass
    return out


def test_network_processes_die_with_their_parent_even_if_a_fork_keeps_their_pipe(
    tmp_path, port_factory, roles, closing
):
    # A process forked by the role (multiprocessing's default on Linux) inherits the write end of
    # the network process's pipe: the pipe never closes, only the parent-death watch can tell.
    port = port_factory()
    closing.append(_relay(port))
    r = Role(script("worker", "forked", port=port, tmp=str(tmp_path)), tmp_path)
    roles.append(r)
    r.wait_line("forked")
    nets = _netprocs(descendants(r.proc.pid))
    assert nets
    os.kill(r.proc.pid, signal.SIGKILL)
    took = assert_gone_within(r, nets, 5.0, "the network process of a killed worker with a forked child")
    print(f"[stop] worker forked SIGKILL: network process gone in {took:.2f} s")


# ------------------------------------------------------------------------------------------------
# the command-line roles, reconnecting (no server to talk to)


def _cli_env(tmp_path: Path, port: int) -> dict[str, str]:
    override = {
        "PORT": port,
        "TLS": False,
        "PASSWORD": PW,
        "HEADER_SIZE": 10,
        "ENVIRONMENT_STEPS_BEFORE_TRAINING": 10**9,
        "ENV": {"RTGYM_INTERFACE": "GYM", "GYM_ID": "Pendulum-v1"},
    }
    return dict(os.environ, TMRL_DATA=str(tmp_path / "data"), TMRL_CONFIG_OVERRIDE=json.dumps(override))


@pytest.mark.parametrize("role", ["worker", "trainer"])
@pytest.mark.parametrize("name", ["SIGTERM", "SIGINT", "SIGKILL"])
def test_cli_roles_stop_within_5_s_while_reconnecting(role, name, tmp_path, port_factory, roles):
    sig = getattr(signal, name)
    port = port_factory()  # nobody listens there: the role keeps reconnecting
    r = Role([sys.executable, "-m", "tmrl", f"--{role}"], tmp_path, env=_cli_env(tmp_path, port))
    roles.append(r)
    kids = r.wait_children(1)
    deadline = time.monotonic() + 60
    marker = "waiting for samples" if role == "trainer" else "connecting to the server"
    while marker not in r.log_text():  # built, and its link is retrying
        assert time.monotonic() < deadline and r.proc.poll() is None, r.log_text()[-3000:]
        time.sleep(0.1)
    time.sleep(1.0)
    kids = descendants(r.proc.pid) or kids
    os.kill(r.proc.pid, sig)
    took = assert_gone_within(r, kids, 5.0, f"--{role} reconnecting after {signal.Signals(sig).name}")
    if sig != signal.SIGKILL:
        name, code = ("SIGTERM", 143) if sig == signal.SIGTERM else ("Ctrl-C", 130)
        assert r.proc.returncode == code
        assert f"tmrl: {role} stopped ({name})" in r.log_text()
        assert "Traceback" not in r.log_text()
    print(f"[stop] --{role} reconnecting {signal.Signals(sig).name}: gone in {took:.2f} s")


# ------------------------------------------------------------------------------------------------
# the roles, as scripts: python tests/test_security_stop.py ROLE STATE JSON_ARGS


def _say(**obj: Any) -> None:
    print(json.dumps(obj), flush=True)


def _child(role: str, state: str, args: dict) -> int:
    from tmrl.networking import STOP_TIMEOUT
    from tmrl.roles import _interrupt_on_sigterm, _stopped

    _interrupt_on_sigterm()
    port = args["port"]
    obj: Any = None
    try:
        if role == "worker":
            from test_networking import CountingEnv, JsonActor

            from tmrl.networking import RolloutWorker

            obj = RolloutWorker(
                env_cls=lambda: CountingEnv(obs_dim=2**16),  # 256 KiB per observation
                actor_module_cls=JsonActor, server_ip="127.0.0.1", server_port=port, password=PW,
                security=None, header_size=10, keys_dir=args["tmp"], model_history=0,
                model_path=str(Path(args["tmp"]) / "w.json"), max_samples_per_episode=20,
            )
            _say(ready=True)
            if state == "held":
                sending_since = [time.monotonic()]

                def watch() -> None:  # a send that blocks: the relay holds this worker back
                    while time.monotonic() - sending_since[0] < 1.0:
                        time.sleep(0.05)
                    _say(held=True)

                threading.Thread(target=watch, daemon=True).start()
                while True:
                    obj.collect_train_episode()
                    sending_since[0] = time.monotonic()
                    obj.send_and_clear_buffer()
            elif state == "forked":
                obj.wait_connected(30)
                if os.fork() == 0:  # holds every descriptor of the role, then goes away
                    time.sleep(12)
                    os._exit(0)
                _say(forked=True)
                while True:
                    time.sleep(0.1)
            else:
                obj.wait_connected(30)
                _say(receiving=True)
                while True:
                    obj.update_actor_weights(verbose=False, blocking=True)
        elif role == "trainer":
            from tmrl.transport import TrainerLink

            obj = TrainerLink("127.0.0.1", port, PW, security=None)
            obj.wait_connected(30)
            _say(ready=True)
            _say(broadcasting=True)
            while True:
                obj.broadcast_weights(b"\0" * BIG)
        else:
            obj = _relay(port, max_consumables=2)
            _say(ready=True)
            _say(**{state: True})
            while obj.running:
                time.sleep(0.2)
    except KeyboardInterrupt as err:
        if obj is not None:
            obj.close(STOP_TIMEOUT) if hasattr(obj, "close") else obj.stop(STOP_TIMEOUT)
        return _stopped(role, err)
    return 0


if __name__ == "__main__":
    sys.exit(_child(sys.argv[1], sys.argv[2], json.loads(sys.argv[3])))
