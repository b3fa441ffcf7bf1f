"""Compatibility module: the constants of the original ``tmrl.config.config_constants``.

Its documented job is to read the configuration when imported: it calls
:func:`tmrl.config.loader.load_config` (``config.json`` of the data folder, or the defaults when
that file does not exist yet, plus ``$TMRL_CONFIG_OVERRIDE``) and exposes the values under the
original names. Unlike the original it creates no folder, downloads nothing, sets no environment
variable and configures no logging; paths are :class:`pathlib.Path` objects.

New code should call :func:`~tmrl.config.loader.load_config` and pass the dict around, or hand
:class:`tmrl.config.settings.NetSettings` to the roles, instead. The networking values below are
taken from :class:`~tmrl.config.settings.NetSettings`, where they are derived once.

Raises (at import):
    tmrl.config.loader.ConfigError: the configuration is invalid (one line naming the key).
"""

from __future__ import annotations

import platform
from pathlib import Path
from typing import Any

from tmrl.config.loader import data_paths, load_config
from tmrl.config.settings import NetSettings

__compatibility__ = "0.6.0"

TMRL_CONFIG: dict[str, Any] = load_config()
CONFIG_VERSION: str = TMRL_CONFIG["__VERSION__"]

# --- data folder ---------------------------------------------------------------------------------

_PATHS = data_paths(TMRL_CONFIG)
_NET = NetSettings.from_config(TMRL_CONFIG)
TMRL_FOLDER: Path = _PATHS.root
PATH_DATA: Path = TMRL_FOLDER
CONFIG_FOLDER: Path = TMRL_FOLDER / "config"
CONFIG_FILE: Path = _PATHS.config_file
WEIGHTS_FOLDER: Path = _PATHS.weights
CHECKPOINTS_FOLDER: Path = _PATHS.checkpoints
DATASET_FOLDER: Path = _PATHS.dataset
REWARD_FOLDER: Path = _PATHS.reward
CREDENTIALS_FOLDER: Path = _PATHS.credentials
LOGS_FOLDER: Path = _PATHS.logs

# --- general -------------------------------------------------------------------------------------

RUN_NAME: str = TMRL_CONFIG["RUN_NAME"]
RESET_TRAINING: bool = TMRL_CONFIG["RESET_TRAINING"]
BUFFERS_MAXLEN: int = TMRL_CONFIG["BUFFERS_MAXLEN"]
RW_MAX_SAMPLES_PER_EPISODE: int = TMRL_CONFIG["RW_MAX_SAMPLES_PER_EPISODE"]
PRAGMA_RNN = False
CUDA_TRAINING: bool = TMRL_CONFIG["CUDA_TRAINING"]
CUDA_INFERENCE: bool = TMRL_CONFIG["CUDA_INFERENCE"]
PRAGMA_GAMEPAD: bool = TMRL_CONFIG["VIRTUAL_GAMEPAD"]
SEED: int | None = TMRL_CONFIG["SEED"]

LOCALHOST_WORKER: bool = TMRL_CONFIG["LOCALHOST_WORKER"]
LOCALHOST_TRAINER: bool = TMRL_CONFIG["LOCALHOST_TRAINER"]
PUBLIC_IP_SERVER: str = TMRL_CONFIG["PUBLIC_IP_SERVER"]
SERVER_IP_FOR_WORKER: str = _NET.server_ip_for_worker
SERVER_IP_FOR_TRAINER: str = _NET.server_ip_for_trainer

# --- environment ---------------------------------------------------------------------------------

ENV_CONFIG: dict[str, Any] = TMRL_CONFIG["ENV"]
RTGYM_INTERFACE: str = ENV_CONFIG["RTGYM_INTERFACE"]
SYSTEM: str = platform.system()
RTGYM_VERSION = "real-time-gym-ts-v1"
PRAGMA_PROGRESS: bool = RTGYM_INTERFACE.endswith("LIDARPROGRESS")
PRAGMA_LIDAR: bool = RTGYM_INTERFACE.endswith("LIDAR") or PRAGMA_PROGRESS
PRAGMA_TM2020_TMNF = True
LIDAR_BLACK_THRESHOLD = [55, 55, 55]
REWARD_CONFIG: dict[str, Any] = ENV_CONFIG["REWARD_CONFIG"]
REWARD_END_OF_TRACK: float = REWARD_CONFIG["END_OF_TRACK"]
CONSTANT_PENALTY: float = REWARD_CONFIG["CONSTANT_PENALTY"]
SLEEP_TIME_AT_RESET: float = ENV_CONFIG["SLEEP_TIME_AT_RESET"]
IMG_HIST_LEN: int = ENV_CONFIG["IMG_HIST_LEN"]
ACT_BUF_LEN: int = ENV_CONFIG["RTGYM_CONFIG"]["act_buf_len"]
WINDOW_WIDTH: int = ENV_CONFIG["WINDOW_WIDTH"]
WINDOW_HEIGHT: int = ENV_CONFIG["WINDOW_HEIGHT"]
GRAYSCALE: bool = ENV_CONFIG["IMG_GRAYSCALE"]
IMG_WIDTH: int = ENV_CONFIG["IMG_WIDTH"]
IMG_HEIGHT: int = ENV_CONFIG["IMG_HEIGHT"]
LINUX_X_OFFSET: int = ENV_CONFIG["LINUX_X_OFFSET"]
LINUX_Y_OFFSET: int = ENV_CONFIG["LINUX_Y_OFFSET"]
IMG_SCALE_CHECK_ENV: float = ENV_CONFIG["IMG_SCALE_CHECK_ENV"]
GYM_ID: str = ENV_CONFIG["GYM_ID"]
GYM_KWARGS: dict[str, Any] = ENV_CONFIG["GYM_KWARGS"]
SIM_FAST_MODE: bool = ENV_CONFIG["SIM_FAST_MODE"]

# --- algorithm -----------------------------------------------------------------------------------

ALG_CONFIG: dict[str, Any] = TMRL_CONFIG["ALG"]
ALG_NAME: str = ALG_CONFIG["ALGORITHM"]

# --- debugging and benchmarking ------------------------------------------------------------------

CRC_DEBUG = False
CRC_DEBUG_SAMPLES = 100
PROFILE_TRAINER = False
SYNCHRONIZE_CUDA = False
DEBUG_MODE: bool = TMRL_CONFIG["DEBUG_MODE"]

# --- files ---------------------------------------------------------------------------------------

MODEL_HISTORY: int = _NET.model_history
MODEL_PATH_WORKER: Path = _NET.model_path_worker
MODEL_PATH_SAVE_HISTORY: Path = _NET.model_path_save_history
MODEL_PATH_TRAINER: Path = _NET.model_path_trainer
CHECKPOINT_PATH: Path = _NET.checkpoint_path
DATASET_PATH: Path = _PATHS.dataset
REWARD_PATH: Path = _PATHS.reward_file

# --- wandb ---------------------------------------------------------------------------------------

WANDB_RUN_ID: str = _NET.wandb_run_id
WANDB_PROJECT: str = _NET.wandb_project
WANDB_ENTITY: str = _NET.wandb_entity
WANDB_KEY: str = _NET.wandb_key

# --- networking ----------------------------------------------------------------------------------

PRINT_BYTESIZES = True
PORT: int = _NET.port
LOCAL_PORT_SERVER: int = TMRL_CONFIG["LOCAL_PORT_SERVER"]
LOCAL_PORT_TRAINER: int = TMRL_CONFIG["LOCAL_PORT_TRAINER"]
LOCAL_PORT_WORKER: int = TMRL_CONFIG["LOCAL_PORT_WORKER"]
PASSWORD: str = _NET.password
SECURITY: str | None = _NET.security
CREDENTIALS_DIRECTORY: Path = _NET.credentials_directory
HOSTNAME: str = _NET.hostname
NB_WORKERS: int | None = _NET.max_workers
BUFFER_SIZE: int = TMRL_CONFIG["BUFFER_SIZE"]
HEADER_SIZE: int = _NET.header_size
ALLOW_PLAIN_TCP: bool = _NET.allow_plain_tcp
ALLOW_PICKLE: bool = _NET.allow_pickle
MAX_FRAME_BYTES: int = _NET.max_frame_bytes
SERVER_MEMORY_BYTES: int = _NET.server_memory_bytes
SERVER_PARTIAL_TIMEOUT: float = _NET.server_partial_timeout
