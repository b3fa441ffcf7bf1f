"""Compatibility module: the objects of the original ``tmrl.config.config_objects``, built from the
configuration when imported (that is this module's documented job).

It reads the config through :mod:`tmrl.config.config_constants` and exposes partials
(:func:`tmrl.util.partial`) under the original names:

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
compressor, replay memory and models (:func:`tmrl.sim.interfaces.pipeline_parts`).

Raises (at import):
    tmrl.config.loader.ConfigError: the configuration is invalid (including an unknown key in
        ``ENV.RTGYM_CONFIG.interface_kwargs``).
    tmrl.errors.UserError: a module the configured interface needs is not available.
"""

from __future__ import annotations

import importlib
import inspect
from collections.abc import Callable, Iterable
from typing import Any

import tmrl.config.config_constants as cfg
from tmrl.config.schema import AGENT_CLASSES, ConfigError, arguments
from tmrl.errors import UserError
from tmrl.util import partial

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

_SIM = ("SIMLIDAR", "SIMLIDARPROGRESS", "SIMFULL")
_TM = ("TM20FULL", "TM20LIDAR", "TM20LIDARPROGRESS")
_SUPPORTED = ("GYM", "DRONE", *_SIM, *_TM)
_IMAGE = ("SIMFULL", "TM20FULL")


def _module(name: str) -> Any:
    """Import a tmrl module; a tmrl module that does not exist becomes a one-line UserError
    (other import errors, such as a missing third-party package, keep their own message)."""
    try:
        return importlib.import_module(name)
    except ModuleNotFoundError as e:
        missing = e.name or ""
        if missing.startswith("tmrl") and (name == missing or name.startswith(missing + ".")):
            raise UserError(
                f"ENV.RTGYM_INTERFACE {cfg.RTGYM_INTERFACE!r} needs {name}, which is not available in "
                f"this installation of tmrl; reinstall tmrl or use one of {', '.join(_SUPPORTED)}"
            ) from None
        raise


def _attr(module: str, name: str) -> Any:
    mod = _module(module)
    try:
        return getattr(mod, name)
    except AttributeError:
        raise UserError(
            f"{module}.{name} is not available in this installation of tmrl "
            f"(needed by ENV.RTGYM_INTERFACE {cfg.RTGYM_INTERFACE!r})"
        ) from None


if cfg.RTGYM_INTERFACE not in _SUPPORTED:  # the schema refuses other values: only a stale module gets here
    raise UserError(
        f"ENV.RTGYM_INTERFACE {cfg.RTGYM_INTERFACE!r} is not supported by tmrl.config.config_objects; "
        f"use one of {', '.join(_SUPPORTED)}"
    )


def _named_parameters(func: Callable[..., Any]) -> tuple[set[str], bool]:
    """Keyword-passable parameter names of ``func`` and whether it also takes ``**kwargs``."""
    params = inspect.signature(func).parameters.values()
    names = {p.name for p in params
             if p.kind in (p.POSITIONAL_OR_KEYWORD, p.KEYWORD_ONLY) and p.name != "self"}
    return names, any(p.kind is p.VAR_KEYWORD for p in params)


def _init_keywords(cls: type) -> set[str]:
    """Keywords ``cls(...)`` accepts, following ``**kwargs`` handed up the class hierarchy."""
    names: set[str] = set()
    for klass in cls.__mro__:
        if "__init__" not in vars(klass) or klass is object:
            continue
        own, more = _named_parameters(vars(klass)["__init__"])
        names |= own
        if not more:
            break
    return names


def check_interface_kwargs(kwargs: Iterable[str], allowed: Iterable[str], interface: str) -> None:
    """Refuse a key of ``ENV.RTGYM_CONFIG.interface_kwargs`` that the interface does not take.

    Args:
        kwargs: the keys given.
        allowed: the keys the interface takes.
        interface: the ``RTGYM_INTERFACE`` value, for the message.

    Raises:
        ConfigError: one line naming the first unknown key and the accepted ones.
    """
    allowed = set(allowed)
    unknown = sorted(set(kwargs) - allowed)
    if unknown:
        raise ConfigError(
            f"ENV.RTGYM_CONFIG.interface_kwargs.{unknown[0]} is not an argument of the {interface} interface; "
            f"remove it or use one of {', '.join(sorted(allowed))}"
        )


class DropActionBuffer:
    """Sample compressor for real-time environments: removes the action buffer (the last
    ``act_buf_len`` elements of the observation tuple) before a sample is sent, since the replay
    memory rebuilds it from the stored actions (see ``RealTimeTorchMemory``)."""

    def __init__(self, act_buf_len: int):
        self.act_buf_len = int(act_buf_len)

    def __call__(self, prev_act: Any, obs: Any, rew: Any, terminated: Any, truncated: Any,
                 info: Any) -> tuple:
        obs = tuple(obs)[: len(obs) - self.act_buf_len] if self.act_buf_len else obs
        return prev_act, obs, rew, terminated, truncated, info

    def __repr__(self) -> str:
        return f"DropActionBuffer(act_buf_len={self.act_buf_len})"


def _device(cuda: bool) -> str:
    if not cuda:
        return "cpu"
    import torch

    return "cuda" if torch.cuda.is_available() else "cpu"


def _no_limit(rt: dict[str, Any]) -> dict[str, Any]:
    if rt.get("ep_max_length") is None:
        rt["ep_max_length"] = float("inf")  # the real-time env's "no limit"
    return rt


ALG_CONFIG: dict[str, Any] = cfg.ALG_CONFIG
ALG_NAME: str = cfg.ALG_NAME
DEVICE_TRAINING: str = _device(cfg.CUDA_TRAINING)
DEVICE_INFERENCE: str = _device(cfg.CUDA_INFERENCE)

_rtgym: dict[str, Any] = cfg.ENV_CONFIG["RTGYM_CONFIG"]
_GenericGymEnv = _attr("tmrl.envs", "GenericGymEnv")
_memory_common: dict[str, Any] = arguments(cfg.TMRL_CONFIG, "GenericTorchMemory")

INT: Any = None
CONFIG_DICT: dict[str, Any] | None = None
OBS_PREPROCESSOR: Any = None
SAMPLE_COMPRESSOR: Any = None
SAMPLE_PREPROCESSOR: Any = None

# --- environment, models, compression, memory ----------------------------------------------------

def _mlp_model(alg: str) -> Any:
    """The actor-critic class of an algorithm for flat (MLP) observations: its agent's default
    ``model_cls`` (the registry, :data:`tmrl.algorithms.ALGORITHMS`, names the agent)."""
    agent = _attr("tmrl.algorithms", "agent_class")(alg)
    return inspect.signature(agent).parameters["model_cls"].default


if cfg.RTGYM_INTERFACE == "GYM":
    ENV_CLS = partial(_GenericGymEnv, id=cfg.GYM_ID, gym_kwargs=dict(cfg.GYM_KWARGS))
    POLICY = _attr("tmrl.models", "SquashedGaussianMLPActor")
    TRAIN_MODEL = _mlp_model(ALG_NAME)
    MEMORY = partial(_attr("tmrl.memory", "GenericTorchMemory"), **_memory_common)

elif cfg.RTGYM_INTERFACE == "DRONE":
    _drone_cls = _attr("tmrl.realtime", "DroneInterface")
    # Files written for the original carry TrackMania's "save_replays", which the drone does not take.
    _drone_kwargs = {k: v for k, v in _rtgym["interface_kwargs"].items() if k != "save_replays"}
    # The drone interface hands the keywords it does not name to its DummyRCDrone.
    check_interface_kwargs(
        _drone_kwargs,
        _init_keywords(_drone_cls) | _init_keywords(_attr("tmrl.realtime", "DummyRCDrone")),
        "DRONE",
    )
    if len(_rtgym["interface_args"]) > 2:
        raise ConfigError(
            "ENV.RTGYM_CONFIG.interface_args has more than 2 values: the DRONE interface takes at most "
            "success_distance and speed_factor (prefer interface_kwargs)"
        )
    INT = partial(_drone_cls)
    CONFIG_DICT = dict(_attr("tmrl.realtime", "DEFAULT_CONFIG_DICT"))
    CONFIG_DICT.update({k: v for k, v in _rtgym.items() if k not in ("interface_args", "interface_kwargs")})
    CONFIG_DICT["interface_args"] = tuple(_rtgym["interface_args"])
    CONFIG_DICT["interface_kwargs"] = _drone_kwargs
    CONFIG_DICT["interface"] = INT
    _no_limit(CONFIG_DICT)
    ENV_CLS = partial(_GenericGymEnv, id=cfg.RTGYM_VERSION, gym_kwargs={"config": CONFIG_DICT})
    POLICY = _attr("tmrl.models", "SquashedGaussianMLPActor")
    TRAIN_MODEL = _mlp_model(ALG_NAME)
    if _rtgym["act_in_obs"]:
        SAMPLE_COMPRESSOR = DropActionBuffer(cfg.ACT_BUF_LEN)
        MEMORY = partial(_attr("tmrl.memory", "RealTimeTorchMemory"), act_buf_len=cfg.ACT_BUF_LEN,
                         **_memory_common)
    else:  # no action buffer in the observations: nothing to drop or rebuild
        MEMORY = partial(_attr("tmrl.memory", "GenericTorchMemory"), **_memory_common)

else:  # the driving interfaces: simulator (SIM*) and TrackMania (TM20*) share their pipeline
    _parts = _attr("tmrl.sim.interfaces", "pipeline_parts")(cfg.RTGYM_INTERFACE)
    if cfg.RTGYM_INTERFACE in _SIM:
        _sim = _module("tmrl.sim.interfaces")
        try:
            _sim_kwargs = _sim.interface_kwargs(cfg.TMRL_CONFIG)
        except ConfigError:
            raise
        except UserError as e:  # an unknown interface keyword: a configuration mistake
            raise ConfigError(str(e)) from None
        _sim_cls = _sim.interface_class(cfg.RTGYM_INTERFACE)
        INT = partial(_sim_cls, **_sim_kwargs)
        CONFIG_DICT = _no_limit(_sim.realtime_config(cfg.TMRL_CONFIG))
        if cfg.SIM_FAST_MODE:
            _max_len = _rtgym["ep_max_length"]
            ENV_CLS = partial(
                _sim.SimEnv,
                interface=cfg.RTGYM_INTERFACE,
                time_step_duration=_rtgym["time_step_duration"],
                ep_max_length=10**9 if _max_len is None else _max_len,
                act_buf_len=cfg.ACT_BUF_LEN,
                **_sim_kwargs,
            )
        else:
            ENV_CLS = partial(_GenericGymEnv, id=cfg.RTGYM_VERSION, gym_kwargs={"config": CONFIG_DICT})
    else:
        _tm = _module("tmrl.tm.interfaces")
        CONFIG_DICT = _no_limit(_tm.realtime_config(cfg.TMRL_CONFIG))
        _tm_cls = CONFIG_DICT["interface"]
        check_interface_kwargs(CONFIG_DICT["interface_kwargs"], _init_keywords(_tm_cls), cfg.RTGYM_INTERFACE)
        INT = partial(_tm_cls, **CONFIG_DICT["interface_kwargs"])
        ENV_CLS = partial(_GenericGymEnv, id=cfg.RTGYM_VERSION, gym_kwargs={"config": CONFIG_DICT})
    OBS_PREPROCESSOR = _parts["obs_preprocessor"]
    SAMPLE_COMPRESSOR = _parts["sample_compressor"]
    POLICY = _parts["actor_cls"]
    if ALG_NAME in ("SAC", "REDQSAC"):
        TRAIN_MODEL = _parts["model_cls"]  # REDQ passes its number of critics (n) itself
    elif cfg.RTGYM_INTERFACE in _IMAGE:
        # Their critics (dropout, quantile, batch-normalised) exist as MLPs only: none reads images.
        raise ConfigError(
            f"ALG.ALGORITHM {ALG_NAME} has no image model, so it does not run with ENV.RTGYM_INTERFACE "
            f"{cfg.RTGYM_INTERFACE}: use a lidar interface ({', '.join(i for i in (*_SIM, *_TM) if i not in _IMAGE)}) "
            "or ALG.ALGORITHM SAC or REDQSAC"
        )
    else:
        # The algorithm's MLP actor-critic with the lidar scaling; its actor is the workers' LidarActor.
        TRAIN_MODEL = _attr("tmrl.driving.models", "lidar_model_cls")(ALG_NAME)
    MEMORY = partial(
        _parts["memory_cls"],
        hist_len=cfg.IMG_HIST_LEN,
        act_buf_len=cfg.ACT_BUF_LEN,
        crc_debug=cfg.CRC_DEBUG,
        **_memory_common,
    )

#: The memory class (tmrl 0.7's ``MEM``): the competition template builds its own partial of it.
MEM: Any = MEMORY.func
CONFIG_DICT_MODIFIERS: dict[str, Any] = dict(_rtgym)

# --- algorithm -----------------------------------------------------------------------------------

# Every ALG key reaches its agent argument by the settings table (tmrl/config/schema.py, ``feeds``).
_agent_name = AGENT_CLASSES[ALG_NAME]
AGENT = partial(_attr("tmrl.algorithms", "agent_class")(ALG_NAME), model_cls=TRAIN_MODEL,
                **arguments(cfg.TMRL_CONFIG, _agent_name))

# --- training loop -------------------------------------------------------------------------------

TRAINER = partial(
    _attr("tmrl.training_offline", "TorchTrainingOffline"),
    env_cls=ENV_CLS,
    memory_cls=MEMORY,
    training_agent_cls=AGENT,
    device=DEVICE_TRAINING,
    **arguments(cfg.TMRL_CONFIG, "TorchTrainingOffline"),
)

# --- checkpoints (the original's hooks; none are needed by the built-in pipelines) ---------------

DUMP_RUN_INSTANCE_FN = None
LOAD_RUN_INSTANCE_FN = None
UPDATER_FN = None
