"""The NATS backend's weights channel: the trainer's writing and the workers' reading.

The weights travel through JetStream's object store (chunked by NATS) in the bucket
:data:`~tmrl.transport.jetstream.layout.DEFAULT_BUCKET`; a key-value entry
:data:`~tmrl.transport.jetstream.layout.LATEST_KEY` of the same bucket names the newest object,
and its revision is the weights' version. A message on ``tmrl.notify.<bucket>`` announces each
new one.

- :class:`_WeightsWriter` (in :class:`~tmrl.transport.jetstream.trainer.NatsTrainerLink`): uploads
  the newest weights in the background (older ones not uploaded yet are skipped) and keeps the
  previous object for workers reading it now.
- :class:`_WeightsReader` (in :class:`~tmrl.transport.jetstream.worker.NatsWorkerLink`): reads the
  newest weights on each announcement and every :data:`WEIGHTS_POLL` seconds, never an older
  version over a newer one.

:data:`WEIGHTS_POLL` is read here: set it on this module, not on the re-export modules.
"""

from __future__ import annotations

import collections
import logging
import secrets
import threading
import time
from typing import Any

from tmrl import wire
from tmrl.transport._nats_server import NOTIFY_PREFIX
from tmrl.transport.jetstream.connect import _NatsLink
from tmrl.transport.jetstream.layout import LATEST_KEY, WEIGHTS_OBJECT

logger = logging.getLogger("tmrl.transport.nats")

WEIGHTS_POLL = 2.0
"""Seconds between a worker's checks for new weights when it hears no announcement."""
STORE_ANSWER = 2.0
"""Seconds the trainer waits for the store's answer to one request of a weights upload (a chunk:
one more second per MB of it) before it starts the upload again: a store whose leader was killed
answers nothing it was given, and its new leader is elected within seconds."""
UPLOAD_BOUND = 60.0
"""Seconds a weights upload may take in all (one more per MB of weights) before it starts again."""


class _WeightsReader(_NatsLink):
    """The workers' end of the weights channel (mixed into the worker's link)."""

    def _init_reader(self) -> None:
        """The reading side's state (before the connection starts)."""
        self._weights: bytes | None = None
        self._weights_cv = threading.Condition()
        self._version: tuple[str, int] | None = None
        self._relookup = True
        self._weights_wake: Any = None  # an asyncio.Event, made on the loop

    def latest_weights(self, block: bool = False, timeout: float | None = None) -> bytes | None:
        """The newest weights broadcast since the last call (older unread ones dropped), or None;
        with ``block``, wait up to ``timeout`` seconds for them."""
        deadline = None if timeout is None else time.monotonic() + timeout
        with self._weights_cv:
            while block and self._weights is None and not self._closed:
                left = None if deadline is None else deadline - time.monotonic()
                if left is not None and left <= 0:
                    break
                self._weights_cv.wait(1.0 if left is None else min(left, 1.0))
            weights, self._weights = self._weights, None
        return weights

    @property
    def weights_version(self) -> tuple[str, int] | None:
        """``(store epoch, revision)`` of the last weights received, or None."""
        return self._version

    async def _weights_reader(self) -> None:
        import asyncio

        wake = self._weights_wake

        async def announced(msg: Any) -> None:
            wake.set()

        subscribed = False
        kv = js = None
        epoch = ""
        while True:
            try:
                await asyncio.wait_for(wake.wait(), WEIGHTS_POLL)
            except asyncio.TimeoutError:
                pass
            wake.clear()
            if not self._is_connected:
                continue
            if self._relookup:
                kv, self._relookup = None, False  # looked up again after a reconnection
            try:
                if not subscribed:
                    await self._nc.subscribe(f"{NOTIFY_PREFIX}.{self._bucket}", cb=announced)
                    subscribed = True  # nats-py subscribes again by itself after reconnections
                if kv is None:
                    js = self._nc.jetstream(timeout=5)
                    kv = await js.key_value(self._bucket)
                    status = await kv.status()
                    epoch = str(getattr(status.stream_info, "created", "") or "")
                await self._read_weights(kv, js, epoch)
            except Exception as e:  # noqa: BLE001 (no bucket yet, a restart: tried again later)
                logger.debug("worker link: no weights read (%s: %s)", type(e).__name__, e)
                kv = None

    async def _read_weights(self, kv: Any, js: Any, epoch: str) -> None:
        import asyncio

        import nats.js.errors as jse

        try:
            entry = await kv.get(LATEST_KEY)
        except jse.KeyNotFoundError:
            return
        version = (epoch, int(entry.revision))
        if self._version is not None and self._version[0] == epoch and version[1] <= self._version[1]:
            return  # never an older version over a newer one
        meta = wire.decode(bytes(entry.value or b""))
        if not (isinstance(meta, dict) and isinstance(meta.get("name"), str) and isinstance(meta.get("nuid"), str)
                and type(meta.get("size")) is int):
            logger.error("worker link: ignored a weights announcement that is not valid")
            return
        try:
            # Bounded, and ended with the connection (cut mid-read, it would wait out the bound).
            data = await self._while_connected(self._fetch_object(js, meta["name"], meta["nuid"]),
                                               30.0 + meta["size"] / 1e6)
        except (asyncio.TimeoutError, ConnectionError, LookupError, jse.NotFoundError):
            # deleted meanwhile (newer weights came) or cut: read the newest again, soon
            await asyncio.sleep(0.05)
            self._weights_wake.set()
            return
        except ValueError as e:
            logger.error("worker link: dropped weights that are not whole (%s)", e)
            return
        try:
            weights = wire.decode(data)
        except Exception as e:  # noqa: BLE001 (hostile or corrupt data must not stop the reader)
            logger.error("worker link: dropped weights that could not be decoded: %s", e)
            return
        if not isinstance(weights, (bytes, bytearray)):
            logger.error("worker link: dropped a broadcast that is not weights bytes (%s)", type(weights).__name__)
            return
        self._version = version
        with self._weights_cv:
            self._weights = bytes(weights)
            self._weights_cv.notify_all()


    async def _fetch_object(self, js: Any, name: str, nuid: str) -> bytes:
        """Object ``name``'s bytes, read with direct gets: its description, then its chunks one
        by one. Any replica of the store answers one (no leader is needed) and no consumer is
        made: nats-py's ``ObjectStore.get`` creates one per read (three workers reading about 15
        times a second kept over a hundred alive in the chaos soak, each made and removed through
        the cluster's metadata leader).

        Raises:
            LookupError: the object is not (or no longer) in the store, or was replaced.
            ValueError: its chunks do not add up to its size and digest.
        """
        import base64
        import hashlib
        import json

        import nats.js.errors as jse
        from nats.js.object_store import OBJ_DIGEST_TYPE

        stream = _store_stream(self._bucket)
        meta_subject, chunk_subject = _object_subjects(self._bucket, name, nuid)
        try:
            description = json.loads((await js.get_last_msg(stream, meta_subject, direct=True)).data or b"{}")
        except jse.NotFoundError:
            raise LookupError(f"weights object {name} is not in the store") from None
        if not isinstance(description, dict) or description.get("nuid") != nuid or description.get("deleted"):
            raise LookupError(f"weights object {name} was replaced or deleted")
        chunks, size = description.get("chunks"), description.get("size")
        if type(chunks) is not int or type(size) is not int or chunks < 0 or size < 0:
            raise ValueError(f"weights object {name} has a description that is not valid")
        parts, digest, seq, got = [], hashlib.sha256(), 0, 0
        for _ in range(chunks):
            try:
                msg = await js.get_msg(stream, seq=seq + 1, subject=chunk_subject, direct=True, next=True)
            except jse.NotFoundError:
                raise LookupError(f"weights object {name} was deleted during the read") from None
            data = bytes(msg.data or b"")
            got += len(data)
            if got > size:
                raise ValueError(f"weights object {name} has more bytes than its size")
            parts.append(data)
            digest.update(data)
            seq = int(msg.seq)
        expected = str(description.get("digest", "")).replace(OBJ_DIGEST_TYPE, "").replace(OBJ_DIGEST_TYPE.upper(), "")
        try:
            same = base64.urlsafe_b64decode(expected) == digest.digest()
        except ValueError:
            same = False
        if got != size or not same:
            raise ValueError(f"weights object {name} does not match its size and digest")
        return b"".join(parts)


def _object_subjects(bucket: str, name: str | None = None, nuid: str | None = None) -> tuple[str, str]:
    """The object store's subjects (nats-py's layout): object ``name``'s description and object
    ``nuid``'s chunks; ``>`` for every one of them when not given."""
    import base64

    from nats.js.object_store import OBJ_CHUNKS_PRE_TEMPLATE, OBJ_META_PRE_TEMPLATE

    obj = ">" if name is None else base64.urlsafe_b64encode(name.encode()).decode()
    return (OBJ_META_PRE_TEMPLATE.format(bucket=bucket, obj=obj),
            OBJ_CHUNKS_PRE_TEMPLATE.format(bucket=bucket, obj=">" if nuid is None else nuid))


def _store_stream(bucket: str) -> str:
    """The object store's stream."""
    from nats.js.object_store import OBJ_STREAM_TEMPLATE

    return OBJ_STREAM_TEMPLATE.format(bucket=bucket)


class _WeightsWriter(_NatsLink):
    """The trainer's end of the weights channel (mixed into the trainer's link)."""

    def _init_writer(self) -> None:
        """The writing side's state (before the connection starts)."""
        self.broadcasts = 0
        """Weights uploaded and announced."""
        self._pending_weights: bytes | None = None
        self._weights_lock = threading.Lock()
        self._weights_wake: Any = None  # an asyncio.Event, made on the loop
        self._uploading = False
        self._objects: collections.deque[tuple[str, str]] = collections.deque()  # (name, nuid)
        self._cut_uploads = 0  # uploads given up since the store was last swept of their chunks
        self.failed_uploads = 0
        """Uploads given up (the connection dropped, the store did not answer in time) and tried again."""

    def broadcast_weights(self, data: bytes) -> None:
        """Send ``data`` to every connected worker and to every worker that connects later (only
        the newest broadcast is kept). Returns at once; the upload runs in the background.

        Raises:
            TypeError: ``data`` is not bytes-like.
            RuntimeError: the link is closed.
        """
        if not isinstance(data, (bytes, bytearray, memoryview)):
            raise TypeError(f"broadcast_weights takes bytes, not {type(data).__name__}")
        if self._closed:
            raise RuntimeError("this link is closed")
        encoded = wire.encode(bytes(data))
        with self._weights_lock:
            self._pending_weights = encoded
        self._loop.call(self._weights_wake.set)

    async def _broadcaster(self) -> None:
        import asyncio

        while True:
            await self._weights_wake.wait()
            self._weights_wake.clear()
            while self._is_connected:
                with self._weights_lock:
                    data, self._pending_weights = self._pending_weights, None
                    self._uploading = data is not None
                if data is None:
                    break
                try:
                    # Ended with the connection: a chunk lost with it would wait out its answer.
                    await self._while_connected(self._upload(data), UPLOAD_BOUND + len(data) / 1e6)
                except Exception as e:  # noqa: BLE001 (kept and uploaded after the reconnection)
                    self._cut_uploads += 1
                    self.failed_uploads += 1
                    self._error_log("trainer link: uploading the weights failed (%s: %s)", type(e).__name__, e)
                    with self._weights_lock:
                        if self._pending_weights is None:
                            self._pending_weights = data
                    await asyncio.sleep(0.5)
                finally:
                    with self._weights_lock:
                        self._uploading = False

    async def _upload(self, data: bytes) -> None:
        """Store ``data`` as a new object, name it in the key-value entry, announce it, and remove
        the objects before the previous one."""
        js = self._nc.jetstream(timeout=STORE_ANSWER)
        name = f"{WEIGHTS_OBJECT}-{secrets.token_hex(8)}"
        nuid = await self._put_object(js, name, data)
        kv = await js.key_value(self._bucket)
        await kv.put(LATEST_KEY, wire.encode({"name": name, "nuid": nuid, "size": len(data)}))
        await self._nc.publish(f"{NOTIFY_PREFIX}.{self._bucket}", b"")
        self.broadcasts += 1
        self._objects.append((name, nuid))
        while len(self._objects) > 2:  # the previous one stays for workers reading it now
            await self._remove_object(js, *self._objects.popleft())
        if self._cut_uploads:  # what uploads given up left (chunks, maybe a description)
            try:
                await self._remove_all_but(js, [sub for obj in self._objects for sub in self._subjects(*obj)])
                self._cut_uploads = 0
            except Exception as e:  # noqa: BLE001 (tried again after the next upload)
                logger.debug("trainer link: what cut uploads left was not removed (%s)", e)

    async def _put_object(self, js: Any, name: str, data: bytes) -> str:
        """Store ``data`` as object ``name`` of the store (nats-py's layout: chunks, then the
        description, which any object store client reads) and return its nuid.

        Written here rather than with nats-py's ``ObjectStore.put``, which first asks for an
        object of the same name (one request more per broadcast), waits a whole chunk's answer
        time for the smallest chunk, and after a failure asks the store to remove the chunks,
        waiting again when the store is the one not answering (9 to 13 s after a kill of the
        store's leader in the chaos soak). A request is given up after :data:`STORE_ANSWER`
        seconds (one more per MB of it); what a failed upload stored is removed after the next
        good one."""
        import base64
        import hashlib
        import json
        from datetime import datetime, timezone

        from nats.js import api
        from nats.js.object_store import MSG_ROLLUP_SUBJECT, OBJ_DIGEST_TEMPLATE

        chunk_size = max(128 * 1024, min(4 * 2**20, int(self._nc.max_payload) - 64 * 1024))
        nuid = secrets.token_hex(11)
        meta_subject, chunk_subject = self._subjects(name, nuid)
        digest, chunks = hashlib.sha256(), 0
        view = memoryview(data)
        for start in range(0, len(data), chunk_size):
            part = bytes(view[start:start + chunk_size])
            await js.publish(chunk_subject, part, timeout=STORE_ANSWER + len(part) / 1e6)
            digest.update(part)
            chunks += 1
        info = api.ObjectInfo(
            name=name, bucket=self._bucket, nuid=nuid, size=len(data), chunks=chunks,
            mtime=datetime.now(timezone.utc).isoformat(),
            digest=OBJ_DIGEST_TEMPLATE.format(digest=base64.urlsafe_b64encode(digest.digest()).decode()),
            options=api.ObjectMetaOptions(max_chunk_size=chunk_size),
        )
        await js.publish(meta_subject, json.dumps(info.as_dict()).encode(),
                         headers={api.Header.ROLLUP: MSG_ROLLUP_SUBJECT}, timeout=STORE_ANSWER)
        return nuid

    def _subjects(self, name: str | None = None, nuid: str | None = None) -> tuple[str, str]:
        """See :func:`_object_subjects` (this link's bucket)."""
        return _object_subjects(self._bucket, name, nuid)

    def _store_stream(self) -> str:
        return _store_stream(self._bucket)

    async def _remove_object(self, js: Any, name: str, nuid: str) -> None:
        """Remove an object and leave nothing of it: its description first (a worker reading it
        finds it gone), then its chunks. nats-py's ``delete`` leaves a description marked deleted
        for every object, kept forever: one per broadcast, 54,000 in the hour of a chaos soak,
        which the server indexed and a restarted trainer's listing read in full."""
        stream = self._store_stream()
        meta, chunks = self._subjects(name, nuid)
        try:
            await js.purge_stream(stream, subject=meta)
            await js.purge_stream(stream, subject=chunks)
        except Exception as e:  # noqa: BLE001 (left for the next trainer's cleanup)
            logger.debug("trainer link: weights object %s not removed (%s)", name, e)

    async def _clean_objects(self, js: Any) -> None:
        """Remove what earlier trainers left in the store except the latest object: older
        objects, the descriptions of deleted ones (earlier versions of tmrl left one per
        broadcast), the chunks of an upload cut by a kill."""
        import nats.js.errors as jse
        from nats.js import api
        from nats.js.object_store import MSG_ROLLUP_SUBJECT

        stream = self._store_stream()
        kv = await js.key_value(self._bucket)
        keep: tuple[str, str] | None = None
        try:
            meta = wire.decode(bytes((await kv.get(LATEST_KEY)).value or b""))
            if isinstance(meta, dict) and isinstance(meta.get("name"), str) and isinstance(meta.get("nuid"), str):
                keep = (meta["name"], meta["nuid"])
        except (jse.NotFoundError, wire.DecodeError):
            pass
        kept_subjects: tuple[str, ...] = ()
        kept_seq = None
        if keep is not None:
            kept_subjects = self._subjects(*keep)
            try:
                description = await js.get_last_msg(stream, kept_subjects[0])
            except jse.NotFoundError:
                keep, kept_subjects = None, ()
            else:  # written again, so that every other description is older than it
                kept_seq = (await js.publish(kept_subjects[0], description.data,
                                             headers={api.Header.ROLLUP: MSG_ROLLUP_SUBJECT})).seq
        # Every other description in one request (there can be a million), then what is left
        # (a few chunk subjects), one by one, as the server lists them.
        await js.purge_stream(stream, subject=self._subjects()[0], seq=kept_seq)
        await self._remove_all_but(js, kept_subjects)
        if keep is not None:
            self._objects.append(keep)

    async def _remove_all_but(self, js: Any, kept_subjects: Any) -> None:
        """Purge every subject of the store except ``kept_subjects``, one by one, as the server lists
        them."""
        stream = self._store_stream()
        held = (await js.stream_info(stream, subjects_filter=f"$O.{self._bucket}.>")).state.subjects or {}
        for subject in held:
            if subject not in kept_subjects:
                await js.purge_stream(stream, subject=subject)

    def _flush(self, budget: float) -> None:
        deadline = time.monotonic() + budget
        while self._is_connected and time.monotonic() < deadline:
            with self._weights_lock:
                if self._pending_weights is None and not self._uploading:
                    break
            time.sleep(0.05)
