"""The :class:`Trainer`: the training loop of a distributed run, epoch after epoch, with a
checkpoint after each (and, optionally, Weights & Biases logging)."""

from __future__ import annotations

import logging
import os
import secrets
import tempfile
import time
from collections.abc import Callable, Iterable
from typing import Any

from tmrl.config.settings import NetSettings
from tmrl.distributed._common import (
    FROM_CONFIG,
    LOGGER_NAME,
    NOT_GIVEN,
    STOP_TIMEOUT,
    _given,
    _given_keep_none,
    _settings,
)
from tmrl.distributed.trainer_interface import TrainerInterface
from tmrl.errors import UserError
from tmrl.spaces import PinnedSampleSchema, SampleSchema
from tmrl.util import show_progress_on_console

logger = logging.getLogger(LOGGER_NAME)


class Trainer:
    """Where training happens: runs ``training_cls`` epoch after epoch, feeding it the samples of
    every worker and broadcasting its actor's weights, with a checkpoint after each epoch.

    Args:
        training_cls: a callable (usually a ``partial`` of ``TorchTrainingOffline``) building the
            training instance; ``None`` calls :meth:`configured_training` (this class has no
            configuration of its own to read: :class:`tmrl.networking.Trainer`, the public one,
            reads ``config_objects.TRAINER``, as tmrl 0.7 did).
        server_ip: the server's address (``SERVER_IP_FOR_TRAINER``).
        server_port: the server's port (``PORT``).
        password: the server's password (``PASSWORD``).
        local_com_port: accepted for compatibility with tmrl 0.7, unused.
        header_size: tlspyo header size (``HEADER_SIZE``).
        max_buf_len: accepted for compatibility with tmrl 0.7, unused (the transport bounds memory).
        security: ``"TLS"`` or ``None`` (``SECURITY``).
        keys_dir: credentials folder (``CREDENTIALS_DIRECTORY``).
        hostname: TLS hostname of the server certificate (``HOSTNAME``).
        model_path: where the trainer keeps a copy of the latest weights (``MODEL_PATH_TRAINER``).
        checkpoint_path: checkpoint file, written after every epoch and resumed from at start;
            ``None`` for no checkpoint (by default ``CHECKPOINT_PATH``).
        dump_run_instance_fn: ``fn(run_instance, path)`` writing a checkpoint
            (default: :func:`tmrl.checkpoint.dump_run_instance`: a checkpoint folder with the
            agent, the replay memory, counters and RNG states, written atomically).
        load_run_instance_fn: ``fn(path) -> run_instance`` (default: restores the checkpoint
            folder into a fresh ``training_cls()``; see :func:`tmrl.checkpoint.load_checkpoint`).
        updater_fn: ``fn(run_instance, training_cls) -> run_instance`` applied after loading a
            checkpoint, for example to change hyperparameters of a resumed run.
        obs_preprocessor: the workers' observation preprocessor (``OBS_PREPROCESSOR`` of the
            built-in pipelines; ``None``: the workers use none).
        sample_compressor: the workers' sample compressor (``SAMPLE_COMPRESSOR``; ``None``: none).
            With ``obs_preprocessor`` and the spaces of the training instance (``run_instance.agent.observation_space`` and
            ``action_space``) they give the run's :class:`~tmrl.spaces.SampleSchema`: sample
            batches that do not fit it are dropped before the memory sees them. When neither is
            given (tmrl 0.7's scripts), batches are still checked (numbers, finite values, actions
            in bounds) but their shapes are fixed by the first batch received
            (:class:`~tmrl.spaces.PinnedSampleSchema`); ``python -m tmrl --trainer`` always gives
            them.

    A run has an identity (:attr:`run_id`): created for a new run, kept in the default
    checkpoint, stamped on every broadcast; workers stamp their samples with the identity of the
    weights they act with, and samples made for another run are dropped.

    Raises:
        UserError: bad connection settings; at :meth:`run`, a checkpoint that cannot be resumed
            (for example a checkpoint folder whose header is missing), or a schema that cannot be
            derived.
    """

    def __init__(
        self,
        training_cls: Callable[[], Any] | None = None,
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
        checkpoint_path: str | os.PathLike[str] | None = FROM_CONFIG,
        dump_run_instance_fn: Callable[[Any, str], None] | None = None,
        load_run_instance_fn: Callable[[str], Any] | None = None,
        updater_fn: Callable[[Any, Any], Any] | None = None,
        obs_preprocessor: Callable[[Any], Any] | None = NOT_GIVEN,
        sample_compressor: Callable[..., tuple] | None = NOT_GIVEN,
        *,
        settings: NetSettings | None = None,
    ):
        show_progress_on_console()
        cfg = self.settings = _settings(settings)
        if training_cls is None:
            training_cls = self.configured_training()
        self.training_cls = training_cls
        cp = _given_keep_none(checkpoint_path, cfg.checkpoint_path)
        self.checkpoint_path = str(cp) if cp is not None else None
        self._default_checkpoint = dump_run_instance_fn is None and load_run_instance_fn is None
        if dump_run_instance_fn is None or load_run_instance_fn is None:
            from tmrl import checkpoint

            dump_run_instance_fn = dump_run_instance_fn or checkpoint.dump_run_instance
            load_run_instance_fn = load_run_instance_fn or checkpoint.make_load_run_instance_fn(training_cls)
        self.dump_run_instance_fn = dump_run_instance_fn
        self.load_run_instance_fn = load_run_instance_fn
        self.updater_fn = updater_fn
        self.obs_preprocessor = obs_preprocessor
        self.sample_compressor = sample_compressor
        self.run_instance: Any = None
        self.run_id: str | None = None
        self.callbacks: list[Any] = []
        self.metrics_logger: Any = None
        """where the training loop reports each round (a :class:`tmrl.metrics.MetricsLogger`); ``None``:
        the training instance's own (console only unless it was given one). ``python -m tmrl
        --trainer`` sets one that also writes ``<data folder>/logs/<RUN_NAME>/metrics.csv``."""
        self.interface = TrainerInterface(
            server_ip=server_ip,
            server_port=server_port,
            password=password,
            local_com_port=local_com_port,
            header_size=header_size,
            max_buf_len=max_buf_len,
            security=security,
            keys_dir=keys_dir,
            hostname=hostname,
            model_path=model_path,
            settings=cfg,
        )

    @staticmethod
    def configured_training() -> Callable[[], Any]:
        """The training class used when none is given. This layer reads no run configuration:
        a subclass says where it comes from (:class:`tmrl.networking.Trainer`: ``config.json``).

        Raises:
            UserError: always, here.
        """
        raise UserError(
            "Trainer needs training_cls (a partial of TorchTrainingOffline): pass it, or use "
            "tmrl.networking.Trainer, which reads it from config.json"
        )

    def checkpoint_exists(self) -> bool:
        """Whether there is a checkpoint to resume from at ``checkpoint_path``.

        Raises:
            CheckpointError: a checkpoint folder holds saved state but no header (it would be
                overwritten by a new run): it is refused, never overwritten.
        """
        path = self.checkpoint_path
        if path is None or not os.path.exists(path):
            return False
        if self._default_checkpoint and os.path.isdir(path):
            from tmrl.checkpoint import checkpoint_complete

            return checkpoint_complete(path)
        return True

    def _load_or_create(self) -> Any:
        path = self.checkpoint_path
        if path is not None and self.checkpoint_exists():
            t0 = time.perf_counter()
            run_instance = self.load_run_instance_fn(path)
            logger.info(
                "resumed from checkpoint %s (epoch %s) in %.1f s",
                path,
                getattr(run_instance, "epoch", "?"),
                time.perf_counter() - t0,
            )
            if self.updater_fn is not None:
                run_instance = self.updater_fn(run_instance, self.training_cls)
            run_id = getattr(run_instance, "run_id", None)
            self.run_id = run_id if isinstance(run_id, str) and run_id else None
        else:
            run_instance = self.training_cls()
            self.run_id = secrets.token_hex(8)
            try:
                run_instance.run_id = self.run_id  # kept by the default checkpoint
            except AttributeError:  # a training class with __slots__: the identity lives here only
                pass
            if path is not None:
                self.dump_run_instance_fn(run_instance, path)
        if self.metrics_logger is not None and hasattr(run_instance, "metrics_logger"):
            run_instance.metrics_logger = self.metrics_logger
        add = getattr(run_instance, "add_callback", None)
        for callback in self.callbacks:
            if add is None:
                raise UserError(f"{type(run_instance).__name__} takes no callbacks: build it from tmrl.training_offline")
            add(callback)
        self._announce(run_instance)
        return run_instance

    def add_callback(self, callback: Any) -> None:
        """Observe training: ``callback`` goes to the training loop when :meth:`run` builds or
        resumes it (:meth:`tmrl.training_offline.TrainingOffline.add_callback`: a
        ``TrainingCallback``, or a function called with each round's ``RoundMetrics``)."""
        self.callbacks.append(callback)

    def _announce(self, run_instance: Any) -> None:
        """Give the interface the run's schema and identity, and broadcast the actor at once:
        workers that (re)connect get this run's weights (and identity) without waiting for the
        next training step, which may itself wait for their samples."""
        self.interface.run_id = self.run_id
        pace = getattr(run_instance, "pace", None)
        self.interface.pace_source = pace if callable(pace) else None
        agent = getattr(run_instance, "agent", None)
        spaces = None
        for holder in (agent, run_instance):
            obs, act = getattr(holder, "observation_space", None), getattr(holder, "action_space", None)
            if obs is not None and act is not None:
                spaces = (obs, act)
                break
        if spaces is not None and self.obs_preprocessor is NOT_GIVEN and self.sample_compressor is NOT_GIVEN:
            self.interface.schema = PinnedSampleSchema(spaces[1])
            logger.info(
                "sample batches are checked for numbers, finite values and actions in bounds, their shapes are "
                "fixed by the first batch: give Trainer the workers' obs_preprocessor and sample_compressor "
                "(None if they have none) to check shapes against the spaces"
            )
        elif spaces is not None:
            given = [None if f is NOT_GIVEN else f for f in (self.obs_preprocessor, self.sample_compressor)]
            self.interface.schema = SampleSchema(*spaces, *given)
            logger.info("sample batches are checked against %r", self.interface.schema)
        else:
            logger.info("the training instance names no spaces: sample batches are checked for structure only")
        ensure_finite = getattr(run_instance, "ensure_finite", None)  # also keeps a good copy
        if agent is not None and hasattr(agent, "get_actor") and (not callable(ensure_finite) or ensure_finite()):
            try:
                self.interface.broadcast_model(agent.get_actor())
            except Exception:
                logger.exception("could not broadcast the actor")

    def _iterate_epochs(self) -> Iterable[Any]:
        run_instance = self._load_or_create()
        self.run_instance = run_instance
        while run_instance.epoch < run_instance.epochs:
            stats = run_instance.run_epoch(interface=self.interface)
            ensure_finite = getattr(run_instance, "ensure_finite", None)
            if callable(ensure_finite) and not ensure_finite():
                logger.error("checkpoint not saved: the agent's parameters are not finite")
            elif self.checkpoint_path is not None:
                t0 = time.perf_counter()
                try:
                    self.dump_run_instance_fn(run_instance, self.checkpoint_path)
                except OSError as err:  # a full disk, a folder gone: written atomically, the last one stands
                    logger.error("checkpoint not saved (%s): the previous one is kept; training goes on", err)
                else:
                    logger.info("checkpoint saved in %.2f s", time.perf_counter() - t0)
            yield stats

    def run(self) -> None:
        """Train until ``training_cls``'s number of epochs is reached; the network link is
        closed at the end (also on Ctrl-C, which propagates as ``KeyboardInterrupt``: then within
        a few seconds, without waiting for the server)."""
        try:
            for _ in self._iterate_epochs():
                pass
        except KeyboardInterrupt:
            self.interface.close(STOP_TIMEOUT)
            raise
        finally:
            self.interface.close()

    def run_with_wandb(
        self,
        entity: str | None = None,
        project: str | None = None,
        run_id: str | None = None,
        key: str | None = None,
    ) -> None:
        """Like :meth:`run`, logging every epoch's statistics to Weights & Biases.

        Args:
            entity: wandb entity, a user or team (``WANDB_ENTITY`` from the config when ``None``).
            project: wandb project (``WANDB_PROJECT``).
            run_id: wandb run id, to resume the same wandb run (``WANDB_RUN_ID``).
            key: wandb API key (``WANDB_KEY``); set as ``WANDB_API_KEY`` for this process.

        Raises:
            UserError: wandb is not installed.
        """
        try:
            import wandb  # type: ignore[import-not-found]
        except ImportError as err:
            raise UserError('wandb is not installed: pip install ".[wandb]" in the checkout of this project') from err
        from tmrl.util import partial_to_dict

        cfg = self.settings
        entity = _given(entity, cfg.wandb_entity)
        project = _given(project, cfg.wandb_project)
        run_id = _given(run_id, cfg.wandb_run_id)
        key = _given(key, cfg.wandb_key)
        if key:
            os.environ["WANDB_API_KEY"] = key
        try:
            config = partial_to_dict(self.training_cls)  # type: ignore[arg-type]
        except (ValueError, TypeError, AttributeError):
            config = {}
        resume = self.checkpoint_exists()
        wandb_dir = tempfile.mkdtemp(prefix="tmrl-wandb-")
        wandb.init(
            dir=wandb_dir,
            entity=entity,
            project=project,
            id=run_id,
            resume="allow" if resume else None,
            config=config,
        )
        try:
            for stats in self._iterate_epochs():
                for entry in stats if isinstance(stats, list) else [stats]:
                    if entry is None:
                        continue
                    wandb.log({k: v for k, v in dict(entry).items() if isinstance(v, (int, float))})
        except KeyboardInterrupt:
            self.interface.close(STOP_TIMEOUT)
            raise
        finally:
            self.interface.close()
            wandb.finish()


# ================================================================================================
# Rollout worker
