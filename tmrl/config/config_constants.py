"""Compatibility module: the constants of the original ``tmrl.config.config_constants``.

Its documented job is to read the configuration when imported: it loads it
(:func:`tmrl.config.loader.process_config`: ``config.json`` of the data folder, or the defaults
when that file does not exist yet, plus ``$TMRL_CONFIG_OVERRIDE``; the roles of :mod:`tmrl.roles`
run with the same one) and exposes the values of :func:`tmrl.config.constants.constants` under the
original names. Unlike the original it creates no folder, downloads nothing, sets no environment
variable and configures no logging; paths are :class:`pathlib.Path` objects.

New code should call :func:`~tmrl.config.loader.load_config` and pass the dict around, or hand
:class:`tmrl.config.settings.NetSettings` to the roles, instead. The networking values below are
taken from :class:`~tmrl.config.settings.NetSettings`, where they are derived once.

Raises (at import):
    tmrl.config.loader.ConfigError: the configuration is invalid (one line naming the key).
"""

from __future__ import annotations

import platform  # noqa: F401 (the original module's namespace held it)
from pathlib import Path
from typing import Any

from tmrl.config.constants import constants as _constants
from tmrl.config.loader import data_paths, load_config  # noqa: F401 (as above)
from tmrl.config.loader import process_config as _process_config
from tmrl.config.settings import NetSettings  # noqa: F401 (as above)

__compatibility__ = "0.6.0"

# Read again at every import of this module (its documented job); the roles run with this one too.
TMRL_CONFIG: dict[str, Any] = _process_config(reload=True)
_C = _constants(TMRL_CONFIG)
CONFIG_VERSION: str = _C.CONFIG_VERSION

# --- data folder ---------------------------------------------------------------------------------

TMRL_FOLDER: Path = _C.TMRL_FOLDER
PATH_DATA: Path = _C.PATH_DATA
CONFIG_FOLDER: Path = _C.CONFIG_FOLDER
CONFIG_FILE: Path = _C.CONFIG_FILE
WEIGHTS_FOLDER: Path = _C.WEIGHTS_FOLDER
CHECKPOINTS_FOLDER: Path = _C.CHECKPOINTS_FOLDER
DATASET_FOLDER: Path = _C.DATASET_FOLDER
REWARD_FOLDER: Path = _C.REWARD_FOLDER
CREDENTIALS_FOLDER: Path = _C.CREDENTIALS_FOLDER
LOGS_FOLDER: Path = _C.LOGS_FOLDER

# --- general -------------------------------------------------------------------------------------

RUN_NAME: str = _C.RUN_NAME
RESET_TRAINING: bool = _C.RESET_TRAINING
BUFFERS_MAXLEN: int = _C.BUFFERS_MAXLEN
RW_MAX_SAMPLES_PER_EPISODE: int = _C.RW_MAX_SAMPLES_PER_EPISODE
PRAGMA_RNN = _C.PRAGMA_RNN
CUDA_TRAINING: bool = _C.CUDA_TRAINING
CUDA_INFERENCE: bool = _C.CUDA_INFERENCE
PRAGMA_GAMEPAD: bool = _C.PRAGMA_GAMEPAD
SEED: int | None = _C.SEED

LOCALHOST_WORKER: bool = _C.LOCALHOST_WORKER
LOCALHOST_TRAINER: bool = _C.LOCALHOST_TRAINER
PUBLIC_IP_SERVER: str = _C.PUBLIC_IP_SERVER
SERVER_IP_FOR_WORKER: str = _C.SERVER_IP_FOR_WORKER
SERVER_IP_FOR_TRAINER: str = _C.SERVER_IP_FOR_TRAINER

# --- environment ---------------------------------------------------------------------------------

ENV_CONFIG: dict[str, Any] = _C.ENV_CONFIG
RTGYM_INTERFACE: str = _C.RTGYM_INTERFACE
SYSTEM: str = _C.SYSTEM
RTGYM_VERSION = _C.RTGYM_VERSION
PRAGMA_PROGRESS: bool = _C.PRAGMA_PROGRESS
PRAGMA_LIDAR: bool = _C.PRAGMA_LIDAR
PRAGMA_TM2020_TMNF = _C.PRAGMA_TM2020_TMNF
LIDAR_BLACK_THRESHOLD = _C.LIDAR_BLACK_THRESHOLD
REWARD_CONFIG: dict[str, Any] = _C.REWARD_CONFIG
REWARD_END_OF_TRACK: float = _C.REWARD_END_OF_TRACK
CONSTANT_PENALTY: float = _C.CONSTANT_PENALTY
SLEEP_TIME_AT_RESET: float = _C.SLEEP_TIME_AT_RESET
IMG_HIST_LEN: int = _C.IMG_HIST_LEN
ACT_BUF_LEN: int = _C.ACT_BUF_LEN
WINDOW_WIDTH: int = _C.WINDOW_WIDTH
WINDOW_HEIGHT: int = _C.WINDOW_HEIGHT
GRAYSCALE: bool = _C.GRAYSCALE
IMG_WIDTH: int = _C.IMG_WIDTH
IMG_HEIGHT: int = _C.IMG_HEIGHT
LINUX_X_OFFSET: int = _C.LINUX_X_OFFSET
LINUX_Y_OFFSET: int = _C.LINUX_Y_OFFSET
IMG_SCALE_CHECK_ENV: float = _C.IMG_SCALE_CHECK_ENV
GYM_ID: str = _C.GYM_ID
GYM_KWARGS: dict[str, Any] = _C.GYM_KWARGS
SIM_FAST_MODE: bool = _C.SIM_FAST_MODE

# --- algorithm -----------------------------------------------------------------------------------

ALG_CONFIG: dict[str, Any] = _C.ALG_CONFIG
ALG_NAME: str = _C.ALG_NAME

# --- debugging and benchmarking ------------------------------------------------------------------

CRC_DEBUG = _C.CRC_DEBUG
CRC_DEBUG_SAMPLES = _C.CRC_DEBUG_SAMPLES
PROFILE_TRAINER = _C.PROFILE_TRAINER
SYNCHRONIZE_CUDA = _C.SYNCHRONIZE_CUDA
DEBUG_MODE: bool = _C.DEBUG_MODE

# --- files ---------------------------------------------------------------------------------------

MODEL_HISTORY: int = _C.MODEL_HISTORY
MODEL_PATH_WORKER: Path = _C.MODEL_PATH_WORKER
MODEL_PATH_SAVE_HISTORY: Path = _C.MODEL_PATH_SAVE_HISTORY
MODEL_PATH_TRAINER: Path = _C.MODEL_PATH_TRAINER
CHECKPOINT_PATH: Path = _C.CHECKPOINT_PATH
DATASET_PATH: Path = _C.DATASET_PATH
REWARD_PATH: Path = _C.REWARD_PATH

# --- wandb ---------------------------------------------------------------------------------------

WANDB_RUN_ID: str = _C.WANDB_RUN_ID
WANDB_PROJECT: str = _C.WANDB_PROJECT
WANDB_ENTITY: str = _C.WANDB_ENTITY
WANDB_KEY: str = _C.WANDB_KEY

# --- networking ----------------------------------------------------------------------------------

PRINT_BYTESIZES = _C.PRINT_BYTESIZES
PORT: int = _C.PORT
LOCAL_PORT_SERVER: int = _C.LOCAL_PORT_SERVER
LOCAL_PORT_TRAINER: int = _C.LOCAL_PORT_TRAINER
LOCAL_PORT_WORKER: int = _C.LOCAL_PORT_WORKER
PASSWORD: str = _C.PASSWORD
SECURITY: str | None = _C.SECURITY
CREDENTIALS_DIRECTORY: Path = _C.CREDENTIALS_DIRECTORY
HOSTNAME: str = _C.HOSTNAME
NB_WORKERS: int | None = _C.NB_WORKERS
BUFFER_SIZE: int = _C.BUFFER_SIZE
HEADER_SIZE: int = _C.HEADER_SIZE
ALLOW_PLAIN_TCP: bool = _C.ALLOW_PLAIN_TCP
ALLOW_PICKLE: bool = _C.ALLOW_PICKLE
MAX_FRAME_BYTES: int = _C.MAX_FRAME_BYTES
SERVER_MEMORY_BYTES: int = _C.SERVER_MEMORY_BYTES
SERVER_PARTIAL_TIMEOUT: float = _C.SERVER_PARTIAL_TIMEOUT
