"""Compatibility module: the objects of the original ``tmrl.config.config_objects``, built from the
configuration when imported (that is this module's documented job).

It reads the config through :mod:`tmrl.config.config_constants` and exposes partials
(:func:`tmrl.util.partial`) under the original names:

- ``ENV_CLS``: the environment (``tmrl.envs.GenericGymEnv``)
- ``POLICY``: the actor class the workers run; ``TRAIN_MODEL``: the actor-critic trained
- ``MEMORY``: the replay memory; ``AGENT``: the training agent; ``TRAINER``: the training loop
- ``SAMPLE_COMPRESSOR``, ``OBS_PREPROCESSOR``, ``SAMPLE_PREPROCESSOR``
- ``CONFIG_DICT`` (the real-time configuration, for real-time interfaces), ``INT`` (the interface),
  ``ALG_CONFIG``, ``ALG_NAME``, ``DUMP_RUN_INSTANCE_FN``, ``LOAD_RUN_INSTANCE_FN``, ``UPDATER_FN``

Supported values of ``ENV.RTGYM_INTERFACE`` so far: ``"GYM"`` (any Gymnasium environment named by
``ENV.GYM_ID``) and ``"DRONE"`` (the real-time simulated drone of :mod:`tmrl.realtime`).

Raises (at import):
    tmrl.config.loader.ConfigError: the configuration is invalid.
    tmrl.errors.UserError: the configured interface, or a module it needs, is not available in
        this version of tmrl.
"""

from __future__ import annotations

import importlib
from typing import Any

import tmrl.config.config_constants as cfg
from tmrl.errors import UserError
from tmrl.util import partial

__all__ = [
    "AGENT",
    "ALG_CONFIG",
    "ALG_NAME",
    "CONFIG_DICT",
    "DEVICE_INFERENCE",
    "DEVICE_TRAINING",
    "DUMP_RUN_INSTANCE_FN",
    "ENV_CLS",
    "INT",
    "LOAD_RUN_INSTANCE_FN",
    "MEMORY",
    "OBS_PREPROCESSOR",
    "POLICY",
    "SAMPLE_COMPRESSOR",
    "SAMPLE_PREPROCESSOR",
    "TRAINER",
    "TRAIN_MODEL",
    "UPDATER_FN",
]

_SUPPORTED = ("GYM", "DRONE")


def _module(name: str) -> Any:
    """Import a tmrl module; a tmrl module that does not exist yet becomes a one-line UserError
    (other import errors, such as a missing third-party package, keep their own message)."""
    try:
        return importlib.import_module(name)
    except ModuleNotFoundError as e:
        missing = e.name or ""
        if missing.startswith("tmrl") and (name == missing or name.startswith(missing + ".")):
            raise UserError(
                f"ENV.RTGYM_INTERFACE {cfg.RTGYM_INTERFACE!r} needs {name}, which is not available yet in "
                f"this version of tmrl; use one of {', '.join(_SUPPORTED)}"
            ) from None
        raise


def _attr(module: str, name: str) -> Any:
    mod = _module(module)
    try:
        return getattr(mod, name)
    except AttributeError:
        raise UserError(
            f"{module}.{name} is not available yet in this version of tmrl "
            f"(needed by ENV.RTGYM_INTERFACE {cfg.RTGYM_INTERFACE!r})"
        ) from None


if cfg.RTGYM_INTERFACE not in _SUPPORTED:
    raise UserError(
        f"ENV.RTGYM_INTERFACE {cfg.RTGYM_INTERFACE!r} is not available yet in tmrl.config.config_objects; "
        f"use one of {', '.join(_SUPPORTED)} (e.g. --config '{{\"ENV\": {{\"RTGYM_INTERFACE\": \"GYM\"}}}}')"
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


ALG_CONFIG: dict[str, Any] = cfg.ALG_CONFIG
ALG_NAME: str = cfg.ALG_NAME
DEVICE_TRAINING: str = _device(cfg.CUDA_TRAINING)
DEVICE_INFERENCE: str = _device(cfg.CUDA_INFERENCE)

# --- models --------------------------------------------------------------------------------------

POLICY = _attr("tmrl.models", "SquashedGaussianMLPActor")
TRAIN_MODEL = _attr("tmrl.models", "MLPActorCritic" if ALG_NAME == "SAC" else "REDQMLPActorCritic")

# --- environment, compression, memory ------------------------------------------------------------

_GenericGymEnv = _attr("tmrl.envs", "GenericGymEnv")

if cfg.RTGYM_INTERFACE == "GYM":
    INT: Any = None
    CONFIG_DICT: dict[str, Any] | None = None
    ENV_CLS = partial(_GenericGymEnv, id=cfg.GYM_ID, gym_kwargs=dict(cfg.GYM_KWARGS))
    SAMPLE_COMPRESSOR: Any = None
    MEMORY = partial(
        _attr("tmrl.memory", "GenericTorchMemory"),
        memory_size=cfg.TMRL_CONFIG["MEMORY_SIZE"],
        batch_size=cfg.TMRL_CONFIG["BATCH_SIZE"],
    )
else:  # DRONE
    _rtgym = cfg.ENV_CONFIG["RTGYM_CONFIG"]
    INT = partial(_attr("tmrl.realtime", "DroneInterface"))
    CONFIG_DICT = dict(_attr("tmrl.realtime", "DEFAULT_CONFIG_DICT"))
    CONFIG_DICT.update({k: v for k, v in _rtgym.items() if k not in ("interface_args",)})
    CONFIG_DICT["interface_args"] = tuple(_rtgym["interface_args"])
    # Files written for the original carry TrackMania's "save_replays", which the drone does not take.
    CONFIG_DICT["interface_kwargs"] = {k: v for k, v in _rtgym["interface_kwargs"].items() if k != "save_replays"}
    CONFIG_DICT["interface"] = INT
    if CONFIG_DICT.get("ep_max_length") is None:
        CONFIG_DICT["ep_max_length"] = float("inf")  # the real-time env's "no limit"
    ENV_CLS = partial(_GenericGymEnv, id=cfg.RTGYM_VERSION, gym_kwargs={"config": CONFIG_DICT})
    if _rtgym["act_in_obs"]:
        SAMPLE_COMPRESSOR = DropActionBuffer(cfg.ACT_BUF_LEN)
        MEMORY = partial(
            _attr("tmrl.memory", "RealTimeTorchMemory"),
            memory_size=cfg.TMRL_CONFIG["MEMORY_SIZE"],
            batch_size=cfg.TMRL_CONFIG["BATCH_SIZE"],
            act_buf_len=cfg.ACT_BUF_LEN,
        )
    else:  # no action buffer in the observations: nothing to drop or rebuild
        SAMPLE_COMPRESSOR = None
        MEMORY = partial(
            _attr("tmrl.memory", "GenericTorchMemory"),
            memory_size=cfg.TMRL_CONFIG["MEMORY_SIZE"],
            batch_size=cfg.TMRL_CONFIG["BATCH_SIZE"],
        )

OBS_PREPROCESSOR: Any = None
SAMPLE_PREPROCESSOR: Any = None

# --- algorithm -----------------------------------------------------------------------------------

_agent_kwargs: dict[str, Any] = {
    "model_cls": TRAIN_MODEL,
    "lr_actor": ALG_CONFIG["LR_ACTOR"],
    "lr_critic": ALG_CONFIG["LR_CRITIC"],
    "lr_entropy": ALG_CONFIG["LR_ENTROPY"],
    "gamma": ALG_CONFIG["GAMMA"],
    "polyak": ALG_CONFIG["POLYAK"],
    "learn_entropy_coef": ALG_CONFIG["LEARN_ENTROPY_COEF"],
    "target_entropy": ALG_CONFIG["TARGET_ENTROPY"],
    "alpha": ALG_CONFIG["ALPHA"],
    "optimizer_actor": ALG_CONFIG["OPTIMIZER_ACTOR"],
    "optimizer_critic": ALG_CONFIG["OPTIMIZER_CRITIC"],
    "betas_actor": list(ALG_CONFIG["BETAS_ACTOR"]),
    "betas_critic": list(ALG_CONFIG["BETAS_CRITIC"]),
    "l2_actor": ALG_CONFIG["L2_ACTOR"],
    "l2_critic": ALG_CONFIG["L2_CRITIC"],
}
if ALG_NAME == "SAC":
    AGENT = partial(_attr("tmrl.algorithms.sac", "SACAgent"), **_agent_kwargs)
else:
    AGENT = partial(
        _attr("tmrl.algorithms.redq", "REDQSACAgent"),
        **_agent_kwargs,
        n=ALG_CONFIG["REDQ_N"],
        m=ALG_CONFIG["REDQ_M"],
        q_updates_per_policy_update=ALG_CONFIG["REDQ_Q_UPDATES_PER_POLICY_UPDATE"],
    )

# --- training loop -------------------------------------------------------------------------------

TRAINER = partial(
    _attr("tmrl.training_offline", "TorchTrainingOffline"),
    env_cls=ENV_CLS,
    memory_cls=MEMORY,
    training_agent_cls=AGENT,
    epochs=cfg.TMRL_CONFIG["MAX_EPOCHS"],
    rounds=cfg.TMRL_CONFIG["ROUNDS_PER_EPOCH"],
    steps=cfg.TMRL_CONFIG["TRAINING_STEPS_PER_ROUND"],
    update_buffer_interval=cfg.TMRL_CONFIG["UPDATE_BUFFER_INTERVAL"],
    update_model_interval=cfg.TMRL_CONFIG["UPDATE_MODEL_INTERVAL"],
    max_training_steps_per_env_step=cfg.TMRL_CONFIG["MAX_TRAINING_STEPS_PER_ENVIRONMENT_STEP"],
    start_training=cfg.TMRL_CONFIG["ENVIRONMENT_STEPS_BEFORE_TRAINING"],
    device=DEVICE_TRAINING,
)

# --- checkpoints (the original's hooks; none are needed by the built-in pipelines) ---------------

DUMP_RUN_INSTANCE_FN = None
LOAD_RUN_INSTANCE_FN = None
UPDATER_FN = None
