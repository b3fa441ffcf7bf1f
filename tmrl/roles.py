"""What ``python -m tmrl --server/--trainer/--worker/--expert/--test/--benchmark`` start.

Each function builds its object from the process's configuration
(:func:`tmrl.config.loader.process_config`, read once, the one ``tmrl.config.config_constants``
exposes) through :func:`tmrl.assembly.assemble` (the objects ``tmrl.config.config_objects`` hands
out too), runs it until it is done or interrupted, and returns the process exit code (0 done,
130 Ctrl-C, 143 SIGTERM, 129 SIGHUP, 149 Ctrl-Break). Ctrl-C, SIGTERM, SIGHUP (a closed terminal,
Linux and macOS; ignored under ``nohup``) and Ctrl-Break (Windows) stop the role cleanly within a
few seconds, in every state: the network link or relay is closed (no child process keeps a port)
and one line says which signal stopped what.
"""

from __future__ import annotations

import logging
import os
import sys
import threading
from collections.abc import Mapping
from typing import Any

from tmrl.errors import UserError
from tmrl.distributed import STOP_TIMEOUT

__all__ = [
    "THREADS_ENV",
    "WORKER_MODES",
    "configured_actor",
    "role_threads",
    "run_benchmark",
    "run_export_weights",
    "run_import_weights",
    "run_server",
    "run_trainer",
    "run_worker",
    "size_threads",
]

logger = logging.getLogger(__name__)

#: Modes of :func:`run_worker`: ``train`` (send samples, load weights), ``expert`` (send samples,
#: ignore weights), ``test`` (standalone: run the current weights, send nothing).
WORKER_MODES = ("train", "expert", "test")

#: Exit code of a role stopped by Ctrl-C (128 + SIGINT, as the CLI's).
INTERRUPTED = 130
#: Exit code of a role stopped by SIGTERM (128 + SIGTERM).
TERMINATED = 143
#: Exit code of a role stopped by SIGHUP (128 + SIGHUP): its terminal was closed (POSIX).
HUNG_UP = 129
#: Exit code of a role stopped by Ctrl-Break (128 + SIGBREAK, Windows).
BROKEN = 149


class Terminated(KeyboardInterrupt):
    """SIGTERM arrived (``kill``, a service manager): stop like Ctrl-C, and say which it was."""

    signum = 15  # SIGTERM: the exit code is 128 + signum


class HungUp(Terminated):
    """SIGHUP arrived (the role's terminal was closed): stop like Ctrl-C, and say which it was."""

    signum = 1  # SIGHUP


class CtrlBreak(Terminated):
    """Ctrl-Break arrived (Windows' SIGBREAK): stop like Ctrl-C, and say which it was."""

    signum = 21  # SIGBREAK


def _interrupt_on_sigterm() -> None:
    """Make SIGTERM and SIGHUP stop a role like Ctrl-C: cleanly, within a few seconds. A SIGHUP
    inherited as ignored (``nohup``) stays ignored."""
    import signal

    def handler(signum: int, frame: Any) -> None:
        # A second signal during the clean-up would interrupt it half-way: the first one is enough.
        for other in stop_signals:
            signal.signal(other, signal.SIG_IGN)
        if signum == getattr(signal, "SIGHUP", None):
            raise HungUp
        raise CtrlBreak if signum == getattr(signal, "SIGBREAK", None) else Terminated

    stop_signals = [signal.SIGTERM]
    for name in ("SIGHUP", "SIGBREAK"):  # where they exist: POSIX, Windows
        signum = getattr(signal, name, None)
        if signum is not None and signal.getsignal(signum) is not signal.SIG_IGN:
            stop_signals.append(signum)
    if threading.current_thread() is threading.main_thread():
        for signum in stop_signals:
            signal.signal(signum, handler)


def _stopped(role: str, err: KeyboardInterrupt, detail: str = "") -> int:
    """Say in one line that ``role`` stopped and why; return the exit code."""
    if isinstance(err, HungUp):
        name, code = "SIGHUP", HUNG_UP
    elif isinstance(err, CtrlBreak):
        name, code = "Ctrl-Break", BROKEN
    elif isinstance(err, Terminated):
        name, code = "SIGTERM", TERMINATED
    else:
        name, code = "Ctrl-C", INTERRUPTED
    _say(f"tmrl: {role} stopped ({name}){detail}")
    return code


def _say(line: str) -> None:
    try:
        print(line, file=sys.stderr, flush=True)
    except OSError:  # the terminal was closed (SIGHUP): nobody left to read it
        pass


#: Environment variable: how many threads each role's PyTorch (and OpenMP, MKL) uses; set by
#: ``--threads N`` too. Unset: ``OMP_NUM_THREADS`` when set, else the role's share of the cores.
THREADS_ENV = "TMRL_THREADS"


def _cores() -> int:
    try:
        return len(os.sched_getaffinity(0))  # the cores this process may run on
    except (AttributeError, OSError):
        return os.cpu_count() or 1


def role_threads(role: str, cores: int | None = None) -> tuple[int, str]:
    """How many threads ``role`` (``"trainer"``, ``"worker"``, ...) gives PyTorch, and why.

    ``$TMRL_THREADS`` when set, else ``$OMP_NUM_THREADS`` when set, else the role's share of this
    machine's ``cores``: a worker 1 (it acts on one observation at a time), a trainer every core
    but one, which is left to the worker and the server's relay that usually run beside it (on
    two cores: 1 each, as in the demo; PyTorch's own default, a thread per core in every role,
    oversubscribes the machine as soon as two roles share it).

    Raises:
        UserError: ``$TMRL_THREADS`` is not a whole number of at least 1.
    """
    text = os.environ.get(THREADS_ENV, "").strip()
    if text:
        if not text.isdigit() or int(text) < 1:
            raise UserError(f"{THREADS_ENV}={text!r}: set it to a whole number of threads of at least 1 (or unset it)")
        return int(text), THREADS_ENV
    omp = os.environ.get("OMP_NUM_THREADS", "").strip()
    if omp.isdigit() and int(omp) >= 1:
        return int(omp), "OMP_NUM_THREADS"
    cores = _cores() if cores is None else cores
    return (max(1, cores - 1) if role == "trainer" else 1), f"{cores} cores"


def size_threads(role: str) -> int:
    """Give this process's PyTorch :func:`role_threads` threads, and set ``OMP_NUM_THREADS`` and
    ``MKL_NUM_THREADS`` to the same number for the libraries and processes started later.
    Returns the number."""
    n, why = role_threads(role)
    os.environ["OMP_NUM_THREADS"] = os.environ["MKL_NUM_THREADS"] = str(n)
    import torch

    torch.set_num_threads(n)
    logger.info("%s: %d PyTorch thread%s (%s; %s or --threads to change)", role, n, "" if n == 1 else "s", why,
                THREADS_ENV)
    return n


def _config() -> dict[str, Any]:
    """The configuration the roles run with: the process's, which ``config_constants`` exposes too."""
    from tmrl.config.loader import process_config

    return process_config()


def _constants() -> Any:
    """The original ``config_constants`` names of the roles' configuration."""
    from tmrl.config.constants import constants

    return constants(_config())


def _settings() -> Any:
    """The roles' settings of the loaded config (the one the objects were built from)."""
    from tmrl.config.settings import NetSettings

    return NetSettings.from_config(_config())


def _objects() -> Any:
    """The objects of the roles' configuration: the same ones ``config_objects`` hands out."""
    from tmrl.assembly import assemble

    return assemble(_config())


def run_server(cfg: Mapping[str, Any] | None = None, stop_event: threading.Event | None = None) -> int:
    """Run the server until Ctrl-C (or until ``stop_event`` is set). Returns the exit code.

    Args:
        cfg: the loaded config dict (the values themselves are read from the process's configuration).
        stop_event: lets a caller (tests, a service wrapper) stop the server without a signal.

    Raises:
        UserError: the port cannot be bound, or the TLS credentials are missing.
    """
    from tmrl.distributed import Server

    _interrupt_on_sigterm()
    server = Server(settings=_settings())
    stop_event = stop_event or threading.Event()
    try:  # from here a stop signal says "server stopped", also right after the line below
        logger.info("server running on port %d; Ctrl-C to stop", server.port)
        while not stop_event.wait(1.0):
            if not server.running:
                _say(f"tmrl: the server on port {server.port} stopped unexpectedly")
                return 1
    except KeyboardInterrupt as err:
        # why: a stopped server must be gone within seconds; the relay's default flush budget
        # (15 s) outlasted a loaded machine's patience (a Ctrl-C'd server alive 20 s later).
        server.stop(STOP_TIMEOUT)
        return _stopped("server", err)
    finally:
        server.stop()
    return 0


def _set_aside(path: str) -> None:
    """Move a checkpoint out of the way (``RESET_TRAINING``), keeping one previous copy."""
    import os

    from tmrl import platform

    old = f"{path}.previous"
    if os.path.isdir(old):
        platform.remove_tree(old)
    elif os.path.exists(old):
        platform.remove(old)
    platform.replace(path, old)
    logger.warning("RESET_TRAINING is true: starting a new run; the previous checkpoint is now %s", old)


def _seed_generators() -> None:
    """Seed Python's, NumPy's and PyTorch's global generators with ``SEED`` (nothing when null)."""
    seed = getattr(_constants(), "SEED", None)
    if seed is None:
        return
    import random

    import numpy as np
    import torch

    random.seed(seed)
    np.random.seed(seed % 2**32)
    torch.manual_seed(seed)


def trainer_from_config() -> Any:
    """The :class:`~tmrl.distributed.Trainer` that ``--trainer`` runs, built from the config."""
    from tmrl.distributed import Trainer

    _seed_generators()
    co = _objects()
    return Trainer(
        training_cls=co.TRAINER,
        settings=_settings(),
        dump_run_instance_fn=getattr(co, "DUMP_RUN_INSTANCE_FN", None),
        load_run_instance_fn=getattr(co, "LOAD_RUN_INSTANCE_FN", None),
        updater_fn=getattr(co, "UPDATER_FN", None),
        obs_preprocessor=getattr(co, "OBS_PREPROCESSOR", None),
        sample_compressor=getattr(co, "SAMPLE_COMPRESSOR", None),
    )


def _metrics_logger(cc: Any) -> Any:
    """The trainer's metrics: the console line, ``<data folder>/logs/<RUN_NAME>/metrics.csv`` and
    TensorBoard events beside it when tensorboard is installed."""
    from tmrl.metrics import MetricsLogger

    return MetricsLogger(run_name=cc.RUN_NAME, folder=cc.TMRL_FOLDER)


def run_trainer(cfg: Mapping[str, Any] | None = None, wandb: bool = False) -> int:
    """Run the trainer (with Weights & Biases logging when ``wandb``) until its last epoch or
    Ctrl-C. Returns the exit code."""
    _interrupt_on_sigterm()
    size_threads("trainer")
    cc = _constants()
    trainer = trainer_from_config()
    trainer.metrics_logger = _metrics_logger(cc)
    path = trainer.checkpoint_path
    if getattr(cc, "RESET_TRAINING", False) and path is not None and os.path.exists(path):
        _set_aside(path)
    logger.info("trainer running %s", getattr(_objects(), "ALG_NAME", "the configured algorithm"))
    try:
        if wandb:
            trainer.run_with_wandb()  # entity, project, run id and key from the settings
        else:
            trainer.run()
    except KeyboardInterrupt as err:
        trainer.interface.close(STOP_TIMEOUT)
        return _stopped("trainer", err, "; the last checkpoint is kept")
    return 0


def _env_cls() -> Any:
    co, cc = _objects(), _constants()
    env_cls = getattr(co, "ENV_CLS", None)
    if env_cls is not None:
        return env_cls
    from tmrl.envs import GenericGymEnv
    from tmrl.util import partial

    return partial(GenericGymEnv, id=cc.RTGYM_VERSION, gym_kwargs={"config": co.CONFIG_DICT})


def _with_replays(env_cls: Any) -> Any:
    """``env_cls`` with the interface's ``save_replays`` on (the simulator and TrackMania)."""
    from tmrl.util import partial

    keywords = dict(getattr(env_cls, "keywords", {}))
    gym_kwargs = keywords.get("gym_kwargs")
    if isinstance(gym_kwargs, Mapping) and isinstance(gym_kwargs.get("config"), Mapping):  # real-time
        config = dict(gym_kwargs["config"])
        config["interface_kwargs"] = {**dict(config.get("interface_kwargs") or {}), "save_replays": True}
        return partial(env_cls.func, *env_cls.args, **{**keywords, "gym_kwargs": {**gym_kwargs, "config": config}})
    if "interface" in keywords:  # the simulator in fast mode
        return partial(env_cls.func, *env_cls.args, **{**keywords, "save_replays": True})
    raise UserError("saving replays needs a simulator (SIM*) or TrackMania (TM20*) ENV.RTGYM_INTERFACE")


def worker_from_config(standalone: bool = False, save_replays: bool = False) -> Any:
    """The :class:`~tmrl.distributed.RolloutWorker` that ``--worker`` runs, built from the config
    (``save_replays``: with the interface's replays on, for :func:`tmrl.tools.save_replays.save_replays`)."""
    from tmrl.distributed import RolloutWorker

    _seed_generators()
    cc, co, settings = _constants(), _objects(), _settings()
    device = getattr(co, "DEVICE_INFERENCE", "cpu")  # "cuda" only when CUDA_INFERENCE and a GPU is there
    if getattr(cc, "CUDA_INFERENCE", False) and device == "cpu":
        logger.warning("CUDA_INFERENCE is true but PyTorch sees no CUDA device: the policy runs on the CPU")
    return RolloutWorker(
        env_cls=_with_replays(_env_cls()) if save_replays else _env_cls(),
        actor_module_cls=co.POLICY,
        sample_compressor=getattr(co, "SAMPLE_COMPRESSOR", None),
        device=device,
        max_samples_per_episode=settings.max_samples_per_episode,
        obs_preprocessor=getattr(co, "OBS_PREPROCESSOR", None),
        crc_debug=bool(getattr(cc, "CRC_DEBUG", False)),
        standalone=standalone,
        settings=settings,
    )


def run_worker(cfg: Mapping[str, Any] | None = None, mode: str = "train", standalone: bool | None = None) -> int:
    """Run a rollout worker until Ctrl-C. Returns the exit code.

    Args:
        cfg: the loaded config dict.
        mode: ``"train"`` (``--worker``), ``"expert"`` (``--expert``) or ``"test"`` (``--test``:
            standalone, no server).
        standalone: connect to no server (default: only in ``"test"`` mode). ``--worker --test``
            runs ``"train"`` standalone, as tmrl 0.7 does: exploring episodes, no samples sent.

    Raises:
        UserError: unknown ``mode``, or bad connection settings.
    """
    if mode not in WORKER_MODES:
        raise UserError(f"unknown worker mode {mode!r}: use one of {', '.join(WORKER_MODES)}")
    _interrupt_on_sigterm()
    size_threads("worker")
    worker = worker_from_config(standalone=mode == "test" if standalone is None else standalone)
    from tmrl.realtime.timeouts import summarised_timeouts

    try:
        # a real-time environment under load: one line per 10 s about late time steps, not two per step
        with summarised_timeouts():
            if mode == "train":
                worker.run()
            elif mode == "expert":
                worker.run(expert=True)
            else:
                worker.run_episodes(10_000)
    except KeyboardInterrupt as err:
        worker.close(STOP_TIMEOUT)
        return _stopped("worker", err, "" if mode == "test" else "; samples already sent are kept")
    finally:
        worker.close()
    return 0


def run_benchmark(cfg: Mapping[str, Any] | None = None, nb_steps: int = 1000) -> int:
    """Benchmark the configured environment (``--benchmark``): a standalone worker steps it
    ``nb_steps`` times and the environment's timing figures are printed. Returns the exit code."""
    _interrupt_on_sigterm()
    size_threads("worker")
    worker = worker_from_config(standalone=True)
    try:
        res = worker.run_env_benchmark(nb_steps=nb_steps, test=False, verbose=False)
    except KeyboardInterrupt as err:
        return _stopped("benchmark", err)
    finally:
        worker.close()
    print(f"benchmark ({nb_steps} steps): {res}")
    return 0


def configured_actor() -> Any:
    """A fresh instance of the actor the configured workers run (the objects' ``POLICY`` on the
    environment's spaces), on the CPU."""
    from tmrl.assembly import actor_for

    return actor_for(_env_cls(), _objects().POLICY)


def run_import_weights(cfg: Mapping[str, Any] | None, src: str, out: str | None = None) -> int:
    """``--import-weights FILE [--out PATH]``: convert a tmrl 0.7 weights file for the configured
    actor and write it where the worker reads its weights (``out`` by default
    ``MODEL_PATH_WORKER``). Returns the exit code.

    Raises:
        tmrl.legacy_weights.LegacyWeightsError: the file is not tensors only, or does not fit.
    """
    from tmrl.legacy_weights import import_file

    target = out if out is not None else str(_constants().MODEL_PATH_WORKER)
    path = import_file(src, target, configured_actor())
    print(f"imported {src} into {path} (the worker and --test load it from there)")
    return 0


def run_export_weights(cfg: Mapping[str, Any] | None, src: str, out: str | None = None) -> int:
    """``--export-weights FILE [--out PATH]``: write this tmrl's weights file ``FILE`` as a
    tmrl 0.7 weights file (default ``out``: next to it, ``<name>-tmrl07.tmod``). Returns the exit
    code.

    Raises:
        tmrl.legacy_weights.LegacyWeightsError: no such file, or weights that do not fit.
    """
    from pathlib import Path

    from tmrl.legacy_weights import export_file

    target = Path(out) if out is not None else Path(src).with_name(Path(src).stem + "-tmrl07.tmod")
    path = export_file(src, target, configured_actor())
    print(f"exported {src} to {path} (tmrl 0.7 reads it with torch.load)")
    return 0
