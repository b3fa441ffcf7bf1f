"""The objects a configuration describes: the environment, the models, the replay memory, the
training agent and loop, the sample compressor and preprocessor.

:func:`assemble` builds them from a loaded config as partials (:func:`tmrl.util.partial`) and
classes, under the names of the original ``tmrl.config.config_objects`` (``ENV_CLS``, ``POLICY``,
``TRAIN_MODEL``, ``MEMORY``, ``AGENT``, ``TRAINER``, ...). The roles (:mod:`tmrl.roles`) and the
compatibility module :mod:`tmrl.config.config_objects` both take their objects from here; built
once per process and configuration, they hand out the same objects.

Values of ``ENV.RTGYM_INTERFACE``:

- ``"GYM"``: any Gymnasium environment named by ``ENV.GYM_ID``;
- ``"DRONE"``: the real-time simulated drone of :mod:`tmrl.realtime`;
- ``"SIMLIDAR"``, ``"SIMLIDARPROGRESS"``, ``"SIMFULL"``: the built-in simulated track
  (:mod:`tmrl.sim`), stepped as fast as the CPU allows when ``ENV.SIM_FAST_MODE`` is true (the
  default), in real time through :mod:`tmrl.realtime` otherwise;
- ``"TM20FULL"``, ``"TM20LIDAR"``, ``"TM20LIDARPROGRESS"``: TrackMania 2020 (:mod:`tmrl.tm`).
  Assembling touches no game and imports none of the game's packages (mss, vgamepad, cv2): the
  game is reached at the environment's first reset.

The simulator and TrackMania share their observations, hence their preprocessor, sample
compressor, replay memory and models (:func:`tmrl.sim.interfaces.pipeline_parts`); ``ALG.ALGORITHM``
``"DRQ"`` (image interfaces only) keeps the frames uint8 from the worker to the model
(:mod:`tmrl.algorithms.drq`). Importing this
module reads nothing and imports none of the modules the objects come from.
"""

from __future__ import annotations

import copy
import importlib
import inspect
import json
import threading
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass
from typing import Any

from tmrl.config.constants import RTGYM_VERSION
from tmrl.config.schema import AGENT_CLASSES, ConfigError, arguments
from tmrl.errors import UserError
from tmrl.util import partial

__all__ = ["Assembly", "DropActionBuffer", "actor_for", "assemble", "check_interface_kwargs"]


_SIM = ("SIMLIDAR", "SIMLIDARPROGRESS", "SIMFULL")
_TM = ("TM20FULL", "TM20LIDAR", "TM20LIDARPROGRESS")
_SUPPORTED = ("GYM", "DRONE", *_SIM, *_TM)
_IMAGE = ("SIMFULL", "TM20FULL")


@dataclass(frozen=True)
class Assembly:
    """The objects of one configuration, under the original ``config_objects`` names.

    Attributes:
        ENV_CLS: the environment the workers run (and the trainer builds once to read its spaces).
        POLICY: the actor class the workers run.
        TRAIN_MODEL: the actor-critic class trained.
        MEMORY: the replay memory, a partial with the config's arguments.
        MEM: the memory class (``MEMORY.func``).
        AGENT: the training agent, a partial.
        TRAINER: the training loop, a partial (``TorchTrainingOffline``).
        SAMPLE_COMPRESSOR: what a worker applies to a sample before sending it (None: nothing).
        OBS_PREPROCESSOR: what the worker and the memory apply to observations (None: nothing).
        SAMPLE_PREPROCESSOR: the original's sample preprocessor (None in every pipeline).
        INT: the real-time interface, a partial (None for ``GYM``).
        CONFIG_DICT: the real-time configuration (None for ``GYM``).
        CONFIG_DICT_MODIFIERS: ``ENV.RTGYM_CONFIG`` as written in ``config.json`` (a copy).
        ALG_CONFIG: the ``ALG`` section.
        ALG_NAME: ``ALG.ALGORITHM``.
        DEVICE_TRAINING: ``"cuda"`` when ``CUDA_TRAINING`` and PyTorch sees a GPU, else ``"cpu"``.
        DEVICE_INFERENCE: the same for ``CUDA_INFERENCE``.
        DUMP_RUN_INSTANCE_FN: the original's checkpoint hook (None: the built-in one).
        LOAD_RUN_INSTANCE_FN: the original's checkpoint hook (None: the built-in one).
        UPDATER_FN: the original's checkpoint hook (None: none).
    """

    ENV_CLS: Any
    POLICY: Any
    TRAIN_MODEL: Any
    MEMORY: Any
    MEM: Any
    AGENT: Any
    TRAINER: Any
    SAMPLE_COMPRESSOR: Any
    OBS_PREPROCESSOR: Any
    SAMPLE_PREPROCESSOR: Any
    INT: Any
    CONFIG_DICT: dict[str, Any] | None
    CONFIG_DICT_MODIFIERS: dict[str, Any]
    ALG_CONFIG: dict[str, Any]
    ALG_NAME: str
    DEVICE_TRAINING: str
    DEVICE_INFERENCE: str
    DUMP_RUN_INSTANCE_FN: Any = None
    LOAD_RUN_INSTANCE_FN: Any = None
    UPDATER_FN: Any = None


_CACHE: dict[str, Assembly] = {}
_LOCK = threading.Lock()


def assemble(cfg: Mapping[str, Any]) -> Assembly:
    """The objects of ``cfg``, built on the first call for a configuration and the same
    :class:`Assembly` on every later call with an equal configuration (in this process).

    Args:
        cfg: a complete, validated config (:func:`tmrl.config.loader.load_config`); it is copied,
            so changing it afterwards changes none of the objects.

    Raises:
        tmrl.config.loader.ConfigError: the configuration does not fit the interface (an unknown
            key in ``ENV.RTGYM_CONFIG.interface_kwargs``, an algorithm without image model on an
            image interface, DrQ on an interface without images); one line.
        tmrl.errors.UserError: a module the configured interface needs is not available.
    """
    key = json.dumps(cfg, sort_keys=True, default=repr)
    with _LOCK:
        built = _CACHE.get(key)
        if built is None:
            built = _CACHE[key] = _build(copy.deepcopy(dict(cfg)))
        return built


def actor_for(env_cls: Callable[[], Any], policy: Callable[..., Any]) -> Any:
    """A fresh ``policy`` actor on the spaces of the environment ``env_cls`` builds (it is built
    to read them, then closed; a TrackMania environment touches no game until its first reset).

    Args:
        env_cls: what builds the environment (an :class:`Assembly`'s ``ENV_CLS``).
        policy: the actor class (an :class:`Assembly`'s ``POLICY``).
    """
    env = env_cls()
    try:
        obs_space, act_space = env.observation_space, env.action_space
    finally:
        close = getattr(env, "close", None)
        if callable(close):
            close()
    return policy(observation_space=obs_space, action_space=act_space)


# --- helpers -------------------------------------------------------------------------------------


def _module(name: str, interface: str) -> Any:
    """Import a tmrl module; a tmrl module that does not exist becomes a one-line UserError
    (other import errors, such as a missing third-party package, keep their own message)."""
    try:
        return importlib.import_module(name)
    except ModuleNotFoundError as e:
        missing = e.name or ""
        if missing.startswith("tmrl") and (name == missing or name.startswith(missing + ".")):
            raise UserError(
                f"ENV.RTGYM_INTERFACE {interface!r} needs {name}, which is not available in "
                f"this installation of tmrl; reinstall tmrl or use one of {', '.join(_SUPPORTED)}"
            ) from None
        raise


def _attr(module: str, name: str, interface: str) -> Any:
    mod = _module(module, interface)
    try:
        return getattr(mod, name)
    except AttributeError:
        raise UserError(
            f"{module}.{name} is not available in this installation of tmrl "
            f"(needed by ENV.RTGYM_INTERFACE {interface!r})"
        ) from None


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


def _mlp_model(alg: str, interface: str) -> Any:
    """The actor-critic class of an algorithm for flat (MLP) observations: its agent's default
    ``model_cls`` (the registry, :data:`tmrl.algorithms.ALGORITHMS`, names the agent)."""
    agent = _attr("tmrl.algorithms", "agent_class", interface)(alg)
    return inspect.signature(agent).parameters["model_cls"].default


# --- the objects ---------------------------------------------------------------------------------


def _build(cfg: dict[str, Any]) -> Assembly:
    env = cfg["ENV"]
    interface: str = env["RTGYM_INTERFACE"]
    if interface not in _SUPPORTED:  # the schema refuses other values: only a stale module gets here
        raise UserError(
            f"ENV.RTGYM_INTERFACE {interface!r} is not supported by tmrl.assembly; "
            f"use one of {', '.join(_SUPPORTED)}"
        )
    alg_name: str = cfg["ALG"]["ALGORITHM"]
    if alg_name == "DRQ" and interface not in _IMAGE:
        raise ConfigError(
            f'ALG.ALGORITHM "DRQ" learns from images, and ENV.RTGYM_INTERFACE {interface} gives none: use '
            f"{' or '.join(_IMAGE)}, or another ALG.ALGORITHM"
        )
    rtgym: dict[str, Any] = env["RTGYM_CONFIG"]
    act_buf_len: int = rtgym["act_buf_len"]
    generic_gym_env = _attr("tmrl.envs", "GenericGymEnv", interface)
    memory_common: dict[str, Any] = arguments(cfg, "GenericTorchMemory")
    parts: dict[str, Any] = {"INT": None, "CONFIG_DICT": None, "OBS_PREPROCESSOR": None,
                             "SAMPLE_COMPRESSOR": None, "SAMPLE_PREPROCESSOR": None}

    if interface == "GYM":
        parts["ENV_CLS"] = partial(generic_gym_env, id=env["GYM_ID"], gym_kwargs=dict(env["GYM_KWARGS"]))
        parts["POLICY"] = _attr("tmrl.models", "SquashedGaussianMLPActor", interface)
        parts["TRAIN_MODEL"] = _mlp_model(alg_name, interface)
        parts["MEMORY"] = partial(_attr("tmrl.memory", "GenericTorchMemory", interface), **memory_common)

    elif interface == "DRONE":
        drone_cls = _attr("tmrl.realtime", "DroneInterface", interface)
        # Files written for the original carry TrackMania's "save_replays", which the drone does not take.
        drone_kwargs = {k: v for k, v in rtgym["interface_kwargs"].items() if k != "save_replays"}
        # The drone interface hands the keywords it does not name to its DummyRCDrone.
        check_interface_kwargs(
            drone_kwargs,
            _init_keywords(drone_cls) | _init_keywords(_attr("tmrl.realtime", "DummyRCDrone", interface)),
            "DRONE",
        )
        if len(rtgym["interface_args"]) > 2:
            raise ConfigError(
                "ENV.RTGYM_CONFIG.interface_args has more than 2 values: the DRONE interface takes at most "
                "success_distance and speed_factor (prefer interface_kwargs)"
            )
        parts["INT"] = partial(drone_cls)
        config_dict = dict(_attr("tmrl.realtime", "DEFAULT_CONFIG_DICT", interface))
        config_dict.update({k: v for k, v in rtgym.items() if k not in ("interface_args", "interface_kwargs")})
        config_dict["interface_args"] = tuple(rtgym["interface_args"])
        config_dict["interface_kwargs"] = drone_kwargs
        config_dict["interface"] = parts["INT"]
        parts["CONFIG_DICT"] = _no_limit(config_dict)
        parts["ENV_CLS"] = partial(generic_gym_env, id=RTGYM_VERSION, gym_kwargs={"config": config_dict})
        parts["POLICY"] = _attr("tmrl.models", "SquashedGaussianMLPActor", interface)
        parts["TRAIN_MODEL"] = _mlp_model(alg_name, interface)
        if rtgym["act_in_obs"]:
            parts["SAMPLE_COMPRESSOR"] = DropActionBuffer(act_buf_len)
            parts["MEMORY"] = partial(_attr("tmrl.memory", "RealTimeTorchMemory", interface),
                                      act_buf_len=act_buf_len, **memory_common)
        else:  # no action buffer in the observations: nothing to drop or rebuild
            parts["MEMORY"] = partial(_attr("tmrl.memory", "GenericTorchMemory", interface), **memory_common)

    else:  # the driving interfaces: simulator (SIM*) and TrackMania (TM20*) share their pipeline
        _driving(cfg, interface, alg_name, generic_gym_env, memory_common, parts)

    memory = parts["MEMORY"]
    model = parts["TRAIN_MODEL"]
    # Every ALG key reaches its agent argument by the settings table (tmrl/config/schema.py, ``feeds``).
    agent_args = arguments(cfg, AGENT_CLASSES[alg_name])
    agent = partial(_attr("tmrl.algorithms", "agent_class", interface)(alg_name), model_cls=model, **agent_args)
    device_training = _device(cfg["CUDA_TRAINING"])
    trainer = partial(
        _attr("tmrl.training_offline", "TorchTrainingOffline", interface),
        env_cls=parts["ENV_CLS"],
        memory_cls=memory,
        training_agent_cls=agent,
        device=device_training,
        **arguments(cfg, "TorchTrainingOffline"),
    )
    return Assembly(
        MEM=memory.func,
        AGENT=agent,
        TRAINER=trainer,
        CONFIG_DICT_MODIFIERS=dict(rtgym),
        ALG_CONFIG=cfg["ALG"],
        ALG_NAME=alg_name,
        DEVICE_TRAINING=device_training,
        DEVICE_INFERENCE=_device(cfg["CUDA_INFERENCE"]),
        **parts,
    )


def _driving(cfg: dict[str, Any], interface: str, alg_name: str, generic_gym_env: Any,
             memory_common: dict[str, Any], parts: dict[str, Any]) -> None:
    """The objects of the simulator (SIM*) and TrackMania (TM20*) interfaces, into ``parts``."""
    env = cfg["ENV"]
    rtgym = env["RTGYM_CONFIG"]
    act_buf_len = rtgym["act_buf_len"]
    pipeline = _attr("tmrl.sim.interfaces", "pipeline_parts", interface)(interface)
    if interface in _SIM:
        sim = _module("tmrl.sim.interfaces", interface)
        try:
            sim_kwargs = sim.interface_kwargs(cfg)
        except ConfigError:
            raise
        except UserError as e:  # an unknown interface keyword: a configuration mistake
            raise ConfigError(str(e)) from None
        parts["INT"] = partial(sim.interface_class(interface), **sim_kwargs)
        config_dict = parts["CONFIG_DICT"] = _no_limit(sim.realtime_config(cfg))
        if env["SIM_FAST_MODE"]:
            max_len = rtgym["ep_max_length"]
            parts["ENV_CLS"] = partial(
                sim.SimEnv,
                interface=interface,
                time_step_duration=rtgym["time_step_duration"],
                ep_max_length=10**9 if max_len is None else max_len,
                act_buf_len=act_buf_len,
                **sim_kwargs,
            )
        else:
            parts["ENV_CLS"] = partial(generic_gym_env, id=RTGYM_VERSION, gym_kwargs={"config": config_dict})
    else:
        tm = _module("tmrl.tm.interfaces", interface)
        config_dict = parts["CONFIG_DICT"] = _no_limit(tm.realtime_config(cfg))
        tm_cls = config_dict["interface"]
        check_interface_kwargs(config_dict["interface_kwargs"], _init_keywords(tm_cls), interface)
        parts["INT"] = partial(tm_cls, **config_dict["interface_kwargs"])
        parts["ENV_CLS"] = partial(generic_gym_env, id=RTGYM_VERSION, gym_kwargs={"config": config_dict})
    parts["OBS_PREPROCESSOR"] = pipeline["obs_preprocessor"]
    parts["SAMPLE_COMPRESSOR"] = pipeline["sample_compressor"]
    parts["POLICY"] = pipeline["actor_cls"]
    memory_cls = pipeline["memory_cls"]
    if alg_name == "DRQ":  # an image interface (checked in _build): frames stay uint8 up to the model
        parts["OBS_PREPROCESSOR"] = _attr("tmrl.driving.preprocessors", "preprocess_full_obs_uint8", interface)
        memory_cls = _attr("tmrl.driving.memories", "RawImageMemory", interface)
        parts["POLICY"] = _attr("tmrl.algorithms.drq", "DrQActor", interface)
        parts["TRAIN_MODEL"] = _attr("tmrl.algorithms.drq", "DrQActorCritic", interface)
    elif alg_name in ("SAC", "REDQSAC"):
        parts["TRAIN_MODEL"] = pipeline["model_cls"]  # REDQ passes its number of critics (n) itself
    elif interface in _IMAGE:
        # Their critics (dropout, quantile, batch-normalised) exist as MLPs only: none reads images.
        raise ConfigError(
            f"ALG.ALGORITHM {alg_name} has no image model, so it does not run with ENV.RTGYM_INTERFACE "
            f"{interface}: use a lidar interface ({', '.join(i for i in (*_SIM, *_TM) if i not in _IMAGE)}) "
            "or ALG.ALGORITHM SAC or REDQSAC"
        )
    else:
        # The algorithm's MLP actor-critic with the lidar scaling; its actor is the workers' LidarActor.
        parts["TRAIN_MODEL"] = _attr("tmrl.driving.models", "lidar_model_cls", interface)(alg_name)
    parts["MEMORY"] = partial(
        memory_cls,
        hist_len=env["IMG_HIST_LEN"],
        act_buf_len=act_buf_len,
        crc_debug=False,  # the original's CRC_DEBUG constant
        **memory_common,
    )
