"""The trainer's side of the network (:class:`TrainerInterface`): receives sample batches,
checks them against the run's schema, drops second copies and batches of other runs
(:class:`PayloadOrder`), and broadcasts the actor's weights."""

from __future__ import annotations

import collections
import logging
import os
import tempfile
import threading
from collections.abc import Callable
from pathlib import Path
from typing import Any

from tmrl import platform
from tmrl.config.settings import NetSettings
from tmrl.distributed._common import FROM_CONFIG, LOGGER_NAME, _given, _make_link, _settings, check_refused, close_budget
from tmrl.distributed.buffer import Buffer, unpack_buffer
from tmrl.distributed.weights import _weights_problem, pack_weights, remove_stale_temporaries, replace_file
from tmrl.spaces import SampleRejected, SampleSchema, describe_spaces
from tmrl.util import RateLimitedLog
from tmrl.wire_buffers import PayloadError

logger = logging.getLogger(LOGGER_NAME)


class PayloadOrder:
    """Per-worker bookkeeping of payload sequence numbers on the trainer side.

    The transport delivers sample payloads at least once: after a dropped connection the relay
    re-sends what the trainer did not acknowledge, possibly after newer payloads. A payload is
    taken when its number is new for its worker, including a late one that fills a gap; a
    second copy is refused. Gaps still open are counted as lost and logged.

    Memory is bounded whatever the peers send: at most ``max_sources`` workers are followed (the
    least recently heard of is forgotten) and at most ``max_gaps`` open gaps per worker.

    Args:
        max_gaps: how many open gaps are remembered per worker (the oldest are forgotten).
        max_sources: how many workers are followed.
    """

    def __init__(self, max_gaps: int = 10_000, max_sources: int = 4096):
        self.max_gaps = max_gaps
        self.max_sources = max_sources
        self._last: collections.OrderedDict[Any, int] = collections.OrderedDict()
        self._gaps: dict[Any, dict[int, None]] = {}
        self.lost = 0
        self.duplicates = 0
        self._lost_log = RateLimitedLog(logger, logging.WARNING, 1.0)

    def accept(self, src: Any, seq: Any) -> bool:
        """Whether payload ``seq`` of worker ``src`` should be used (``False``: a duplicate)."""
        if type(seq) is not int:
            return True  # a peer that does not number its payloads: nothing to check
        last = self._last.get(src)
        if last is not None:
            self._last.move_to_end(src)
        elif len(self._last) >= self.max_sources:
            old, _ = self._last.popitem(last=False)
            self._gaps.pop(old, None)
        gaps = self._gaps.setdefault(src, {})
        if last is None or seq == last + 1:
            self._last[src] = seq
            return True
        if seq > last + 1:
            missing = seq - last - 1
            for k in range(max(last + 1, seq - self.max_gaps), seq):
                gaps[k] = None
            while len(gaps) > self.max_gaps:
                del gaps[next(iter(gaps))]
            self.lost += missing
            self._lost_log("worker %s: %d sample payloads missing (%d in total)", src, missing, self.lost)
            self._last[src] = seq
            return True
        if seq in gaps:  # late, but new
            del gaps[seq]
            self.lost -= 1
            return True
        self.duplicates += 1
        logger.debug("worker %s: dropped a second copy of payload %d", src, seq)
        return False


def _actor_bytes(model: Any, model_path: Path) -> bytes:
    """The bytes ``model.save`` writes: in memory when that ``save`` is
    :class:`~tmrl.actor.TorchActorModule`'s (:meth:`~tmrl.actor.TorchActorModule.to_bytes`), else
    through a temporary file next to ``model_path`` (an actor with a ``save`` of its own, such as
    a tmrl 0.7 script's ``ActorModule``)."""
    from tmrl.actor import TorchActorModule

    if getattr(type(model), "save", None) is TorchActorModule.save:
        return model.to_bytes()
    fd, tmp = tempfile.mkstemp(prefix=f".{model_path.name}.", suffix=".tmp", dir=model_path.parent)
    os.close(fd)
    try:
        model.save(tmp)
        return Path(tmp).read_bytes()
    finally:
        platform.remove(tmp)


class _Publisher:
    """Sends the trainer's weights on a thread of its own, the newest only.

    :meth:`put` never waits for the network: the training thread goes on at once. Weights given
    while earlier ones are still being sent wait; newer ones replace them (counted in
    :attr:`replaced`): the workers count the versions they skip as models received (the
    version numbers say how many), and keep only the newest anyway, as the relay does. On the
    tutorial's settings (a broadcast after every update, batch 32) writing the trainer's copy,
    signing and piping 270 KB to the network process took a third of the trainer's time on a
    loaded machine, where the network process was often not running to read the pipe.

    An error of the sending (the network process gone) is raised by the next :meth:`put`.

    Args:
        send: ``send(*job)``, called on the publishing thread.
    """

    def __init__(self, send: Callable[..., None]) -> None:
        self._send = send
        self._cv = threading.Condition()
        self._pending: tuple[Any, ...] | None = None
        self._busy = False
        self._closed = False
        self._error: BaseException | None = None
        self.replaced = 0
        """Weights replaced by newer ones before they were sent."""
        self._thread = threading.Thread(target=self._run, daemon=True, name="tmrl-trainer-publish")
        self._thread.start()

    def put(self, job: tuple[Any, ...]) -> None:
        """Send ``job`` soon (replacing one not sent yet).

        Raises:
            ConnectionError, RuntimeError: the sending of earlier weights failed (for example,
                the link's network process is gone, or the link was closed).
        """
        with self._cv:
            if self._error is not None:
                error, self._error = self._error, None
                raise error
            if self._closed:
                raise RuntimeError("this trainer interface is closed")
            if self._pending is not None:
                self.replaced += 1
            self._pending = job
            self._cv.notify_all()

    def _run(self) -> None:
        while True:
            with self._cv:
                self._cv.wait_for(lambda: self._pending is not None or self._closed)
                if self._pending is None:
                    return
                job, self._pending = self._pending, None
                self._busy = True
            try:
                self._send(*job)
            except Exception as err:  # noqa: BLE001 (given to the training thread at its next put)
                with self._cv:
                    self._error = err
            finally:
                with self._cv:
                    self._busy = False
                    self._cv.notify_all()

    def flush(self, timeout: float | None = None) -> bool:
        """Wait until everything given so far was sent; ``False`` after ``timeout`` seconds."""
        with self._cv:
            return self._cv.wait_for(lambda: self._pending is None and not self._busy, timeout)

    def close(self, timeout: float) -> None:
        """Send what is waiting (for at most ``timeout`` seconds), then let the thread end (one
        still writing to a network process that does not read ends when the link closes)."""
        self.flush(timeout)
        with self._cv:
            self._closed = True
            self._cv.notify_all()


class TrainerInterface:
    """The trainer's side of the network, as ``TrainingOffline.run_epoch`` sees it:
    :meth:`retrieve_buffer` and :meth:`broadcast_model`.

    Statistics are kept per worker across calls: the buffer returned by :meth:`retrieve_buffer`
    reports, for each worker, the latest episode statistics it ever sent. When the connection to
    the server comes back (a restarted server), the latest weights are broadcast again.

    Received sample batches are checked before anyone sees them: their structure always, and
    when :attr:`schema` is set, their shapes, dtypes and values (see :class:`~tmrl.spaces.SampleSchema`).
    A batch that fails is dropped whole, counted in :attr:`rejected_batches` and reported in a
    rate-limited log line naming the worker and the first problem. Batches stamped with another
    :attr:`run_id` are dropped and counted in :attr:`foreign_batches`.

    Args: as :class:`Trainer` (``server_ip``, ``server_port``, ``password``, ``header_size``,
    ``security``, ``keys_dir``, ``hostname``, ``model_path``); ``local_com_port`` and
    ``max_buf_len`` are accepted for compatibility with tmrl 0.7 and unused.
    ``schema``: the run's :class:`~tmrl.spaces.SampleSchema` (``None``: structure only).
    ``run_id``: the run identity stamped on the weights (``None``: none).
    ``sign_weights``: sign every broadcast with the trainer key of the credentials folder
    (created there when missing; see :mod:`tmrl.transport.credentials`).

    Raises:
        UserError: bad connection settings (see :mod:`tmrl.transport`).
    """

    def __init__(
        self,
        server_ip: str | None = None,
        server_port: int | None = None,
        password: str | None = None,
        local_com_port: int | None = None,
        header_size: int | None = None,
        max_buf_len: int | None = None,
        security: str | None = FROM_CONFIG,
        keys_dir: str | os.PathLike[str] | None = None,
        hostname: str | None = None,
        model_path: str | os.PathLike[str] | None = None,
        schema: SampleSchema | None = None,
        run_id: str | None = None,
        sign_weights: bool = True,
        *,
        settings: NetSettings | None = None,
    ):
        from tmrl.transport import BACKENDS

        cfg = _settings(settings)
        self.model_path = Path(_given(model_path, cfg.model_path_trainer))
        remove_stale_temporaries(self.model_path)
        self.server_ip = _given(server_ip, cfg.server_ip_for_trainer)
        self._where = f"{self.server_ip}:{_given(server_port, cfg.port)}"
        self.maxlen = cfg.buffers_maxlen
        self.schema = schema
        self.run_id = run_id
        keys = _given(keys_dir, cfg.credentials_directory)
        self._key: Any = None
        if sign_weights and keys is not None:
            from tmrl.transport.credentials import ensure_trainer_key

            self._key = ensure_trainer_key(keys)
        self._link = _make_link(
            BACKENDS[cfg.transport].trainer,
            self.server_ip,
            server_port,
            password,
            local_com_port,
            header_size,
            security,
            keys_dir,
            hostname,
            cfg,
            trainer_key=self._key,
            **cfg.transport_options("trainer"),
        )
        self._stats: collections.OrderedDict[int | None, dict[str, float]] = collections.OrderedDict()
        self._order = PayloadOrder()
        self.rejected_batches = 0
        self.foreign_batches = 0
        self.received_samples = 0
        self.skipped_broadcasts = 0
        self._copy_problems = 0  # the trainer's copy of the weights not written (file held)
        self.weights_version = 0
        self.pace_source: Callable[[], dict[str, Any] | None] | None = None
        """Gives the pacing fields broadcast with the weights (``TrainingOffline.pace``)."""
        self._reject_log = RateLimitedLog(logger, logging.WARNING, 1.0)
        self._foreign_log = RateLimitedLog(logger, logging.INFO, 1.0)
        self._last_weights: bytes | None = None
        self._weights_lock = threading.Lock()
        self._publisher = _Publisher(self._publish)
        self.connections = 0
        """Connections to the server seen so far (the latest weights are broadcast again on each
        after the first)."""
        self._closed = threading.Event()
        self._watcher = threading.Thread(
            target=self._rebroadcast_on_reconnect, daemon=True, name="tmrl-trainer-reconnect"
        )
        self._watcher.start()
        logger.info("trainer connecting to the server at %s", self.server_ip)

    @property
    def rejected_payloads(self) -> int:
        """Alias of :attr:`rejected_batches` (its earlier name)."""
        return self.rejected_batches

    @property
    def lost_payloads(self) -> int:
        """Sample payloads that some worker sent and that never arrived (so far)."""
        return self._order.lost

    @property
    def duplicate_payloads(self) -> int:
        """Second copies of payloads, dropped (the transport delivers at least once)."""
        return self._order.duplicates

    def counters(self) -> dict[str, int]:
        """Counters for the trainer's metrics row: ``rejected_batches`` (malformed or off-schema
        batches dropped), ``foreign_batches`` (stamped for another run), ``skipped_broadcasts``
        (weights with non-finite values not sent)."""
        return {
            "rejected_batches": self.rejected_batches,
            "foreign_batches": self.foreign_batches,
            "skipped_broadcasts": self.skipped_broadcasts,
        }

    @property
    def connected(self) -> bool:
        """Whether the trainer is connected to the server right now."""
        return bool(self._link.connected)

    def wait_connected(self, timeout: float | None = None) -> bool:
        """Wait until connected to the server; ``False`` after ``timeout`` seconds."""
        return bool(self._link.wait_connected(timeout))

    def _rebroadcast_on_reconnect(self) -> None:
        # why: a restarted server has lost the latest weights; workers that (re)connect to it
        # would otherwise wait for the next training step, which may itself wait for their samples.
        # Only a reconnection: both links deliver what was broadcast before their first connection,
        # and weights broadcast just after it, before this thread looked, were sent once already
        # (sent again, a worker could take them for the next ones).
        was_connected = False
        while not self._closed.wait(0.1):
            connected = self._link.connected
            if connected and not was_connected:
                with self._weights_lock:
                    if self.connections and self._last_weights is not None:
                        try:
                            self._link.broadcast_weights(self._last_weights)
                        except (ConnectionError, RuntimeError):  # closing: nothing to do
                            return
                self.connections += 1
            was_connected = connected

    def _unpack(self, payload: Any) -> Buffer | None:
        """The payload as a checked buffer, or ``None`` (dropped, counted and logged)."""
        src = payload.get("src") if isinstance(payload, dict) else None
        who = f"worker {src}" if type(src) is int else "a peer"
        run = payload.get("run") if isinstance(payload, dict) else None
        if run is not None and self.run_id is not None and run != self.run_id:
            self.foreign_batches += 1
            self._foreign_log(
                "dropped a sample batch from %s made for another run (%d so far): it acted with weights "
                "of an earlier run",
                who,
                self.foreign_batches,
            )
            return None
        try:
            buf = unpack_buffer(payload, maxlen=self.maxlen, schema=self.schema)
        except (PayloadError, SampleRejected) as err:
            self.rejected_batches += 1
            self._reject_log(
                "dropped a sample batch from %s: %s (%d dropped so far)", who, err, self.rejected_batches
            )
            return None
        if not self._order.accept(payload["src"], payload.get("seq")):
            return None  # a second copy of a payload already taken (at-least-once delivery)
        return buf

    def retrieve_buffer(self) -> Buffer:
        """Every sample received since the last call (possibly none), never blocking.

        Raises:
            tmrl.distributed._common.PasswordRefused: the server refused the password (one line).

        ``sources`` gives each sample's worker id; batches that are malformed, do not fit
        :attr:`schema` or were made for another run are dropped (see the class docstring).
        """
        check_refused(self._link, "trainer", self._where)
        res = Buffer(maxlen=self.maxlen)
        res.sources = []
        for payload in self._link.receive_samples():
            buf = self._unpack(payload)
            if buf is None:
                continue
            for key, values in buf.stats.items():
                self._stats.setdefault(key, {}).update(values)
                self._stats.move_to_end(key)
                while len(self._stats) > 1024:  # bounded whatever source ids peers make up
                    self._stats.popitem(last=False)
            res += buf
        self._reject_log.flush()
        self._foreign_log.flush()
        self.received_samples += len(res)
        res.stats = {k: dict(v) for k, v in self._stats.items()}
        return res

    def broadcast_model(self, model: Any) -> None:
        """Send ``model``'s weights (an ``ActorModule``) to every worker.

        The actor's file (what ``model.save`` writes, made in memory when that ``save`` is
        :class:`~tmrl.actor.TorchActorModule`'s) replaces ``model_path`` (the trainer keeps a
        local copy, not synced to disk: see :func:`~tmrl.distributed.weights.replace_file`) and is
        broadcast, stamped with :attr:`run_id` and signed with the trainer key. Weights that hold
        a non-finite value are neither kept nor sent (logged, counted in ``skipped_broadcasts``).
        """
        self.model_path.parent.mkdir(parents=True, exist_ok=True)
        data = _actor_bytes(model, self.model_path)
        problem = _weights_problem(None, data)
        if problem is not None:
            self.skipped_broadcasts += 1
            logger.error(
                "did not broadcast the actor's weights: %s (%d broadcasts skipped)", problem, self.skipped_broadcasts
            )
            return
        obs_space = getattr(model, "observation_space", None)
        act_space = getattr(model, "action_space", None)
        spaces = (
            describe_spaces(obs_space, act_space) if obs_space is not None and act_space is not None else None
        )
        self.weights_version += 1
        pace = self.pace_source() if self.pace_source is not None else None
        self._publisher.put((data, spaces, self.weights_version, self.run_id, pace))

    def _publish(self, data: bytes, spaces: Any, version: int, run: str | None, pace: Any) -> None:
        """On the publishing thread: keep the trainer's copy, then send the signed envelope (also
        when the copy could not be written: another process holds the file, Windows)."""
        try:
            replace_file(self.model_path, data)
        except OSError as err:
            self._copy_problems += 1
            logger.warning("could not write the trainer's copy of the weights %s (%s); the next broadcast "
                           "writes it again (%d so far)", self.model_path, err, self._copy_problems)
        envelope = pack_weights(data, spaces, version, run=run, meta=pace, key=self._key)
        with self._weights_lock:
            self._last_weights = envelope
            self._link.broadcast_weights(envelope)

    def flush_broadcasts(self, timeout: float | None = None) -> bool:
        """Wait until the weights given to :meth:`broadcast_model` so far were handed to the
        network (and written to ``model_path``); ``False`` after ``timeout`` seconds."""
        return self._publisher.flush(timeout)

    def close(self, timeout: float = 15.0) -> None:
        """Send the latest weights given to :meth:`broadcast_model` (for at most half of
        ``timeout``), then disconnect (idempotent); the link's process is killed after
        ``timeout`` seconds."""
        timeout = close_budget(self._link, timeout)
        self._publisher.close(timeout / 2)
        self._closed.set()
        self._link.close(timeout)

