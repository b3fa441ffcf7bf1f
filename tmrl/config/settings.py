"""The loaded config as an object for the distributed roles (server, trainer, workers).

:class:`NetSettings` holds every value the roles of :mod:`tmrl.networking` take from
``config.json`` (ports, password, TLS, file paths, transport limits), derived in one place from a
loaded config: :meth:`NetSettings.from_config`. A role built without ``settings=`` loads the
config when it is built (never at import); the CLI passes the config it loaded. The compatibility
module :mod:`tmrl.config.config_constants` exposes the same values under the original names, taken
from here.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

__all__ = ["NetSettings"]


@dataclass(frozen=True)
class NetSettings:
    """What the roles read from the config (keys in parentheses).

    Attributes:
        port: public port of the server (``PORT``).
        password: the shared secret (``PASSWORD``).
        header_size: size of the transport's message header (``HEADER_SIZE``).
        security: ``"TLS"`` or None for plain TCP (``TLS``).
        credentials_directory: folder of the TLS key, certificate and the trainer's signing key
            (``TLS_CREDENTIALS_DIRECTORY``, or ``credentials/`` of the data folder).
        hostname: host name in the TLS certificate (``TLS_HOSTNAME``).
        max_workers: most workers at once, None for no limit (``NB_WORKERS``, negative: None).
        server_ip_for_worker: where a worker reaches the server (``LOCALHOST_WORKER``,
            ``PUBLIC_IP_SERVER``).
        server_ip_for_trainer: where the trainer reaches the server (``LOCALHOST_TRAINER``,
            ``PUBLIC_IP_SERVER``).
        buffers_maxlen: most samples held in a network buffer (``BUFFERS_MAXLEN``).
        max_samples_per_episode: a worker truncates longer episodes (``RW_MAX_SAMPLES_PER_EPISODE``).
        model_path_worker: the worker's weights file (from ``RUN_NAME``).
        model_path_trainer: the trainer's weights file (from ``RUN_NAME``).
        model_path_save_history: prefix of the worker's saved weights history (from ``RUN_NAME``).
        model_history: keep every N-th received model, 0 for none (``SAVE_MODEL_EVERY``).
        worker_sync_steps: a worker syncs every N steps of a train episode, 0 between episodes
            only (``WORKER_SYNC_STEPS``).
        checkpoint_path: the trainer's checkpoint (from ``RUN_NAME``).
        allow_plain_tcp: plain TCP beyond this machine (``ALLOW_PLAIN_TCP``).
        allow_pickle: accept pickled messages (``ALLOW_PICKLE``).
        max_frame_bytes: largest message accepted (``MAX_FRAME_BYTES``).
        server_memory_bytes: the relay's memory budget (``SERVER_MEMORY_BYTES``).
        server_partial_timeout: seconds a half-received message may wait (``SERVER_PARTIAL_TIMEOUT``).
        wandb_project: Weights & Biases project of ``--trainer --wandb`` (``WANDB_PROJECT``).
        wandb_entity: Weights & Biases entity, a user or team (``WANDB_ENTITY``).
        wandb_key: Weights & Biases API key (``WANDB_KEY``).
        wandb_run_id: Weights & Biases run id (``RUN_NAME``).
        transport: the transport backend, a key of :data:`tmrl.transport.BACKENDS` (``TRANSPORT``).
        nats: the ``NATS`` section (used when ``transport`` is ``"nats"``).
        data_folder: the data folder (the NATS server's store lies under it by default).
    """

    port: int
    password: str
    header_size: int
    security: str | None
    credentials_directory: Path
    hostname: str
    max_workers: int | None
    server_ip_for_worker: str
    server_ip_for_trainer: str
    buffers_maxlen: int
    max_samples_per_episode: int
    model_path_worker: Path
    model_path_trainer: Path
    model_path_save_history: Path
    model_history: int
    checkpoint_path: Path
    allow_plain_tcp: bool
    allow_pickle: bool
    max_frame_bytes: int
    server_memory_bytes: int
    server_partial_timeout: float
    wandb_project: str
    wandb_entity: str
    wandb_key: str
    wandb_run_id: str
    transport: str = "tlspyo"
    nats: Mapping[str, Any] = field(default_factory=dict)
    data_folder: Path | None = None
    worker_sync_steps: int = 0

    @classmethod
    def from_config(cls, cfg: Mapping[str, Any], folder: Any = None) -> NetSettings:
        """The settings of a loaded config. Reads and creates nothing.

        Args:
            cfg: a complete, validated config (:func:`tmrl.config.loader.load_config`).
            folder: the data folder the paths lie under; None for the data folder of
                :func:`tmrl.config.loader.data_folder`.
        """
        from tmrl.config.loader import data_paths

        paths = data_paths(cfg, folder)
        public = cfg["PUBLIC_IP_SERVER"]
        return cls(
            port=int(cfg["PORT"]),
            password=cfg["PASSWORD"],
            header_size=int(cfg["HEADER_SIZE"]),
            security="TLS" if cfg["TLS"] else None,
            credentials_directory=paths.credentials,
            hostname=cfg["TLS_HOSTNAME"],
            max_workers=None if cfg["NB_WORKERS"] < 0 else int(cfg["NB_WORKERS"]),
            server_ip_for_worker="127.0.0.1" if cfg["LOCALHOST_WORKER"] else public,
            server_ip_for_trainer="127.0.0.1" if cfg["LOCALHOST_TRAINER"] else public,
            buffers_maxlen=int(cfg["BUFFERS_MAXLEN"]),
            max_samples_per_episode=int(cfg["RW_MAX_SAMPLES_PER_EPISODE"]),
            model_path_worker=paths.model_worker,
            model_path_trainer=paths.model_trainer,
            model_path_save_history=paths.model_history_prefix,
            model_history=int(cfg["SAVE_MODEL_EVERY"]),
            checkpoint_path=paths.checkpoint,
            allow_plain_tcp=bool(cfg["ALLOW_PLAIN_TCP"]),
            allow_pickle=bool(cfg["ALLOW_PICKLE"]),
            max_frame_bytes=int(cfg["MAX_FRAME_BYTES"]),
            server_memory_bytes=int(cfg["SERVER_MEMORY_BYTES"]),
            server_partial_timeout=float(cfg["SERVER_PARTIAL_TIMEOUT"]),
            wandb_project=cfg["WANDB_PROJECT"],
            wandb_entity=cfg["WANDB_ENTITY"],
            wandb_key=cfg["WANDB_KEY"],
            wandb_run_id=cfg["RUN_NAME"],
            transport=cfg["TRANSPORT"],
            nats=dict(cfg["NATS"]),
            data_folder=paths.root,
            worker_sync_steps=int(cfg["WORKER_SYNC_STEPS"]),
        )

    @classmethod
    def load(cls) -> NetSettings:
        """The settings of ``config.json`` in the data folder (with ``$TMRL_CONFIG_OVERRIDE``),
        or of the defaults when that file does not exist yet.

        Raises:
            tmrl.config.schema.ConfigError: the configuration is invalid (one line naming the key).
        """
        from tmrl.config.loader import load_config

        return cls.from_config(load_config())

    def link_options(self) -> dict[str, Any]:
        """The transport options only the config sets (plain TCP beyond localhost, the pickle
        opt-in, the frame size limit)."""
        return {
            "allow_plain_tcp": self.allow_plain_tcp,
            "allow_pickle": self.allow_pickle,
            "max_frame_bytes": self.max_frame_bytes,
        }

    def transport_options(self, role: str) -> dict[str, Any]:
        """The options only the chosen transport takes, for ``role`` (``"relay"``, ``"worker"`` or
        ``"trainer"``): none for tlspyo; the ``NATS`` section's for nats."""
        if self.transport != "nats":
            return {}
        n = self.nats
        opts: dict[str, Any] = {
            "urls": n["URLS"],
            "tls": n["TLS"],
            "stream": n["STREAM"],
            "bucket": n["BUCKET"],
            "max_bytes": int(n["MAX_BYTES"]),
            "max_msgs": int(n["MAX_MSGS"]),
            "replicas": int(n["REPLICAS"]),
        }
        if role == "relay":
            store = str(n["STORE_DIRECTORY"]).strip()
            root = self.data_folder if self.data_folder is not None else Path(".")
            opts["store_dir"] = Path(store).expanduser() if store else root / "nats"
            opts["max_payload"] = int(n["MAX_PAYLOAD"])
        else:
            creds = str(n[f"{role.upper()}_CREDENTIALS"]).strip()
            if creds:
                opts["credentials"] = Path(creds).expanduser()
        return opts

    def relay_options(self) -> dict[str, Any]:
        """The relay's memory bounds."""
        return {"max_total_bytes": self.server_memory_bytes, "partial_timeout": self.server_partial_timeout}
