"""The one table of ``config.json``: every key with its type, default, allowed range, meaning and
the constructor arguments it sets. **A new key is declared here** (in :data:`SCHEMA`, or in one of
its sections) and nowhere else.

Everything else derives from it: the loader validates against it and fills missing keys with its
defaults, ``config/config.json`` is its defaults written out (the other ``config/*.json`` are the
defaults with the changes of :data:`~tmrl.config.generate.EXAMPLES`), and ``docs/config.md`` is
generated from it. Regenerate both after a change with::

    python -m tmrl.config.schema --write

(``--markdown`` and ``--json`` print the reference and the default config instead.)

The parts the table is made of live beside it: the value types in :mod:`tmrl.config.spec`, the
checks across keys in :mod:`tmrl.config.checks`, the generators of the files in
:mod:`tmrl.config.generate`; their names are importable from here as well.

Nothing here reads a file or touches the disk at import.
"""

from __future__ import annotations

import sys
from collections.abc import Mapping
from typing import Any

from tmrl.config import generate
from tmrl.config.checks import check_consistency, redq_subset_problem
from tmrl.config.generate import EXAMPLES
from tmrl.config.spec import (
    NO_CLASS_DEFAULT,
    AnyDict,
    AnyList,
    Bool,
    Choice,
    ConfigError,
    Int,
    Number,
    NumberList,
    SchemaViolation,
    Section,
    Spec,
    Str,
    show,  # noqa: F401 (the loader and older code reach it here)
)

__all__ = [
    "AGENT_CLASSES",
    "ALGORITHMS",
    "COMPILE_MODES",
    "EXAMPLES",
    "NO_CLASS_DEFAULT",
    "ON_DEVICE_MODES",
    "OPTIMIZERS",
    "PASSWORD_PLACEHOLDER",
    "RTGYM_INTERFACES",
    "SCHEMA",
    "UPDATE_ORDERS",
    "AnyDict",
    "AnyList",
    "Bool",
    "Choice",
    "ConfigError",
    "Int",
    "Number",
    "NumberList",
    "SchemaViolation",
    "Section",
    "Spec",
    "Str",
    "arguments",
    "check_consistency",
    "default_config_json",
    "defaults",
    "example_json",
    "fed_arguments",
    "generated_files",
    "markdown_reference",
    "redq_subset_problem",
]

# --- the schema ----------------------------------------------------------------------------------

RTGYM_INTERFACES = (
    "TM20FULL",
    "TM20LIDAR",
    "TM20LIDARPROGRESS",
    "SIMFULL",
    "SIMLIDAR",
    "SIMLIDARPROGRESS",
    "GYM",
    "DRONE",
)
"""Values of ``ENV.RTGYM_INTERFACE``: TrackMania 2020 (full images, lidar, lidar with track
progress), the built-in simulated track (same three observations), any Gymnasium environment
(``ENV.GYM_ID``), and the real-time simulated drone of :mod:`tmrl.realtime`."""

ALGORITHMS = ("SAC", "REDQSAC", "DROQ", "TQC", "CROSSQ", "DRQ", "BRO", "SIMBAV2")
"""Values of ``ALG.ALGORITHM``."""

PASSWORD_PLACEHOLDER = "YourRandomPasswordHere"
"""The password of the shipped file; ``python -m tmrl --install`` replaces it by a random one."""

OPTIMIZERS = ("adam", "adamw", "sgd")
"""Values of ``ALG.OPTIMIZER_ACTOR`` and ``ALG.OPTIMIZER_CRITIC`` (:func:`tmrl.algorithms.sac.make_optimizer`)."""

UPDATE_ORDERS = ("simultaneous", "sequential")
"""Values of ``ALG.UPDATE_ORDER`` (``SACAgent(update_order=...)``)."""

COMPILE_MODES = ("off", "compile", "cudagraph")
"""Values of ``ALG.COMPILE`` (``compile=`` of every agent)."""

ON_DEVICE_MODES = ("auto", "on", "off")
"""Values of ``MEMORY_ON_DEVICE`` (the built-in memories' ``on_device``, :mod:`tmrl.memory.resident`)."""

AGENT_CLASSES = {"SAC": "SACAgent", "REDQSAC": "REDQSACAgent", "DROQ": "DroQAgent", "TQC": "TQCAgent",
                 "CROSSQ": "CrossQAgent", "DRQ": "DrQAgent", "BRO": "BROAgent",
                 "SIMBAV2": "SimbaV2Agent"}
"""The agent class each value of ``ALG.ALGORITHM`` selects (:data:`tmrl.algorithms.ALGORITHMS`)."""

_MIB = 1024 * 1024


def _agents(arg: str, class_default: Any) -> dict[str, Any]:
    """``feeds`` and ``class_default`` of an ``ALG`` key that every agent takes."""
    return {"feeds": tuple(f"{cls}.{arg}" for cls in AGENT_CLASSES.values()), "class_default": class_default}


_ALG = Section(
    {
        "ALGORITHM": Choice("SAC", "training algorithm (SAC: SACAgent, REDQSAC: REDQSACAgent, DROQ: DroQAgent, "
                            "TQC: TQCAgent, CROSSQ: CrossQAgent, DRQ: DrQAgent, image interfaces only, BRO: BROAgent, SIMBAV2: SimbaV2Agent)",
                            ALGORITHMS),
        "LEARN_ENTROPY_COEF": Bool(False, "learn the entropy coefficient (SAC v2) instead of keeping ALPHA fixed",
                                   **_agents("learn_entropy_coef", True)),
        "LR_ACTOR": Number(1e-05, "learning rate of the actor", min=0, min_open=True, **_agents("lr_actor", 1e-3)),
        "LR_CRITIC": Number(5e-05, "learning rate of the critic(s)", min=0, min_open=True,
                            **_agents("lr_critic", 1e-3)),
        "LR_ENTROPY": Number(0.0003, "learning rate of the entropy coefficient (when learned)", min=0,
                             min_open=True, **_agents("lr_entropy", 1e-3)),
        "GAMMA": Number(0.995, "discount factor", min=0, max=1, **_agents("gamma", 0.99)),
        "POLYAK": Number(0.995, "weight of the old target critic in each soft update (1: never updated)",
                         min=0, max=1, **_agents("polyak", 0.995)),
        "TARGET_ENTROPY": Number(-0.5, "target entropy when LEARN_ENTROPY_COEF is true (null: minus the action size)",
                                 nullable=True, **_agents("target_entropy", None)),
        "ALPHA": Number(0.01, "entropy coefficient (fixed, or initial value when learned)", min=0,
                         **_agents("alpha", 0.2)),
        "ALPHA_MAX": Number(None, "ceiling of a learned entropy coefficient once it has come down to it (it falls "
                                  "freely from ALPHA until then; null: no ceiling)", min=0, min_open=True,
                            nullable=True, **_agents("alpha_max", None)),
        "REDQ_N": Int(10, "number of critics in the REDQ ensemble", min=1, feeds=("REDQSACAgent.n",), class_default=10),
        "REDQ_M": Int(2, "number of critics drawn at random for each REDQ target", min=1, feeds=("REDQSACAgent.m",),
                      class_default=2),
        "REDQ_Q_UPDATES_PER_POLICY_UPDATE": Int(20, "REDQ critic updates for each actor update", min=1,
                                                feeds=("REDQSACAgent.q_updates_per_policy_update",), class_default=1),
        "DROQ_DROPOUT_RATE": Number(0.01, "dropout rate of the DroQ critics", min=0, max=1, max_open=True,
                                    feeds=("DroQAgent.dropout_rate",), class_default=0.01),
        "DROQ_Q_UPDATES_PER_POLICY_UPDATE": Int(20, "DroQ critic updates for each actor update", min=1,
                                                feeds=("DroQAgent.q_updates_per_policy_update",), class_default=20),
        "TQC_N": Int(5, "number of TQC critics", min=1, feeds=("TQCAgent.n",), class_default=5),
        "TQC_QUANTILES": Int(25, "quantiles output by each TQC critic", min=1, feeds=("TQCAgent.n_quantiles",),
                             class_default=25),
        "TQC_DROP_PER_CRITIC": Int(2, "largest target quantiles dropped per TQC critic (below TQC_QUANTILES)", min=0,
                                   feeds=("TQCAgent.drop_per_critic",), class_default=2),
        "BRO_N": Int(2, "number of BRO critics", min=1, feeds=("BROAgent.n",), class_default=2),
        "BRO_QUANTILES": Int(25, "quantiles output by each BRO critic", min=1, feeds=("BROAgent.n_quantiles",),
                             class_default=25),
        "BRO_PESSIMISM": Number(1.0, "BRO's beta: the target and the actor read the critics' per-quantile mean minus "
                                     "this many standard deviations (0: optimistic; 1 with two critics: their "
                                     "minimum)", min=0, feeds=("BROAgent.pessimism",), class_default=1.0),
        "BRO_CRITIC_WIDTH": Int(256, "hidden width of each BRO critic (BroNet; the paper: 512, for a GPU)", min=1,
                                feeds=("BROAgent.critic_width",), class_default=256),
        "BRO_CRITIC_BLOCKS": Int(1, "residual blocks of each BRO critic (BroNet: Linear, LayerNorm, ReLU, Linear, "
                                    "LayerNorm, plus the input)", min=0, feeds=("BROAgent.critic_blocks",),
                                 class_default=1),
        "SIMBAV2_N": Int(2, "number of SimbaV2 critics", min=1, feeds=("SimbaV2Agent.n",), class_default=2),
        "SIMBAV2_ATOMS": Int(101, "atoms of the support of each SimbaV2 critic's return distribution", min=2,
                             feeds=("SimbaV2Agent.n_atoms",), class_default=101),
        "SIMBAV2_V_MAX": Number(5.0, "the SimbaV2 support is [-SIMBAV2_V_MAX, SIMBAV2_V_MAX] (returns after the reward "
                                     "scaling)", min=0, min_open=True, feeds=("SimbaV2Agent.v_max",), class_default=5.0),
        "SIMBAV2_CRITIC_WIDTH": Int(128, "width of each SimbaV2 critic's hidden vectors (the paper: 512, for a GPU)",
                                    min=1, feeds=("SimbaV2Agent.critic_width",), class_default=128),
        "SIMBAV2_CRITIC_BLOCKS": Int(1, "residual blocks of each SimbaV2 critic", min=0,
                                     feeds=("SimbaV2Agent.critic_blocks",), class_default=1),
        "SIMBAV2_SCALE_REWARDS": Bool(True, "divide SimbaV2's rewards by a running estimate of the return's scale",
                                      feeds=("SimbaV2Agent.scale_rewards",), class_default=True),
        "SIMBAV2_REWARD_G_MAX": Number(5.0, "the largest scaled return SimbaV2's reward scaling allows", min=0,
                                       min_open=True, feeds=("SimbaV2Agent.reward_g_max",), class_default=5.0),
        "CROSSQ_POLICY_DELAY": Int(3, "CrossQ critic updates for each actor update", min=1,
                                   feeds=("CrossQAgent.policy_delay",), class_default=3),
        "CROSSQ_CRITIC_WIDTH": Int(1024, "width of the two hidden layers of each CrossQ critic (the paper: 2048, "
                                         "for a GPU)", min=1, feeds=("CrossQAgent.critic_width",), class_default=1024),
        "CROSSQ_BN_MOMENTUM": Number(0.01, "momentum of the CrossQ critics' batch normalisation (weight of each "
                                           "batch in the running statistics)", min=0, max=1, min_open=True,
                                    feeds=("CrossQAgent.bn_momentum",), class_default=0.01),
        "CROSSQ_RENORM_WARMUP_STEPS": Int(100000, "CrossQ critic updates of plain batch normalisation before batch "
                                                  "renormalisation", min=0,
                                          feeds=("CrossQAgent.renorm_warmup_steps",), class_default=100000),
        "DRQ_IMAGE_PAD": Int(4, "DrQ's random shift of the trainer's frames: padding in pixels (0: no augmentation)",
                             min=0, feeds=("DrQAgent.image_pad",), class_default=4),
        "OPTIMIZER_ACTOR": Choice("adam", "optimizer of the actor", OPTIMIZERS, **_agents("optimizer_actor", "adam")),
        "OPTIMIZER_CRITIC": Choice("adam", "optimizer of the critic(s)", OPTIMIZERS,
                                   **_agents("optimizer_critic", "adam")),
        "BETAS_ACTOR": NumberList([0.997, 0.997], "Adam/AdamW betas of the actor", length=2,
                                  item=Number(0, "", min=0, max=1, max_open=True), **_agents("betas_actor", None)),
        "BETAS_CRITIC": NumberList([0.997, 0.997], "Adam/AdamW betas of the critic(s)", length=2,
                                   item=Number(0, "", min=0, max=1, max_open=True), **_agents("betas_critic", None)),
        "L2_ACTOR": Number(0.0, "weight decay of the actor optimizer", min=0, **_agents("l2_actor", None)),
        "L2_CRITIC": Number(0.0, "weight decay of the critic optimizer", min=0, **_agents("l2_critic", None)),
        "UPDATE_ORDER": Choice("simultaneous", "SAC only: \"simultaneous\" evaluates the actor loss on the critics "
                               "before their step (one backward pass), \"sequential\" after it (the original tmrl "
                               "SAC)", UPDATE_ORDERS, feeds=("SACAgent.update_order",),
                               class_default="simultaneous"),
        "COMPILE": Choice("off", "the agent's update without Python in the loop: \"off\" (eager), \"compile\" "
                          "(torch.compile of its forward passes and losses) or \"cudagraph\" (the same, replayed as "
                          "CUDA graphs; CUDA only), for every agent; the first update of each kind is checked "
                          "against eager and a mismatch falls back to eager",
                          COMPILE_MODES,
                          feeds=tuple(f"{cls}.compile" for cls in AGENT_CLASSES.values()),
                          class_default="off"),
    },
    "the training algorithm and its hyperparameters",
)

_RTGYM = Section(
    {
        "time_step_duration": Number(0.05, "target duration of one real-time step, in seconds", min=0,
                                     min_open=True),
        "start_obs_capture": Number(0.04, "time after the start of a step when the observation is captured (s)",
                                    min=0),
        "time_step_timeout_factor": Number(1.0, "how late a step may end, in steps, before the clock resets",
                                           min=0),
        "act_buf_len": Int(2, "number of past actions appended to each observation", min=1),
        "benchmark": Bool(False, "time the environment's steps (needed by --benchmark)"),
        "wait_on_done": Bool(True, "pause the environment when an episode ends"),
        "ep_max_length": Int(1000, "episodes are truncated after this many steps (null: never)", min=1,
                             nullable=True),
        "interface_kwargs": AnyDict({}, "keyword arguments of the interface (TrackMania: save_replays)"),
        "interface_args": AnyList([], "positional arguments of the interface"),
        "act_in_obs": Bool(True, "append the action buffer to observations"),
        "reset_act_buf": Bool(True, "fill the action buffer with the default action at reset"),
        "benchmark_polyak": Number(0.1, "smoothing factor of the benchmark averages", min=0, max=1,
                                   min_open=True),
        "benchmark_type": Choice("polyak", "how benchmarks are kept (running averages or full traces)",
                                 ("polyak", "trace")),
        "last_act_on_reset": Bool(False, "at reset, send the last action instead of the default one"),
    },
    "the real-time clock (rtgym parameters)",
)

_REWARD = Section(
    {
        "END_OF_TRACK": Number(100.0, "reward for crossing the finish line"),
        "CONSTANT_PENALTY": Number(0.0, "reward added at every step (zero or negative)"),
        "CHECK_FORWARD": Int(500, "trajectory points searched ahead of the car (allows cuts)", min=1),
        "CHECK_BACKWARD": Int(10, "trajectory points searched behind the car", min=0),
        "FAILURE_COUNTDOWN": Int(10, "steps without progress before the episode ends", min=1),
        "MIN_STEPS": Int(70, "steps at the start of an episode during which it cannot fail", min=0),
        "MAX_STRAY": Number(100.0, "distance from the trajectory (m) that ends the episode", min=0,
                            min_open=True),
    },
    "the trajectory reward (TrackMania and the simulated track)",
)

_ENV = Section(
    {
        "RTGYM_INTERFACE": Choice("TM20FULL", "environment: TrackMania 2020 (TM20*) or the simulated track (SIM*) "
                                              "with images (FULL), lidar (LIDAR) or lidar and progress "
                                              "(LIDARPROGRESS); a Gymnasium env (GYM, see GYM_ID); the real-time "
                                              "drone (DRONE)",
                                  RTGYM_INTERFACES),
        "WINDOW_WIDTH": Int(256, "the game window is resized to this width (pixels)", min=1),
        "WINDOW_HEIGHT": Int(128, "the game window is resized to this height (pixels)", min=1),
        "IMG_WIDTH": Int(64, "width of the images fed to the model", min=1),
        "IMG_HEIGHT": Int(64, "height of the images fed to the model", min=1),
        "IMG_GRAYSCALE": Bool(True, "convert images to grayscale"),
        "SLEEP_TIME_AT_RESET": Number(1.5, "seconds waited after a respawn (the green light)", min=0),
        "IMG_HIST_LEN": Int(4, "number of past images or lidar scans in each observation", min=1),
        "LINUX_X_OFFSET": Int(64, "horizontal offset of the game window's content on Linux (pixels)"),
        "LINUX_Y_OFFSET": Int(70, "vertical offset of the game window's content on Linux (pixels)"),
        "IMG_SCALE_CHECK_ENV": Number(1.0, "zoom of the images shown by --check-environment", min=0,
                                      min_open=True),
        "GYM_ID": Str("Pendulum-v1", "Gymnasium id used when RTGYM_INTERFACE is GYM"),
        "GYM_KWARGS": AnyDict({}, "keyword arguments of gymnasium.make when RTGYM_INTERFACE is GYM"),
        "SIM_FAST_MODE": Bool(True, "SIM* interfaces: step the simulator as fast as the CPU allows (false: in real "
                                    "time through tmrl.realtime, like the game)"),
        "RTGYM_CONFIG": _RTGYM,
        "REWARD_CONFIG": _REWARD,
    },
    "the environment",
)

SCHEMA = Section(
    {
        "RUN_NAME": Str("SAC_4_imgs_pretrained", "name of the run; names the weights and checkpoint files (so "
                                                 "none of < > : \" / \\ | ? *, no device name such as CON or NUL, "
                                                 "no trailing dot or space: Windows refuses them)",
                        nonempty=True, forbid="/\\", filename=True),
        "RESET_TRAINING": Bool(False, "start training from scratch instead of resuming the checkpoint"),
        "BUFFERS_MAXLEN": Int(500000, "maximum number of samples held in a network buffer (not the replay memory)",
                              min=1, feeds=("Buffer.maxlen",)),
        "RW_MAX_SAMPLES_PER_EPISODE": Int(1000, "a worker truncates episodes longer than this", min=1,
                                          feeds=("RolloutWorker.max_samples_per_episode",)),
        "CUDA_TRAINING": Bool(False, "train on the GPU when one is available"),
        "CUDA_INFERENCE": Bool(False, "run the workers' policy on the GPU when one is available"),
        "VIRTUAL_GAMEPAD": Bool(True, "drive TrackMania with a virtual gamepad (false: keyboard)"),
        "OPENPLANET_FOLDER": Str("", "TrackMania: the OpenplanetNext folder that --install copies the plugins into "
                                     "and --doctor checks (empty: OpenplanetNext in the home folder, then in Steam's "
                                     "Proton prefixes on Linux)"),
        "LOCALHOST_WORKER": Bool(True, "the worker reaches the server on 127.0.0.1 (false: PUBLIC_IP_SERVER)"),
        "LOCALHOST_TRAINER": Bool(True, "the trainer reaches the server on 127.0.0.1 (false: PUBLIC_IP_SERVER)"),
        "PUBLIC_IP_SERVER": Str("0.0.0.0", "address of the server when it is on another machine", nonempty=True),
        "PASSWORD": Str(PASSWORD_PLACEHOLDER, "shared secret of the server, trainer and workers (same everywhere)",
                        nonempty=True, feeds=("Server.password", "Trainer.password", "RolloutWorker.password")),
        "TLS": Bool(False, "encrypt and authenticate connections with TLS (needed on public networks)"),
        "TLS_HOSTNAME": Str("default", "host name in the TLS certificate", nonempty=True),
        "TLS_CREDENTIALS_DIRECTORY": Str("", "folder of the TLS key and certificate (empty: credentials/ in the "
                                             "data folder)"),
        "ALLOW_PLAIN_TCP": Bool(False, "allow unencrypted connections to a server on another machine "
                                       "(trusted networks only)"),
        "ALLOW_PICKLE": Bool(False, "accept pickled messages from the network (trusted networks only: "
                                    "pickle can run code)"),
        "MAX_FRAME_BYTES": Int(64 * _MIB, "largest message accepted from the network, in bytes", min=1024),
        "NB_WORKERS": Int(64, "maximum number of workers connected to the server at once (negative: no limit)",
                          feeds=("Server.max_workers",)),
        "SERVER_MEMORY_BYTES": Int(1536 * _MIB, "most memory the server spends on samples waiting for the trainer "
                                                "and on messages being received, in bytes; a connection that "
                                                "would exceed it is closed", min=64 * _MIB),
        "SERVER_PARTIAL_TIMEOUT": Number(60.0, "seconds the server waits for the next part of a half-received "
                                               "message before it drops it and closes the connection", min=1),
        "TRANSPORT": Choice("tlspyo", 'how samples and weights cross the network: "tlspyo" (tmrl\'s relay) or '
                                      '"nats" (NATS JetStream, pip install ".[nats]" in this project\'s checkout; '
                                      'see the Scale-out page)',
                            ("tlspyo", "nats")),
        "NATS": Section(
            {
                "URLS": Str("", "comma-separated URLs of an existing NATS cluster (nats://host:4222,...); empty: "
                                "the server (--server) starts and supervises a local nats-server on PORT"),
                "STREAM": Str("tmrl-samples", "JetStream stream of the sample batches (it names a folder of "
                                              "the store)", nonempty=True, forbid=".*>/\\", filename=True),
                "BUCKET": Str("tmrl-weights", "object-store and key-value bucket of the weights (it names a "
                                              "folder of the store)", nonempty=True, forbid=".*>/\\",
                              filename=True),
                "MAX_BYTES": Int(1024 * _MIB, "bound of the samples stream in bytes: beyond it the oldest batches "
                                              "are discarded (the trainer counts them)", min=_MIB),
                "MAX_MSGS": Int(100000, "bound of the samples stream in batches: beyond it the oldest are "
                                        "discarded (the trainer counts them)", min=1),
                "MAX_PAYLOAD": Int(8 * _MIB, "largest message the local nats-server accepts, in bytes (a sample "
                                             "batch must fit)", min=_MIB, max=64 * _MIB),
                "REPLICAS": Int(1, "copies of the stream and buckets in a NATS cluster (3 on a three-node "
                                   "cluster survives the loss of one node; 1 for a single server)", min=1, max=5),
                "TLS": Choice("auto", 'TLS to the NATS server: "auto" (on when TLS is true or the server is on '
                                      'another machine), "on" or "off"', ("auto", "on", "off")),
                "WORKER_CREDENTIALS": Str("", "a worker's NATS credentials file (worker.json from --install); "
                                              "empty: nats/worker.json in the credentials folder when it exists, "
                                              "else derived from PASSWORD"),
                "TRAINER_CREDENTIALS": Str("", "the trainer's NATS credentials file (trainer.json from --install); "
                                               "empty: nats/trainer.json in the credentials folder when it exists, "
                                               "else derived from PASSWORD"),
                "STORE_DIRECTORY": Str("", "folder of the local nats-server's JetStream store (empty: nats/ in "
                                           "the data folder)"),
            },
            "the NATS JetStream transport (TRANSPORT \"nats\"; see docs/scale-out.md)",
        ),
        "WANDB_PROJECT": Str("tmrl", "wandb project of --trainer --wandb"),
        "WANDB_ENTITY": Str("tmrl", "wandb entity (user or team) of --trainer --wandb"),
        "WANDB_KEY": Str("YourWandbApiKey", "wandb API key of --trainer --wandb"),
        "PORT": Int(55555, "public port of the server", min=1, max=65535,
                    feeds=("Server.port", "Trainer.server_port", "RolloutWorker.server_port")),
        "LOCAL_PORT_SERVER": Int(55556, "kept so that tmrl 0.7 config files load; unused (the server needs one port: PORT)",
                                 min=1, max=65535),
        "LOCAL_PORT_TRAINER": Int(55557, "kept so that tmrl 0.7 config files load; unused (the trainer opens no port)",
                                  min=1, max=65535),
        "LOCAL_PORT_WORKER": Int(55558, "kept so that tmrl 0.7 config files load; unused (workers open no port, "
                                        "several can share a machine)", min=1, max=65535),
        "BUFFER_SIZE": Int(536870912, "kept so that tmrl 0.7 config files load; unused (the transport sizes its "
                           "own socket buffers; MAX_FRAME_BYTES bounds a message)",
                           min=1),
        "HEADER_SIZE": Int(12, "size of the transport's message header, in bytes", min=1,
                           feeds=("Server.header_size", "Trainer.header_size", "RolloutWorker.header_size")),
        "SEED": Int(None, "seeds Python's, NumPy's and PyTorch's generators when a role starts "
                           "(initial weights, exploration); a distributed run still varies with sample arrival order; null: "
                           "no seeding", nullable=True, min=0),
        "DEBUG_MODE": Bool(False, "kept so that tmrl 0.7 config files load; unused (CRC_DEBUG checks samples "
                                            "end to end)"),
        "MAX_EPOCHS": Int(10000, "number of training epochs (a checkpoint is saved after each)", min=1,
                          feeds=("TorchTrainingOffline.epochs",), class_default=10),
        "ROUNDS_PER_EPOCH": Int(100, "rounds per epoch (metrics are reported after each)", min=1,
                                feeds=("TorchTrainingOffline.rounds",), class_default=50),
        "TRAINING_STEPS_PER_ROUND": Int(200, "training steps per round", min=1, feeds=("TorchTrainingOffline.steps",), class_default=2000),
        "MAX_TRAINING_STEPS_PER_ENVIRONMENT_STEP": Number(4.0, "training pauses when updates per collected "
                                                               "sample exceed this", min=0, min_open=True,
                                                        feeds=("TorchTrainingOffline.max_training_steps_per_env_step",), class_default=1.0),
        "MAX_ENVIRONMENT_STEPS_PER_TRAINING_STEP": Number(
            0.0, "workers pause when samples collected per training step exceed this (0: never); for "
            "environments faster than real time, like the simulator in fast mode; real-time environments "
            "pause only between episodes", min=0, feeds=("TorchTrainingOffline.max_env_steps_per_training_step",), class_default=0.0),
        "ENVIRONMENT_STEPS_BEFORE_TRAINING": Int(1000, "samples collected before training starts", min=0,
                                                 feeds=("TorchTrainingOffline.start_training",), class_default=0),
        "UPDATE_MODEL_INTERVAL": Int(200, "training steps between two broadcasts of the weights", min=1,
                                     feeds=("TorchTrainingOffline.update_model_interval",), class_default=100),
        "UPDATE_BUFFER_INTERVAL": Int(200, "training steps between two retrievals of new samples", min=1,
                                      feeds=("TorchTrainingOffline.update_buffer_interval",), class_default=100),
        "SAVE_MODEL_EVERY": Int(0, "workers keep a copy of every N-th received model (0: none)", min=0,
                                feeds=("RolloutWorker.model_history",)),
        "WORKER_SYNC_STEPS": Int(0, "in a train episode, every N steps a worker sends the samples it has and takes the "
                                    "newest weights without waiting (0: only between episodes, as tmrl 0.7); in real "
                                    "time 20 (a second) keeps the policy and the trainer's samples fresh",
                                 min=0, feeds=("RolloutWorker.sync_every",)),
        "MEMORY_SIZE": Int(1000000, "capacity of the replay memory, in samples", min=1,
                           feeds=("GenericTorchMemory.memory_size",), class_default=1000000),
        "BATCH_SIZE": Int(256, "training batch size", min=1, feeds=("GenericTorchMemory.batch_size",), class_default=256),
        "MEMORY_ON_DEVICE": Choice("auto", "where the replay memory builds its batches: \"auto\" keeps its rings on the "
                                   "training GPU too and gathers each batch there (on a CPU: the host path), \"off\" "
                                   "builds them on the host and copies them over, \"on\" puts the rings on the training "
                                   "device whatever it is (on a CPU, a second copy: for tests); rings that do not fit on "
                                   "the GPU fall back to the host with \"auto\" and stop the trainer with \"on\"",
                                   ON_DEVICE_MODES, feeds=("GenericTorchMemory.on_device",), class_default="auto"),
        "ALG": _ALG,
        "ENV": _ENV,
        "__VERSION__": Str("0.6.0", "format version of this file (do not edit)", nonempty=True),
    },
    "config.json",
)
"""The schema of ``config.json``: every key with its type, default, range and meaning (the table
of the Configuration page is generated from it)."""

# --- the table's queries and generated files (the work is done in spec.py and generate.py) -------


def defaults() -> dict[str, Any]:
    """A fresh dict holding every key at its default (with the placeholder password)."""
    return SCHEMA.default_value()


def arguments(cfg: Mapping[str, Any], cls: str) -> dict[str, Any]:
    """The constructor arguments of class ``cls`` (``"SACAgent"``, ``"TorchTrainingOffline"``,
    ...) that a loaded config sets, by the ``feeds`` of the table: ``{"lr_actor": 1e-05, ...}``.

    Args:
        cfg: a complete, validated config (:func:`tmrl.config.loader.load_config`).
        cls: the class name as written in ``feeds``.
    """
    return SCHEMA.arguments(cfg, cls)


def fed_arguments() -> dict[str, dict[str, tuple[str, Any]]]:
    """For each class named in ``feeds``: ``{argument: (key path, class default)}`` (the class
    default is :data:`NO_CLASS_DEFAULT` where the table declares none). The tests check every
    class's signature against it."""
    return SCHEMA.fed_arguments()


def default_config_json() -> str:
    """The text of the shipped ``config/config.json``: the defaults, indented, ending in a newline."""
    return generate.default_config_json(SCHEMA)


def example_json(name: str) -> str:
    """The text of the shipped example ``config/<name>``: a complete, valid config.

    Args:
        name: a file name among the keys of :data:`~tmrl.config.generate.EXAMPLES`
            (``"config_simlidar.json"``).

    Raises:
        KeyError: ``name`` is not one of :data:`~tmrl.config.generate.EXAMPLES`.
    """
    return generate.example_json(SCHEMA, name)


def generated_files() -> dict[str, str]:
    """Repository-relative path -> text of every file generated from the table."""
    return generate.generated_files(SCHEMA)


def markdown_reference() -> str:
    """The text of ``docs/config.md``: one table row per key, generated from :data:`SCHEMA`."""
    return generate.markdown_reference(SCHEMA)


def main(argv: list[str] | None = None) -> int:
    """``python -m tmrl.config.schema``: print or write the generated reference and default file.

    Args:
        argv: the command-line arguments (default: ``sys.argv[1:]``).
    """
    return generate.main(SCHEMA, argv)


if __name__ == "__main__":
    sys.exit(main())
