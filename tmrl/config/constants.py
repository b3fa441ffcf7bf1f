"""The constants of the original ``tmrl.config.config_constants``, derived from a loaded config.

:func:`constants` computes every value that compatibility module exposes (the data folder's paths,
the networking values of :class:`~tmrl.config.settings.NetSettings`, the environment's flags, the
fixed values of the original) from a config dict, without reading or writing anything. The module
:mod:`tmrl.config.config_constants` calls it on the configuration it loads when imported; the
roles (:mod:`tmrl.roles`) call it on the same configuration.
"""

from __future__ import annotations

import platform
from collections.abc import Mapping
from types import SimpleNamespace
from typing import Any

from tmrl.config.loader import data_paths
from tmrl.config.settings import NetSettings

__all__ = ["RTGYM_VERSION", "constants"]

RTGYM_VERSION = "real-time-gym-ts-v1"
"""The Gymnasium id of the real-time environment (:mod:`tmrl.realtime`)."""


def constants(cfg: Mapping[str, Any], folder: Any = None) -> SimpleNamespace:
    """The values of ``tmrl.config.config_constants`` for ``cfg``, under the original names
    (``RUN_NAME``, ``MODEL_PATH_WORKER``, ``PRAGMA_LIDAR``, ...; ``TMRL_CONFIG`` is ``cfg`` itself).

    Args:
        cfg: a complete, validated config (:func:`tmrl.config.loader.load_config`).
        folder: the data folder the paths lie under; None for the data folder of
            :func:`tmrl.config.loader.data_folder`.

    Returns:
        A namespace holding one attribute per name of ``config_constants``, in its order.
    """
    paths = data_paths(cfg, folder)
    net = NetSettings.from_config(cfg, folder)
    env: Mapping[str, Any] = cfg["ENV"]
    interface: str = env["RTGYM_INTERFACE"]
    progress = interface.endswith("LIDARPROGRESS")
    reward: Mapping[str, Any] = env["REWARD_CONFIG"]
    return SimpleNamespace(
        TMRL_CONFIG=cfg,
        CONFIG_VERSION=cfg["__VERSION__"],
        # data folder
        TMRL_FOLDER=paths.root,
        PATH_DATA=paths.root,
        CONFIG_FOLDER=paths.root / "config",
        CONFIG_FILE=paths.config_file,
        WEIGHTS_FOLDER=paths.weights,
        CHECKPOINTS_FOLDER=paths.checkpoints,
        DATASET_FOLDER=paths.dataset,
        REWARD_FOLDER=paths.reward,
        CREDENTIALS_FOLDER=paths.credentials,
        LOGS_FOLDER=paths.logs,
        # general
        RUN_NAME=cfg["RUN_NAME"],
        RESET_TRAINING=cfg["RESET_TRAINING"],
        BUFFERS_MAXLEN=cfg["BUFFERS_MAXLEN"],
        RW_MAX_SAMPLES_PER_EPISODE=cfg["RW_MAX_SAMPLES_PER_EPISODE"],
        PRAGMA_RNN=False,
        CUDA_TRAINING=cfg["CUDA_TRAINING"],
        CUDA_INFERENCE=cfg["CUDA_INFERENCE"],
        PRAGMA_GAMEPAD=cfg["VIRTUAL_GAMEPAD"],
        SEED=cfg["SEED"],
        LOCALHOST_WORKER=cfg["LOCALHOST_WORKER"],
        LOCALHOST_TRAINER=cfg["LOCALHOST_TRAINER"],
        PUBLIC_IP_SERVER=cfg["PUBLIC_IP_SERVER"],
        SERVER_IP_FOR_WORKER=net.server_ip_for_worker,
        SERVER_IP_FOR_TRAINER=net.server_ip_for_trainer,
        # environment
        ENV_CONFIG=env,
        RTGYM_INTERFACE=interface,
        SYSTEM=platform.system(),
        RTGYM_VERSION=RTGYM_VERSION,
        PRAGMA_PROGRESS=progress,
        PRAGMA_LIDAR=interface.endswith("LIDAR") or progress,
        PRAGMA_TM2020_TMNF=True,
        LIDAR_BLACK_THRESHOLD=[55, 55, 55],
        REWARD_CONFIG=reward,
        REWARD_END_OF_TRACK=reward["END_OF_TRACK"],
        CONSTANT_PENALTY=reward["CONSTANT_PENALTY"],
        SLEEP_TIME_AT_RESET=env["SLEEP_TIME_AT_RESET"],
        IMG_HIST_LEN=env["IMG_HIST_LEN"],
        ACT_BUF_LEN=env["RTGYM_CONFIG"]["act_buf_len"],
        WINDOW_WIDTH=env["WINDOW_WIDTH"],
        WINDOW_HEIGHT=env["WINDOW_HEIGHT"],
        GRAYSCALE=env["IMG_GRAYSCALE"],
        IMG_WIDTH=env["IMG_WIDTH"],
        IMG_HEIGHT=env["IMG_HEIGHT"],
        LINUX_X_OFFSET=env["LINUX_X_OFFSET"],
        LINUX_Y_OFFSET=env["LINUX_Y_OFFSET"],
        IMG_SCALE_CHECK_ENV=env["IMG_SCALE_CHECK_ENV"],
        GYM_ID=env["GYM_ID"],
        GYM_KWARGS=env["GYM_KWARGS"],
        SIM_FAST_MODE=env["SIM_FAST_MODE"],
        # algorithm
        ALG_CONFIG=cfg["ALG"],
        ALG_NAME=cfg["ALG"]["ALGORITHM"],
        # debugging and benchmarking
        CRC_DEBUG=False,
        CRC_DEBUG_SAMPLES=100,
        PROFILE_TRAINER=False,
        SYNCHRONIZE_CUDA=False,
        DEBUG_MODE=cfg["DEBUG_MODE"],
        # files
        MODEL_HISTORY=net.model_history,
        MODEL_PATH_WORKER=net.model_path_worker,
        MODEL_PATH_SAVE_HISTORY=net.model_path_save_history,
        MODEL_PATH_TRAINER=net.model_path_trainer,
        CHECKPOINT_PATH=net.checkpoint_path,
        DATASET_PATH=paths.dataset,
        REWARD_PATH=paths.reward_file,
        # wandb
        WANDB_RUN_ID=net.wandb_run_id,
        WANDB_PROJECT=net.wandb_project,
        WANDB_ENTITY=net.wandb_entity,
        WANDB_KEY=net.wandb_key,
        # networking
        PRINT_BYTESIZES=True,
        PORT=net.port,
        LOCAL_PORT_SERVER=cfg["LOCAL_PORT_SERVER"],
        LOCAL_PORT_TRAINER=cfg["LOCAL_PORT_TRAINER"],
        LOCAL_PORT_WORKER=cfg["LOCAL_PORT_WORKER"],
        PASSWORD=net.password,
        SECURITY=net.security,
        CREDENTIALS_DIRECTORY=net.credentials_directory,
        HOSTNAME=net.hostname,
        NB_WORKERS=net.max_workers,
        BUFFER_SIZE=cfg["BUFFER_SIZE"],
        HEADER_SIZE=net.header_size,
        ALLOW_PLAIN_TCP=net.allow_plain_tcp,
        ALLOW_PICKLE=net.allow_pickle,
        MAX_FRAME_BYTES=net.max_frame_bytes,
        SERVER_MEMORY_BYTES=net.server_memory_bytes,
        SERVER_PARTIAL_TIMEOUT=net.server_partial_timeout,
    )
