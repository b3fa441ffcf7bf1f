"""Parent side of a network process: start it, talk to it through its pipes, stop it."""

from __future__ import annotations

import logging
import os
import struct
import subprocess
import sys
import threading
import time
import weakref
from collections.abc import Callable
from pathlib import Path
from typing import Any

from tmrl import wire
from tmrl.errors import UserError
from tmrl.transport import _pipe

logger = logging.getLogger(__name__)

_LIVE: weakref.WeakSet[NetProcess] = weakref.WeakSet()
_ATEXIT_REGISTERED = False


def _stop_all_at_exit() -> None:
    for proc in list(_LIVE):
        proc.stop(timeout=5.0)


class NetProcess:
    """A ``python -m tmrl.transport._netproc`` child with a reader thread for its messages.

    Args:
        cfg: the configuration sent to the child (data only).
        on_message: called in the reader thread with ``(kind, payload)`` for OBJ and STATUS
            messages.
        max_message_bytes: largest message accepted from the child.
        name: used in thread names and errors.
    """

    def __init__(
        self,
        cfg: dict[str, Any],
        on_message: Callable[[int, bytearray], None],
        max_message_bytes: int,
        name: str,
    ):
        global _ATEXIT_REGISTERED
        self.name = name
        self._on_message = on_message
        self._max = max_message_bytes
        self._ready = threading.Event()
        self._ready_info: dict[str, Any] = {}
        self.exited = threading.Event()
        self._stopped = False
        self._stop_lock = threading.Lock()
        env = dict(os.environ)
        root = str(Path(__file__).resolve().parents[2])
        # Frames are large, short-lived buffers: with a fixed mmap threshold glibc returns them to
        # the system when freed, so the process's memory follows what it actually holds.
        env.setdefault("MALLOC_MMAP_THRESHOLD_", str(1 << 20))
        env["PYTHONPATH"] = root + (os.pathsep + env["PYTHONPATH"] if env.get("PYTHONPATH") else "")
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "tmrl.transport._netproc"],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            env=env,
            bufsize=0,
            close_fds=True,
        )
        assert self.proc.stdin is not None and self.proc.stdout is not None  # both are PIPEs
        self._stdin, self._stdout = self.proc.stdin, self.proc.stdout
        _pipe.enlarge(self._stdin.fileno())
        _pipe.enlarge(self._stdout.fileno())
        self._writer = _pipe.PipeWriter(self._stdin.fileno(), closer=self._stdin.close)
        self._reader = threading.Thread(target=self._read_loop, name=f"tmrl-{name}-reader", daemon=True)
        self._reader.start()
        _LIVE.add(self)
        if not _ATEXIT_REGISTERED:
            import atexit

            atexit.register(_stop_all_at_exit)
            _ATEXIT_REGISTERED = True
        cfg = dict(cfg, log_level=logging.getLogger("tmrl.transport").getEffectiveLevel())
        try:
            self._writer.send(_pipe.CONFIG, wire.encode(cfg))
        except _pipe.PipeClosed:
            pass

    @property
    def pid(self) -> int:
        """The child's process id."""
        return self.proc.pid

    def wait_ready(self, timeout: float) -> dict[str, Any]:
        """Wait for the child's READY message.

        Raises:
            UserError: the child reported a problem (its one-line message), or died.
            TimeoutError: no answer within ``timeout`` seconds.
        """
        if not self._ready.wait(timeout):
            self.stop(timeout=1.0)
            raise TimeoutError(f"the {self.name} network process did not start within {timeout} s")
        info = self._ready_info
        if "error" in info:
            self.stop(timeout=5.0)
            raise UserError(str(info["error"]))
        if not info.get("ok"):
            self.stop(timeout=1.0)
            raise RuntimeError(f"the {self.name} network process exited during start-up (see its log above)")
        return info

    def send(self, kind: int, *parts: bytes | bytearray | memoryview) -> bool:
        """Send a message to the child; False when it is gone."""
        try:
            self._writer.send(kind, *parts)
            return True
        except _pipe.PipeClosed:
            return False

    @property
    def alive(self) -> bool:
        """Whether the child is still running."""
        return not self.exited.is_set() and self.proc.poll() is None

    def stop(self, timeout: float = 15.0) -> None:
        """Ask the child to flush and exit; kill it after ``timeout`` seconds. Idempotent.

        Never blocks on the pipe: the STOP message (which tells the child how long it may flush)
        is written only if it fits at once (the child may be held back, not reading); the pipe
        is then closed, which the child notices in every state. If neither could be done (another
        thread is stuck writing to the pipe), the child gets SIGTERM (same effect).
        """
        with self._stop_lock:
            if self._stopped:
                return
            self._stopped = True
        deadline = time.monotonic() + timeout
        budget = max(0.0, timeout - 1.0)  # the child's flush ends before we would kill it
        sent = self._writer.try_send(_pipe.STOP, struct.pack("<d", budget), min(0.5, timeout))
        closed = self._writer.close(0.2)
        if not (sent or closed):
            self._terminate()
        try:
            self.proc.wait(max(0.0, deadline - time.monotonic()))
        except subprocess.TimeoutExpired:
            logger.warning("the %s network process did not exit in %.0f s; killing it", self.name, timeout)
            self.proc.kill()
            try:
                self.proc.wait(5.0)
            except subprocess.TimeoutExpired:
                logger.error("the %s network process (pid %d) outlived its kill", self.name, self.proc.pid)
        self._reader.join(timeout=5.0)
        try:
            self._stdout.close()
        except OSError:
            pass
        _LIVE.discard(self)

    def _terminate(self) -> None:
        try:
            self.proc.terminate()  # SIGTERM: the child flushes briefly and exits (Windows: exits)
        except OSError:
            pass

    def _read_loop(self) -> None:
        f = self._stdout  # a raw FileIO (bufsize=0)
        try:
            while True:
                kind, payload = _pipe.read_message(f, self._max)
                if kind == _pipe.LOG:
                    self._log(payload)
                elif kind == _pipe.READY:
                    self._ready_info = wire.decode(payload)
                    self._ready.set()
                elif kind == _pipe.CLOSED:
                    break
                else:
                    self._on_message(kind, payload)
        except _pipe.PipeClosed:
            pass
        except Exception:
            logger.exception("internal error reading from the %s network process", self.name)
        finally:
            self.exited.set()
            self._ready.set()
            self._on_message(_pipe.CLOSED, bytearray())

    @staticmethod
    def _log(payload: bytearray) -> None:
        try:
            level, name, msg = wire.decode(payload)
            logging.getLogger(str(name)).log(int(level), "%s", msg)
        except (wire.DecodeError, ValueError, TypeError):
            pass


LOCAL_HOSTS = ("localhost", "127.0.0.1", "::1")


def check_server_address(server_ip: Any, server_port: Any) -> None:
    """Refuse, in one line, a server address that is not a non-empty string or a port outside
    1..65535 (every backend's links check the same config keys).

    Raises:
        UserError: naming the config key (SERVER_IP or PORT).
    """
    if not isinstance(server_ip, str) or not server_ip:
        raise UserError(f"the server address must be a non-empty string, not {server_ip!r} (config key SERVER_IP)")
    if type(server_port) is not int or not 1 <= server_port <= 65535:
        raise UserError(f"the server port must be an integer from 1 to 65535, not {server_port!r} (config key PORT)")


def check_common(
    *,
    password: Any,
    header_size: Any,
    security: Any,
    keys_dir: Any,
    max_frame_bytes: Any,
    needs_key: bool,
) -> tuple[str | None, Path | None]:
    """Validate the arguments shared by the relay and the links.

    Returns:
        ``(security, keys_dir)`` normalised (``"TLS"`` or ``None``; an absolute path or ``None``).

    Raises:
        UserError: a bad value, or TLS without credentials.
    """
    from tmrl.transport.credentials import CERT_FILE, KEY_FILE

    if not isinstance(password, str):
        raise UserError(f"the password must be a string, not {type(password).__name__} (config key PASSWORD)")
    if type(header_size) is not int or not 4 <= header_size <= 18:
        raise UserError(
            f"header_size must be an integer from 4 to 18, not {header_size!r}; use the same value everywhere"
        )
    if type(max_frame_bytes) is not int or max_frame_bytes < 1 << 17:
        raise UserError(f"max_frame_bytes must be an integer of at least {1 << 17}, not {max_frame_bytes!r}")
    if len(str(max_frame_bytes)) > header_size:
        raise UserError(f"max_frame_bytes={max_frame_bytes} does not fit in header_size={header_size} digits")
    if security == "SSL":
        security = "TLS"
    if security not in ("TLS", None):
        raise UserError(f"security must be 'TLS' or None, not {security!r} (config key SECURITY)")
    if security is None:
        return None, None
    if keys_dir is None:
        raise UserError(
            "TLS is on but no credentials folder was given (keys_dir): run `python -m tmrl --install` to create it"
        )
    folder = Path(keys_dir).expanduser().resolve()
    needed = [CERT_FILE] + ([KEY_FILE] if needs_key else [])
    for fname in needed:
        if not (folder / fname).is_file():
            hint = (
                "run `python -m tmrl --install` to create the credentials"
                if needs_key
                else "copy certificate.pem from the server's credentials folder (made by `python -m tmrl --install`)"
            )
            raise UserError(f"TLS credentials missing: {folder / fname} not found; {hint}")
    return "TLS", folder
