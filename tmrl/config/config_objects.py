"""Compatibility module: the objects of the original ``tmrl.config.config_objects``, built from the
configuration when imported (that is this module's documented job).

It reads the config through :mod:`tmrl.config.config_constants` and exposes the objects that
:func:`tmrl.assembly.assemble` builds from it (the same objects the roles of :mod:`tmrl.roles` run
with), partials (:func:`tmrl.util.partial`) under the original names:

- ``ENV_CLS``: the environment the workers run (and the trainer builds once to read its spaces)
- ``POLICY``: the actor class the workers run; ``TRAIN_MODEL``: the actor-critic trained
- ``MEMORY``: the replay memory (``MEM``: its class, without the config's arguments);
  ``AGENT``: the training agent; ``TRAINER``: the training loop
- ``SAMPLE_COMPRESSOR``, ``OBS_PREPROCESSOR``, ``SAMPLE_PREPROCESSOR``
- ``CONFIG_DICT`` (the real-time configuration, for real-time interfaces), ``INT`` (the interface),
  ``ALG_CONFIG``, ``ALG_NAME``, ``DUMP_RUN_INSTANCE_FN``, ``LOAD_RUN_INSTANCE_FN``, ``UPDATER_FN``,
  ``CONFIG_DICT_MODIFIERS`` (``ENV.RTGYM_CONFIG`` as written in ``config.json``)

Values of ``ENV.RTGYM_INTERFACE``:

- ``"GYM"``: any Gymnasium environment named by ``ENV.GYM_ID``;
- ``"DRONE"``: the real-time simulated drone of :mod:`tmrl.realtime`;
- ``"SIMLIDAR"``, ``"SIMLIDARPROGRESS"``, ``"SIMFULL"``: the built-in simulated track
  (:mod:`tmrl.sim`), stepped as fast as the CPU allows when ``ENV.SIM_FAST_MODE`` is true (the
  default), in real time through :mod:`tmrl.realtime` otherwise;
- ``"TM20FULL"``, ``"TM20LIDAR"``, ``"TM20LIDARPROGRESS"``: TrackMania 2020 (:mod:`tmrl.tm`).
  Importing this module touches no game and imports none of the game's packages (mss,
  vgamepad, cv2): the game is reached at the environment's first reset.

The simulator and TrackMania share their observations, hence their preprocessor, sample
compressor, replay memory and models (:func:`tmrl.sim.interfaces.pipeline_parts`). New code should call
:func:`tmrl.assembly.assemble` on a loaded config instead.

Raises (at import):
    tmrl.config.loader.ConfigError: the configuration is invalid (including an unknown key in
        ``ENV.RTGYM_CONFIG.interface_kwargs``).
    tmrl.errors.UserError: a module the configured interface needs is not available.
"""

from __future__ import annotations

# The original module's namespace held these names too: kept for scripts that reach them here.
import importlib  # noqa: F401
import inspect  # noqa: F401
from collections.abc import Callable, Iterable  # noqa: F401
from typing import Any

import tmrl.config.config_constants as cfg
from tmrl.assembly import DropActionBuffer, check_interface_kwargs  # noqa: F401
from tmrl.assembly import assemble as _assemble
from tmrl.config.schema import AGENT_CLASSES, ConfigError, arguments  # noqa: F401
from tmrl.errors import UserError  # noqa: F401
from tmrl.util import partial  # noqa: F401

__all__ = [
    "AGENT",
    "ALG_CONFIG",
    "ALG_NAME",
    "CONFIG_DICT",
    "CONFIG_DICT_MODIFIERS",
    "DEVICE_INFERENCE",
    "DEVICE_TRAINING",
    "DUMP_RUN_INSTANCE_FN",
    "ENV_CLS",
    "INT",
    "LOAD_RUN_INSTANCE_FN",
    "MEM",
    "MEMORY",
    "OBS_PREPROCESSOR",
    "POLICY",
    "SAMPLE_COMPRESSOR",
    "SAMPLE_PREPROCESSOR",
    "TRAINER",
    "TRAIN_MODEL",
    "UPDATER_FN",
]

_OBJECTS = _assemble(cfg.TMRL_CONFIG)

ALG_CONFIG: dict[str, Any] = cfg.ALG_CONFIG
ALG_NAME: str = cfg.ALG_NAME
DEVICE_TRAINING: str = _OBJECTS.DEVICE_TRAINING
DEVICE_INFERENCE: str = _OBJECTS.DEVICE_INFERENCE

# --- environment, models, compression, memory ----------------------------------------------------

INT: Any = _OBJECTS.INT
CONFIG_DICT: dict[str, Any] | None = _OBJECTS.CONFIG_DICT
ENV_CLS: Any = _OBJECTS.ENV_CLS
POLICY: Any = _OBJECTS.POLICY
TRAIN_MODEL: Any = _OBJECTS.TRAIN_MODEL
OBS_PREPROCESSOR: Any = _OBJECTS.OBS_PREPROCESSOR
SAMPLE_COMPRESSOR: Any = _OBJECTS.SAMPLE_COMPRESSOR
SAMPLE_PREPROCESSOR: Any = _OBJECTS.SAMPLE_PREPROCESSOR
MEMORY: Any = _OBJECTS.MEMORY
#: The memory class (tmrl 0.7's ``MEM``): the competition template builds its own partial of it.
MEM: Any = _OBJECTS.MEM
CONFIG_DICT_MODIFIERS: dict[str, Any] = _OBJECTS.CONFIG_DICT_MODIFIERS

# --- algorithm and training loop -----------------------------------------------------------------

AGENT: Any = _OBJECTS.AGENT
TRAINER: Any = _OBJECTS.TRAINER

# --- checkpoints (the original's hooks; none are needed by the built-in pipelines) ---------------

DUMP_RUN_INSTANCE_FN: Any = _OBJECTS.DUMP_RUN_INSTANCE_FN
LOAD_RUN_INSTANCE_FN: Any = _OBJECTS.LOAD_RUN_INSTANCE_FN
UPDATER_FN: Any = _OBJECTS.UPDATER_FN
