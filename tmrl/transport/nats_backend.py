"""The NATS JetStream backend's original import path: a re-export of
:mod:`tmrl.transport.jetstream`, where the code lives (one module per job).

Every name this module held keeps working here. The tunables are read by the module that uses
them, so set them there, not here: :data:`~tmrl.transport.jetstream.samples.SEND_WINDOW`,
``SEND_WINDOW_BYTES``, ``ACK_TIMEOUT`` and ``RECEIVE_WINDOW`` in
:mod:`tmrl.transport.jetstream.samples`, :data:`~tmrl.transport.jetstream.weights.WEIGHTS_POLL`
in :mod:`tmrl.transport.jetstream.weights`. Importing this module imports neither ``nats`` nor
starts anything.
"""

from __future__ import annotations

from tmrl.transport._nats_server import (  # noqa: F401 (re-exported: names this module imported)
    DEFAULT_MAX_PAYLOAD,
    INBOX,
    NOTIFY_PREFIX,
    SAMPLES_PREFIX,
    ServerProcess,
    role_credentials,
    users_block,
    write_credentials,
)
from tmrl.transport.jetstream.bridge import _Loop, _Rate, logger  # noqa: F401
from tmrl.transport.jetstream.connect import (  # noqa: F401
    _check_tls_mode,
    _client_tls,
    _NatsLink,
    _require_client,
    _urls,
)
from tmrl.transport.jetstream.layout import (  # noqa: F401
    _NAME,
    CONSUMER,
    DEFAULT_BUCKET,
    DEFAULT_MAX_BYTES,
    DEFAULT_MAX_MSGS,
    DEFAULT_STREAM,
    LATEST_KEY,
    WEIGHTS_OBJECT,
    _check_names,
    _ensure_layout,
    _stream_config,
)
from tmrl.transport.jetstream.samples import (  # noqa: F401
    ACK_TIMEOUT,
    RECEIVE_WINDOW,
    SEND_WINDOW,
    SEND_WINDOW_BYTES,
)
from tmrl.transport.jetstream.server import NatsRelay
from tmrl.transport.jetstream.trainer import NatsTrainerLink
from tmrl.transport.jetstream.weights import WEIGHTS_POLL  # noqa: F401
from tmrl.transport.jetstream.worker import NatsWorkerLink

__all__ = ["NatsRelay", "NatsTrainerLink", "NatsWorkerLink", "write_credentials"]
