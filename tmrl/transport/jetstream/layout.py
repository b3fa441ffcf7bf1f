"""Where the NATS backend keeps things on the server: the samples stream, the weights buckets, their
names and bounds.

- the samples stream (:data:`DEFAULT_STREAM`): subjects ``tmrl.samples.>``, a work queue (an
  acknowledged batch leaves it) bounded by ``max_msgs`` batches and ``max_bytes`` bytes, which
  discards the oldest beyond them; consumed by the durable pull consumer :data:`CONSUMER`;
- the weights (:data:`DEFAULT_BUCKET`): an object store holding the objects
  ``<WEIGHTS_OBJECT>-<random>`` and a key-value bucket of the same name whose entry
  :data:`LATEST_KEY` names the newest object (its revision is the weights' version).

The trainer link and the relay create them (:func:`_ensure_layout`).
"""

from __future__ import annotations

import re
from typing import Any

from tmrl.errors import UserError
from tmrl.transport._nats_server import SAMPLES_PREFIX

DEFAULT_STREAM = "tmrl-samples"
DEFAULT_BUCKET = "tmrl-weights"
DEFAULT_MAX_BYTES = 2**30
DEFAULT_MAX_MSGS = 100_000
CONSUMER = "tmrl-trainer"
WEIGHTS_OBJECT = "actor"
LATEST_KEY = "latest"
_NAME = re.compile(r"[A-Za-z0-9_-]{1,64}")


def _check_names(stream: str, bucket: str) -> None:
    for key, name in (("NATS.STREAM", stream), ("NATS.BUCKET", bucket)):
        if not isinstance(name, str) or not _NAME.fullmatch(name):
            raise UserError(f"{key} must be letters, digits, - and _ only, not {name!r}")


def _stream_config(stream: str, max_bytes: int, max_msgs: int, replicas: int = 1) -> Any:
    from nats.js import api

    return api.StreamConfig(
        name=stream,
        subjects=[f"{SAMPLES_PREFIX}.>"],
        retention=api.RetentionPolicy.WORK_QUEUE,  # an acknowledged batch leaves the stream
        max_msgs=max_msgs,
        max_bytes=max_bytes,
        discard=api.DiscardPolicy.OLD,
        storage=api.StorageType.FILE,
        duplicate_window=120.0,
        num_replicas=replicas,
    )


async def _ensure_layout(js: Any, stream: str, bucket: str, max_bytes: int, max_msgs: int,
                         replicas: int = 1) -> None:
    """Create (or bring up to date) the samples stream and the weights buckets."""
    import nats.js.errors as jse
    from nats.js import api

    cfg = _stream_config(stream, max_bytes, max_msgs, replicas)
    try:
        await js.add_stream(cfg)
    except jse.BadRequestError:  # exists with another configuration (e.g. other bounds)
        await js.update_stream(cfg)
    try:
        await js.create_key_value(bucket=bucket, history=1, storage=api.StorageType.FILE, replicas=replicas)
    except jse.BadRequestError:
        await js.key_value(bucket)
    try:
        await js.create_object_store(bucket=bucket, storage=api.StorageType.FILE, replicas=replicas)
    except jse.BadRequestError:
        await js.object_store(bucket)
