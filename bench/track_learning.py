"""Learning in environment steps: how many simulator steps each agent needs to complete a lap,
on the built-in tracks, with the simulator's lidar observations in fast mode (and Pendulum-v1), or
from its images (``--interface SIMFULL``).

    python -m bench track_learning                 # the default agents, oval/classic/technical, 5 seeds
    python -m bench track_learning --quick         # a CI-sized check (one seed, classic, 1,000 steps)
    python -m bench track_learning --agents SAC,SAC-UTD2,SAC-UTD4 --tracks classic --seeds 5 --jobs 2
    python -m bench track_learning --floor         # the least time the full run can take on this machine
    python -m bench track_learning --device cpu    # on the CPU even where there is a GPU
    python -m bench track_learning --interface SIMFULL --device cuda --jobs 3   # from pixels (a GPU host)
    python -m bench track_learning --interface SIMFULL --quick                  # its CI-sized check

In real time an environment step costs 50 ms of somebody's afternoon whatever the computer, so
the figure that matters is steps, not updates per second. Each run is a fresh process with one
torch thread (``--jobs`` of them at once): a plain synchronous loop (one environment step, then
``UTD`` updates after the variant's uniformly random start, :data:`START_STEPS` unless it names
its own; ``--start-steps`` sets one for all), the samples going through a
standalone :class:`tmrl.networking.RolloutWorker` (the simulator's preprocessor and compressor)
into the trainer's replay memory every ``--append-every`` steps. Every ``--eval-every`` steps one
deterministic test episode is driven (not counted as training steps). The memory's batches, the
agent and the actors train and act on ``--device`` (default ``auto``: the GPU when PyTorch sees
one, which the first printed line names; ``cpu``, ``cuda`` or ``cuda:N`` to choose); ``--merge``
refuses to join records taken on different devices.

Printed per track and agent (median, min and max over the seeds): environment steps to the first
completed lap (training or test episode; "-" where a seed never lapped: then the median counts it
as not reached), steps to a lap within 10 % of the best lap any agent reached on that track, the
best lap time and its ratio to the track's reference lap (:mod:`tmrl.sim.reference`, a driven
planned lap), and the wall time on this machine. ``--floor`` runs nothing to the end: it counts the
matrix products of each variant's update (:func:`update_gflop_per_step`) and prints the time the
runs' updates need at this core's best matrix-product rate (:func:`matmul_gflops`), the floor
under the whole benchmark's wall time. Pendulum (``--pendulum``): steps to a mean test
return above -200. A PNG of the curves (training episode returns against environment steps,
median and range over the seeds, one panel per track) goes beside the JSONL record in bench/out/.

Variants (``--agents``): ``SAC-TMRL`` is SAC with tmrl's default ``ALG`` settings (those the
TrackMania lidar config ships: learning rates 1e-5/5e-5, gamma 0.995, fixed alpha 0.01) at its
``MAX_TRAINING_STEPS_PER_ENVIRONMENT_STEP`` of 4; ``SAC`` is SAC at the demo's learning rates
(1e-3, gamma 0.99) with a learned alpha from 0.2 at 1 update per step, ``SAC-UTD2`` and
``SAC-UTD4`` the same at 2 and 4, ``SAC-UTD4-LR3`` at 4 with learning rates 3e-4, ``SAC-UTD4-TE6``
at 4 with a target entropy of -6 instead of -3; ``SAC-UTD4-FA`` is the demo's setting in real time
(since 2026-11-26): 4 updates per step with tmrl's fixed entropy coefficient 0.01 (``SAC-UTD8-FA``
the same at 8, ``SAC-UTD4-A003`` and ``-A005`` at 0.003 and 0.005, ``SAC-UTD4-FA-R250`` with 250
random steps first instead of 1,000); ``SAC-UTD8-R250`` is the learned alpha at 8 updates per step
after 250 random steps, ``SAC-UTD8-CAP`` and ``SAC-UTD4-CAP`` the same at 8 and 4 with the
coefficient held at or under 0.01 once it has fallen there (the agents' ``alpha_max``, ``ALG.ALPHA_MAX``);
``SAC-UTD4-NB-R250``, ``-SH-R250`` and ``-CL-R250`` are the learned alpha at 4 after 250 random
steps with another entropy term in the critics' target: none, one measured from the target
entropy, one that is only ever a bonus (screens: :func:`_entropy_term_in_target`);
``SAC-UTD4-LN-R250`` and ``SAC-UTD8-LN-R250`` the learned alpha at 4 and 8 after 250 random steps
with layer-normalised critics (DroQ's lidar critics without dropout); ``REDQSAC-UTD4-R250`` is
REDQ-SAC at the demo's settings with the policy updated at each of its 4 critic updates per step,
after 250 random steps, and ``REDQSAC-N5-UTD4-R250`` the same with five critics instead of ten
(about 1.7 times the updates per second on one core), ``REDQSAC-UTD4-CAP-R250`` the ten with the
coefficient held at or under 0.01 once it has fallen there, ``REDQSAC-UTD8-CAP-R250`` the same at
8 updates per step, ``REDQSAC-UTD4-CAP-NS3-R250`` the same at 4 with three-step returns in the
critics' target; ``REDQSAC``, ``DROQ``, ``CROSSQ`` and
``TQC`` use their class defaults (their papers'), each with the lidar model of its kind; ``BRO`` and
``SIMBAV2`` too (at 2 updates per step, BRO-fast's ratio), and the ``BRO-*-CAP-R250`` and
``SIMBAV2-*-CAP-R250`` screens are those agents at the capped screens' settings (learning rates
1e-3, the coefficient learned from 0.2 and held at or under 0.01, 250 random steps) at the ratio
their name gives, ``-W128`` with critics 128 wide, ``-B0`` with BRO's optimistic target
(pessimism 0), ``-B2`` with two residual blocks, ``-NS3`` with three-step returns (the critics'
targets of :func:`_n_step_targets`). ``SAC-W128-UTD4-CAP-R250`` and ``SAC-W128-UTD8-CAP-R250`` are
SAC at the capped screens' settings with actor and critics 128 wide; ``REDQSAC-W64-UTD8-CAP-R250``
and ``REDQSAC-W128-N5-UTD8-CAP-R250`` are ``REDQSAC-UTD8-CAP-R250`` with networks 64 wide, and 128
wide with five critics (``hidden_sizes``: the cheaper updates a CPU trainer keeps up with). The
update-to-data ratio of each variant is in :data:`VARIANTS` (``--utd`` overrides it for all); a run
compares :data:`DEFAULT_AGENTS` unless ``--agents`` names others. Budgets per track are in
:data:`PROFILES`: on ``classic`` every run drives its whole budget, so that best laps compare at an
equal number of steps; on ``oval`` and ``technical`` a run ends 500 steps after its first lap.

From pixels (``--interface SIMFULL``; the default, ``SIMLIDAR``, is everything above). The image
variants (:data:`PIXEL_VARIANTS`) run on the simulator's full interface (speed, gear, rpm and a
history of 4 grayscale 64x64 frames, uint8) with the objects a ``SIMFULL`` config builds
(:func:`tmrl.assembly.assemble`: the fast environment, the preprocessor, the sample compressor, the
replay memory, the actor and the agent), each variant being a set of ``config.json`` keys over the
defaults (:func:`pixel_config`). ``DRQ`` is the recommended image agent: DrQ
(:mod:`tmrl.algorithms.drq`: uint8 frames to the model, ``RawImageMemory``, random shifts of 4
pixels) at DrQ's learning rates 1e-3, initial entropy coefficient 0.1 (learned, target ``-3``),
target factor 0.99 and gamma 0.99, Adam's default betas, 1,000 random steps (DrQ's seed steps,
tmrl's ``ENVIRONMENT_STEPS_BEFORE_TRAINING``) and 8 updates per environment step, the ratio of
this project's lidar recommendation (not measured from pixels yet; ``DRQ-UTD4`` and ``DRQ-UTD1``,
the papers' one update per step, are the screens around it). ``SAC-TMRL-CNN`` is tmrl's
``TM20FULL`` setting: SAC with tmrl's VanillaCNN actor-critic (:class:`tmrl.driving.models.CNNActorCritic`
at its default sizes, one CNN per actor and critic), the ``ImageMemory`` of float frames and
tmrl's default ``ALG`` values (the ``SAC-TMRL`` row's: learning rates 1e-5/5e-5, gamma 0.995,
fixed alpha 0.01, betas 0.997), 4 updates per step after 1,000 random steps. Beside them, on the
same tracks, seeds and budgets, the lidar recommendation :data:`LIDAR_REFERENCE` runs on
``SIMLIDAR`` (any lidar variant named in ``--agents`` does: a lidar model reads no images), so that
one table holds the image rows and their lidar reference. Every row's record names its interface
(``"interface"`` in each measure, and the settings' ``interfaces``); ``--merge`` refuses records of
two interfaces as it refuses two devices. The budgets (:data:`PROFILES` ``"pixels"``: ``oval``
10,000 steps, ending 500 steps after the first lap; ``classic`` 20,000, every run to its end;
``oval,classic`` by default, 3 seeds) are sized for an H100 host on the assumption that the image
trainer reaches about 800 updates per second there (the target of this benchmark, not yet
measured): a ``DRQ`` run on ``classic`` is 19,000 training steps x 8 updates = 152,000 updates,
190 s at that rate, plus its 20,000 environment steps and up to 40 test episodes (a step of the
simulator with the image policy acting took about a millisecond on the development CPU), within the
8 minutes a seed is given; ``--jobs 3`` runs three seeds side by side on the host's cores. On a 2-core CPU the same
update runs at 1.63 per second at batch 256 (docs/benchmarks.md, "From pixels"): about 26 hours for
that run. ``--quick`` with ``SIMFULL`` is a CI-sized check (one seed, ``classic``, 200 steps of
which the last 10 train, batches of 8). ``--floor`` and ``--pendulum`` go with ``SIMLIDAR`` only.
"""

from __future__ import annotations

import argparse
import functools
import json
import os
import statistics
import subprocess
import sys
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor, as_completed
from pathlib import Path
from typing import Any

from bench import harness
from bench.pendulum_learning import _feed_and_train, _parts, _UniformActor

TRACKS = ("oval", "classic", "technical")

#: label -> (ALG.ALGORITHM, settings source, updates per environment step)
VARIANTS: dict[str, tuple[str, str, int]] = {
    "SAC-TMRL": ("SAC", "tmrl", 4),
    "SAC": ("SAC", "demo", 1),
    "SAC-UTD2": ("SAC", "demo", 2),
    "SAC-UTD4": ("SAC", "demo", 4),
    "SAC-UTD4-LR3": ("SAC", "demo", 4),
    "SAC-UTD4-FA": ("SAC", "demo", 4),
    "SAC-UTD8-FA": ("SAC", "demo", 8),
    "SAC-UTD4-TE6": ("SAC", "demo", 4),
    "SAC-UTD4-A003": ("SAC", "demo", 4),
    "SAC-UTD4-A005": ("SAC", "demo", 4),
    "SAC-UTD8-R250": ("SAC", "demo", 8),
    "SAC-UTD8-CAP": ("SAC", "demo", 8),
    "SAC-UTD4-CAP": ("SAC", "demo", 4),
    "SAC-UTD4-FA-R250": ("SAC", "demo", 4),
    "SAC-UTD4-NB-R250": ("SAC", "demo", 4),
    "SAC-UTD4-SH-R250": ("SAC", "demo", 4),
    "SAC-UTD4-CL-R250": ("SAC", "demo", 4),
    "SAC-UTD4-LN-R250": ("SAC", "demo", 4),
    "SAC-UTD8-LN-R250": ("SAC", "demo", 8),
    "REDQSAC-UTD4-R250": ("REDQSAC", "demo", 4),
    "REDQSAC-N5-UTD4-R250": ("REDQSAC", "demo", 4),
    "REDQSAC-UTD4-CAP-R250": ("REDQSAC", "demo", 4),
    "REDQSAC-UTD8-CAP-R250": ("REDQSAC", "demo", 8),
    "REDQSAC-UTD4-CAP-NS3-R250": ("REDQSAC", "demo", 4),
    "REDQSAC": ("REDQSAC", "class", 4),
    "DROQ": ("DROQ", "class", 4),
    "CROSSQ": ("CROSSQ", "class", 1),
    "TQC": ("TQC", "class", 1),
    "BRO": ("BRO", "class", 2),
    "BRO-UTD2-CAP-R250": ("BRO", "demo", 2),
    "BRO-UTD4-CAP-R250": ("BRO", "demo", 4),
    "BRO-UTD8-CAP-R250": ("BRO", "demo", 8),
    "BRO-B0-UTD4-CAP-R250": ("BRO", "demo", 4),
    "BRO-W128-UTD4-CAP-R250": ("BRO", "demo", 4),
    "BRO-B2-UTD4-CAP-R250": ("BRO", "demo", 4),
    "BRO-W128-UTD8-CAP-R250": ("BRO", "demo", 8),
    "BRO-W128-UTD8-CAP-NS3-R250": ("BRO", "demo", 8),
    "BRO-W128-UTD3-CAP-R250": ("BRO", "demo", 3),
    "BRO-W128-UTD3-CAP-NS3-R250": ("BRO", "demo", 3),
    "SAC-W128-UTD4-CAP-R250": ("SAC", "demo", 4),
    "REDQSAC-W64-UTD8-CAP-R250": ("REDQSAC", "demo", 8),
    "REDQSAC-W128-N5-UTD8-CAP-R250": ("REDQSAC", "demo", 8),
    "SAC-W128-UTD8-CAP-R250": ("SAC", "demo", 8),
    "SIMBAV2": ("SIMBAV2", "class", 2),
    "SIMBAV2-UTD2-CAP-R250": ("SIMBAV2", "demo", 2),
    "SIMBAV2-UTD4-CAP-R250": ("SIMBAV2", "demo", 4),
}

#: The agents a run compares unless ``--agents`` says otherwise: tmrl's SAC, the demo's real-time
#: settings on a CPU (``--algorithm SAC``'s, and the default's since 2026-12-02) and the papers' agents (the other variants are the ratio, learning-rate and entropy study).
DEFAULT_AGENTS: tuple[str, ...] = ("SAC-TMRL", "SAC-UTD4-FA", "SAC-W128-UTD8-CAP-R250", "REDQSAC", "DROQ", "CROSSQ",
                                   "TQC")

#: How a ``demo`` variant departs from its base: SAC at the demo's learning rates, gamma and polyak
#: with an entropy coefficient learned from 0.2 toward SAC's ``-act_dim`` (the demo's in fast mode,
#: and in real time until 2026-11-26, when it took ``SAC-UTD4-FA``'s fixed coefficient, tmrl's 0.01),
#: and :data:`START_STEPS` random steps. Keys: ``lr``, ``alpha``, ``learn_entropy_coef``,
#: ``target_entropy``, ``alpha_max`` (the screens' ceiling, the agents' own, ``ALG.ALPHA_MAX``), ``start_steps``,
#: ``backup_entropy`` (True: SAC's target; False, ``"shifted"``, ``"bonus"``: the ``-NB``, ``-SH``
#: and ``-CL`` screens, :func:`_entropy_term_in_target`), ``critic_layer_norm`` (the ``-LN`` screens:
#: critics whose hidden layers are ``Linear -> LayerNorm -> ReLU``, DroQ's lidar critics without
#: dropout, under SAC's update), ``policy_every`` (critic updates per policy update of a REDQ-SAC
#: or DroQ base; otherwise the update ratio, the papers' once per environment step), ``redq_n``
#: (a REDQ-SAC base's number of critics, ``ALG.REDQ_N``; otherwise the paper's 10), ``n_step``
#: (the ``-NS`` screens: critics that regress on ``n``-step returns, :func:`_n_step_targets`),
#: ``agent`` (more keyword arguments of the agent: the BRO screens' ``pessimism``, ``critic_width``,
#: ``critic_blocks``), ``hidden_sizes`` (the widths of the lidar model's actor and critics).
DEMO_OVERRIDES: dict[str, dict[str, Any]] = {
    "SAC-UTD4-LR3": {"lr": 3e-4},
    "SAC-UTD4-FA": {"alpha": 0.01, "learn_entropy_coef": False},
    "SAC-UTD8-FA": {"alpha": 0.01, "learn_entropy_coef": False},
    "SAC-UTD4-TE6": {"target_entropy": -6.0},
    "SAC-UTD4-A003": {"alpha": 0.003, "learn_entropy_coef": False},
    "SAC-UTD4-A005": {"alpha": 0.005, "learn_entropy_coef": False},
    "SAC-UTD8-R250": {"start_steps": 250},
    "SAC-UTD8-CAP": {"start_steps": 250, "alpha_max": 0.01},
    "SAC-UTD4-CAP": {"start_steps": 250, "alpha_max": 0.01},
    "SAC-UTD4-FA-R250": {"alpha": 0.01, "learn_entropy_coef": False, "start_steps": 250},
    "SAC-UTD4-NB-R250": {"start_steps": 250, "backup_entropy": False},
    "SAC-UTD4-SH-R250": {"start_steps": 250, "backup_entropy": "shifted"},
    "SAC-UTD4-CL-R250": {"start_steps": 250, "backup_entropy": "bonus"},
    "SAC-UTD4-LN-R250": {"start_steps": 250, "critic_layer_norm": True},
    "SAC-UTD8-LN-R250": {"start_steps": 250, "critic_layer_norm": True},
    "REDQSAC-UTD4-R250": {"start_steps": 250, "policy_every": 1},
    "REDQSAC-N5-UTD4-R250": {"start_steps": 250, "policy_every": 1, "redq_n": 5},
    "REDQSAC-UTD4-CAP-R250": {"start_steps": 250, "policy_every": 1, "alpha_max": 0.01},
    "REDQSAC-UTD8-CAP-R250": {"start_steps": 250, "policy_every": 1, "alpha_max": 0.01},
    "REDQSAC-UTD4-CAP-NS3-R250": {"start_steps": 250, "policy_every": 1, "alpha_max": 0.01, "n_step": 3},
    "BRO-UTD2-CAP-R250": {"start_steps": 250, "alpha_max": 0.01},
    "BRO-UTD4-CAP-R250": {"start_steps": 250, "alpha_max": 0.01},
    "BRO-UTD8-CAP-R250": {"start_steps": 250, "alpha_max": 0.01},
    "BRO-B0-UTD4-CAP-R250": {"start_steps": 250, "alpha_max": 0.01, "agent": {"pessimism": 0.0}},
    "BRO-W128-UTD4-CAP-R250": {"start_steps": 250, "alpha_max": 0.01, "agent": {"critic_width": 128}},
    "BRO-B2-UTD4-CAP-R250": {"start_steps": 250, "alpha_max": 0.01, "agent": {"critic_blocks": 2}},
    "BRO-W128-UTD8-CAP-NS3-R250": {"start_steps": 250, "alpha_max": 0.01, "n_step": 3, "agent": {"critic_width": 128}},
    "BRO-W128-UTD3-CAP-R250": {"start_steps": 250, "alpha_max": 0.01, "agent": {"critic_width": 128}},
    "BRO-W128-UTD3-CAP-NS3-R250": {"start_steps": 250, "alpha_max": 0.01, "n_step": 3, "agent": {"critic_width": 128}},
    "SAC-W128-UTD4-CAP-R250": {"start_steps": 250, "alpha_max": 0.01, "hidden_sizes": (128, 128)},
    "REDQSAC-W64-UTD8-CAP-R250": {"start_steps": 250, "policy_every": 1, "alpha_max": 0.01, "hidden_sizes": (64, 64)},
    "REDQSAC-W128-N5-UTD8-CAP-R250": {"start_steps": 250, "policy_every": 1, "alpha_max": 0.01, "redq_n": 5,
                                      "hidden_sizes": (128, 128)},
    "SAC-W128-UTD8-CAP-R250": {"start_steps": 250, "alpha_max": 0.01, "hidden_sizes": (128, 128)},
    "BRO-W128-UTD8-CAP-R250": {"start_steps": 250, "alpha_max": 0.01, "agent": {"critic_width": 128}},
    "SIMBAV2-UTD2-CAP-R250": {"start_steps": 250, "alpha_max": 0.01},
    "SIMBAV2-UTD4-CAP-R250": {"start_steps": 250, "alpha_max": 0.01},
}

#: Uniformly random environment steps before training (tmrl's ENVIRONMENT_STEPS_BEFORE_TRAINING),
#: for every variant whose :data:`DEMO_OVERRIDES` entry does not name its own ``start_steps``.
START_STEPS = 1_000


def start_steps_of(label: str) -> int:
    """The random steps variant ``label`` takes before training (an image variant: its config's
    ``ENVIRONMENT_STEPS_BEFORE_TRAINING``)."""
    if label in PIXEL_VARIANTS:
        return int(PIXEL_VARIANTS[label].get("ENVIRONMENT_STEPS_BEFORE_TRAINING", START_STEPS))
    return int(DEMO_OVERRIDES.get(label, {}).get("start_steps", START_STEPS))


def utd_of(label: str) -> int:
    """The updates per environment step of variant ``label`` (an image variant: its config's
    ``MAX_TRAINING_STEPS_PER_ENVIRONMENT_STEP``, tmrl's 4 unless it names its own)."""
    if label in PIXEL_VARIANTS:
        return int(PIXEL_VARIANTS[label].get("MAX_TRAINING_STEPS_PER_ENVIRONMENT_STEP", 4.0))
    return VARIANTS[label][2]


#: The observation interfaces ``--interface`` takes: the lidar (the default) or the images.
INTERFACES = ("SIMLIDAR", "SIMFULL")

#: DrQ's ``ALG`` settings, those :mod:`tmrl.algorithms.drq` and docs/simulator.md give: DrQ's
#: learning rates, initial entropy coefficient (learned toward ``-act_dim``) and target factor,
#: gamma 0.99, Adam's default betas, random shifts of 4 pixels.
DRQ_ALG: dict[str, Any] = {
    "ALGORITHM": "DRQ", "DRQ_IMAGE_PAD": 4, "LR_ACTOR": 0.001, "LR_CRITIC": 0.001, "LR_ENTROPY": 0.001,
    "GAMMA": 0.99, "POLYAK": 0.99, "ALPHA": 0.1, "LEARN_ENTROPY_COEF": True, "TARGET_ENTROPY": None,
    "BETAS_ACTOR": [0.9, 0.999], "BETAS_CRITIC": [0.9, 0.999],
}

#: The image variants of ``--interface SIMFULL``: label -> the ``config.json`` keys it sets over
#: the defaults (:func:`tmrl.config.schema.defaults`, tmrl 0.7.1's ``TM20FULL`` file), which
#: :func:`pixel_config` puts on the simulator's full interface. ``DRQ`` is the recommended image
#: agent (8 updates per step, the lidar recommendation's ratio, after DrQ's 1,000 seed steps);
#: ``DRQ-UTD4`` and ``DRQ-UTD1`` the same at 4 and at the papers' one; ``SAC-TMRL-CNN`` is the
#: defaults themselves: tmrl's SAC with its VanillaCNN actor-critic and its ``ALG`` values, 4
#: updates per step after 1,000 random steps.
PIXEL_VARIANTS: dict[str, dict[str, Any]] = {
    "DRQ": {"MAX_TRAINING_STEPS_PER_ENVIRONMENT_STEP": 8.0, "ENVIRONMENT_STEPS_BEFORE_TRAINING": 1000,
            "ALG": DRQ_ALG},
    "DRQ-UTD4": {"MAX_TRAINING_STEPS_PER_ENVIRONMENT_STEP": 4.0, "ENVIRONMENT_STEPS_BEFORE_TRAINING": 1000,
                 "ALG": DRQ_ALG},
    "DRQ-UTD1": {"MAX_TRAINING_STEPS_PER_ENVIRONMENT_STEP": 1.0, "ENVIRONMENT_STEPS_BEFORE_TRAINING": 1000,
                 "ALG": DRQ_ALG},
    "SAC-TMRL-CNN": {},
}

#: The lidar row of a ``SIMFULL`` table: the lidar recommendation of docs/trackmania.md for a trainer
#: that can afford it (a GPU), run on ``SIMLIDAR`` on the same tracks, seeds and budgets.
LIDAR_REFERENCE = "REDQSAC-UTD8-CAP-R250"

#: The agents a ``SIMFULL`` run compares unless ``--agents`` says otherwise.
DEFAULT_PIXEL_AGENTS: tuple[str, ...] = ("DRQ", "SAC-TMRL-CNN", LIDAR_REFERENCE)


def interface_of(label: str) -> str:
    """The interface variant ``label`` runs on: ``SIMFULL`` for an image variant, ``SIMLIDAR``
    for a lidar one (also inside a ``SIMFULL`` run: a lidar model reads no images)."""
    return "SIMFULL" if label in PIXEL_VARIANTS else "SIMLIDAR"

#: Budgets (environment steps per run) by profile.
PROFILES: dict[str, dict[str, Any]] = {
    # classic runs its whole budget (best laps compared at an equal number of steps); on oval and
    # technical a run ends 500 steps after its first lap (the question there is whether it laps)
    "full": {"steps": {"oval": 10_000, "classic": 10_000, "technical": 20_000, "pendulum": 6_000},
             "seeds": 5, "eval_every": 500, "settle": {"oval": 500, "technical": 500}},
    "quick": {"steps": {"oval": 1_000, "classic": 1_000, "technical": 1_000, "pendulum": 1_000},
              "seeds": 1, "eval_every": 500, "settle": {}},
    # --interface SIMFULL, sized for an H100 host at the assumed ~800 image updates per second (the
    # module's notes): a DRQ seed on classic in about 5 minutes of the 8 it is given
    "pixels": {"steps": {"oval": 10_000, "classic": 20_000, "technical": 20_000},
               "seeds": 3, "eval_every": 500, "settle": {"oval": 500, "technical": 500},
               "tracks": ("oval", "classic")},
    # its CI-sized check: random steps up to the last 10, which train (every variant's own ratio)
    # on batches of 8; one test episode at the end
    "pixels-quick": {"steps": {"oval": 200, "classic": 200, "technical": 200},
                     "seeds": 1, "eval_every": 200, "settle": {}, "tracks": ("classic",),
                     "train_steps": 10, "batch_size": 8},
}


def profile_name(interface: str, quick: bool) -> str:
    """The :data:`PROFILES` key of a command: ``full``/``quick`` (lidar), ``pixels``/``pixels-quick``."""
    if interface == "SIMFULL":
        return "pixels-quick" if quick else "pixels"
    return "quick" if quick else "full"


# --- one run (child process) ----------------------------------------------------------------------


def _agent(label: str, spaces: tuple[Any, Any], env_name: str, utd: int, device: str = "cpu") -> Any:
    """The agent of variant ``label`` on ``env_name``'s spaces and on ``device``, ``utd`` updates
    per environment step. REDQ-SAC and DroQ update their policy once per environment step, as in their papers
    (their ``q_updates_per_policy_update`` is the update-to-data ratio), unless the variant's
    :data:`DEMO_OVERRIDES` entry names its own ``policy_every``."""
    from tmrl.algorithms import agent_class
    from tmrl.config.schema import AGENT_CLASSES, arguments, defaults

    alg, source, _ = VARIANTS[label]
    cls = agent_class(alg)
    kwargs: dict[str, Any] = {}
    policy_every = utd
    if env_name != "pendulum":
        kwargs["model_cls"] = _lidar_model(alg)
    if source == "tmrl":  # tmrl's shipped ALG defaults (the TrackMania lidar config's)
        kwargs.update(arguments(defaults(), AGENT_CLASSES[alg]))
    elif source == "demo":
        from tmrl.sim.demo import DEMO_SETTINGS as S

        v = {"lr": S["lr"], "alpha": 0.2, "learn_entropy_coef": True, "target_entropy": None, "alpha_max": None,
             "backup_entropy": True, "critic_layer_norm": False, "policy_every": utd, "redq_n": None,
             **DEMO_OVERRIDES.get(label, {})}
        kwargs.update(lr_actor=v["lr"], lr_critic=v["lr"], lr_entropy=v["lr"], gamma=S["gamma"], polyak=S["polyak"],
                      alpha=v["alpha"], learn_entropy_coef=v["learn_entropy_coef"], target_entropy=v["target_entropy"],
                      alpha_max=v["alpha_max"])
        policy_every = v["policy_every"]
        if v["critic_layer_norm"] and env_name != "pendulum":
            kwargs["model_cls"] = functools.partial(_lidar_model("DROQ"), dropout_rate=0.0)
        if v["redq_n"] is not None:
            kwargs["n"] = v["redq_n"]
        if v.get("hidden_sizes") is not None:  # the -W screens of SAC: actor and critics that wide
            kwargs["model_cls"] = functools.partial(kwargs["model_cls"], hidden_sizes=tuple(v["hidden_sizes"]))
        kwargs.update(v.get("agent", {}))
    if alg in ("REDQSAC", "DROQ"):
        kwargs["q_updates_per_policy_update"] = policy_every
    agent = cls(*spaces, device, **kwargs)
    if source == "demo" and v["backup_entropy"] is not True:
        _entropy_term_in_target(agent, v["backup_entropy"])
    return agent


def _entropy_term_in_target(agent: Any, how: bool | str = False) -> None:
    """The critics' target with another entropy term than SAC's ``- alpha log pi(a'|o')``.

    ``how=False`` (the ``-NB`` screens): none, ``r + gamma (1 - terminated) Q_targ(o', a')`` with
    ``a' ~ pi(.|o')``; ``"shifted"`` (``-SH``): the term measured from the target entropy ``H``,
    ``- alpha (log pi(a'|o') + H)``, zero on average once the policy's entropy sits at its target;
    ``"bonus"`` (``-CL``): ``- alpha min(log pi(a'|o'), 0)``, a bonus that never turns into a cost
    of going on. The actor's and the coefficient's losses keep theirs. A wrapper of the agent's
    step (the autograd path), not an agent setting: the screens found that none keeps the laps and
    each delays the first (docs/benchmarks.md)."""
    import torch

    target_value = agent.target_value
    agent.fused_update = None  # the fused update computes its own target

    def target_with_term(batch: Any, alpha: Any) -> Any:
        d = batch.terminated.reshape(-1)
        if how == "shifted":
            return target_value(batch, alpha) - agent.gamma * (1.0 - d) * alpha * agent.target_entropy
        if how == "bonus":
            a2, logp_a2 = agent.actor(batch.next_obs)
            q2 = agent.target_q(batch.next_obs, a2)
            return batch.rew.reshape(-1) + agent.gamma * (1.0 - d) * (q2 - alpha * logp_a2.clamp(max=0.0))
        return target_value(batch, torch.zeros_like(alpha))

    agent.target_value = target_with_term


def _n_step_targets(agent: Any, memory: Any, n: int) -> None:
    """The ``-NS`` screens: the critics regress on ``n``-step returns,
    ``sum_{k<K} gamma^k r_{t+k} + gamma^K (1 - terminated_{t+K-1}) (Q_targ(o_{t+K}, a') - alpha log pi(a'|o_{t+K}))``
    with ``K = n``, or fewer where the episode ends (terminated or truncated) or the memory's newest
    sample comes first; the actor's and the coefficient's losses are unchanged. ``memory`` (a
    :class:`~tmrl.memory.GenericTorchMemory` of one worker that never wraps, as in :func:`run`)
    draws the batches, the agent's target takes each one's own ``gamma^K``. Wrappers of
    ``memory.sample`` and ``agent.target_value`` (the autograd path), not settings of either."""
    import numpy as np
    import torch

    from tmrl.batch import Batch
    from tmrl.memory import to_torch

    store, links, gamma = memory._storage, memory._links, float(agent.gamma)
    discount: dict[str, torch.Tensor] = {}

    def sample(indices: Any = None) -> Batch:
        if store.total > store.capacity:
            raise RuntimeError("the n-step screen needs a memory that never wraps")
        slots = memory.sample_indices() if indices is None else links.check_slots(indices)
        ends, ret = slots.copy(), store.rew[slots].astype(np.float64)
        disc = np.full(len(slots), gamma)
        going = ~(store.terminated[slots] | store.truncated[slots])
        for _ in range(1, n):
            # one worker's memory that never wraps: the next slot is the episode's next step
            nxt = np.minimum(ends + 1, store.total - 1)
            ok = going & (ends + 1 < store.total)
            ends = np.where(ok, nxt, ends)
            ret = ret + np.where(ok, disc * store.rew[nxt], 0.0)
            disc = np.where(ok, disc * gamma, disc)
            going = ok & ~(store.terminated[ends] | store.truncated[ends])
        dev = memory.device
        discount["now"] = torch.as_tensor(disc, dtype=torch.float32, device=dev)
        return Batch(to_torch(memory.build_obs(links.prev_slots(slots)), dev), to_torch(store.act[slots], dev),
                     torch.as_tensor(ret, dtype=torch.float32, device=dev), to_torch(memory.build_obs(ends), dev),
                     torch.as_tensor(store.terminated[ends], dtype=torch.float32, device=dev),
                     torch.as_tensor(store.truncated[ends], dtype=torch.float32, device=dev))

    target_value = agent.target_value
    agent.fused_update = None  # the fused update computes its own target

    def n_step_target(batch: Any, alpha: Any) -> Any:
        # gamma (1 - d) (Q_targ - alpha log pi) at o_{t+K}, rescaled to gamma^K
        bootstrap = target_value(batch._replace(rew=torch.zeros_like(batch.rew)), alpha)
        # (B,) for SAC's value, (B, M) for a distributional critic's atoms
        shape = (-1,) + (1,) * (bootstrap.dim() - 1)
        return batch.rew.reshape(shape) + bootstrap * (discount["now"] / gamma).reshape(shape)

    memory.sample, agent.target_value = sample, n_step_target


def _lidar_model(alg: str) -> Any:
    """The lidar actor-critic of agent ``alg`` (:data:`tmrl.driving.models.LIDAR_MODELS`)."""
    from tmrl.driving.models import lidar_model_cls

    return lidar_model_cls(alg)


def pixel_config(label: str, track: str, batch_size: int, memory_size: int = 200_000) -> dict[str, Any]:
    """The validated config of image variant ``label`` on ``track``: the defaults (tmrl's
    ``TM20FULL`` settings), the variant's keys (:data:`PIXEL_VARIANTS`), and the simulator's full
    interface in fast mode with the lidar runs' environment (:func:`tmrl.sim.demo._demo_config`:
    4 frames of 64x64, 2 actions in the observation, episodes of at most 1,000 steps, the default
    reward), ``BATCH_SIZE`` and ``MEMORY_SIZE``."""
    from tmrl.config.loader import deep_merge, validate
    from tmrl.config.schema import defaults
    from tmrl.sim.demo import _demo_config

    cfg = deep_merge(defaults(), PIXEL_VARIANTS[label])
    env = {**_demo_config("SIMFULL", track)["ENV"], "SIM_FAST_MODE": True, "IMG_GRAYSCALE": True}
    cfg = deep_merge(cfg, {"ENV": env, "BATCH_SIZE": int(batch_size), "MEMORY_SIZE": int(memory_size)})
    return validate(cfg, source=f"the {label} variant")


def _pixel_parts(label: str, track: str, batch_size: int, memory_size: int, device: str) -> dict[str, Any]:
    """What :func:`run` needs of image variant ``label``, all from :func:`tmrl.assembly.assemble`
    of its :func:`pixel_config`: the environment factory, the actor class, the worker's
    preprocessor and compressor, the replay memory (batches on ``device``) and the agent factory
    (``agent(spaces, device)``, the config's ``ALG`` and model)."""
    from tmrl.assembly import assemble

    cfg = pixel_config(label, track, batch_size, memory_size)
    built = assemble(cfg)
    return {"env_cls": built.ENV_CLS, "actor_cls": built.POLICY,
            "memory": built.MEMORY(nb_steps=1, device=device),
            "worker": {"obs_preprocessor": built.OBS_PREPROCESSOR, "sample_compressor": built.SAMPLE_COMPRESSOR},
            "max_samples": cfg["ENV"]["RTGYM_CONFIG"]["ep_max_length"],
            "agent": lambda spaces, dev: built.AGENT(*spaces, dev)}


def _observed(env: Any) -> tuple[str, list[list[int]]]:
    """The interface an environment was built with (``SIMLIDAR``, ``SIMFULL``..., ``GYM``) and the
    shapes of its observation's elements: what a run reports it drove, not what it was asked."""
    from tmrl.sim.interfaces import SIM_INTERFACES

    inner = getattr(env.unwrapped, "interface", None)
    name = next((n for n, cls in SIM_INTERFACES.items() if type(inner) is cls), "GYM")
    space = env.observation_space
    elements = list(getattr(space, "spaces", [space]))
    return name, [list(e.shape) for e in elements]


def run(env_name: str, label: str, seed: int, steps: int, utd: int, start_steps: int, eval_every: int,
        batch_size: int, append_every: int, settle: int | None = None,
        on_agent: Callable[[Any], None] | None = None, device: str = "cpu",
        interface: str = "SIMLIDAR") -> dict[str, Any]:
    """One learning run on ``device``: its training episodes (end step, return, lap time or
    None), its test episodes, and timings. With ``settle``, the run ends that many steps after its first lap
    (or at ``steps``). ``on_agent`` is called with the agent once it is built (the floor's FLOP
    count wraps its update there). ``interface``: ``SIMLIDAR`` (a lidar variant of
    :data:`VARIANTS`) or ``SIMFULL`` (an image variant of :data:`PIXEL_VARIANTS`); the result's
    ``interface`` and ``observation`` say what the environment built gave."""
    import numpy as np
    import torch

    from tmrl.networking import RolloutWorker

    if env_name != "pendulum" and interface != interface_of(label):
        raise SystemExit(f"{label} runs on {interface_of(label)}, not {interface}")
    torch.set_num_threads(1)
    torch.manual_seed(seed)
    np.random.seed(seed)
    if interface == "SIMFULL":
        p = _pixel_parts(label, env_name, batch_size, 200_000, device)
    else:
        p = _parts("pendulum" if env_name == "pendulum" else "simlidar", batch_size, 200_000, track=env_name,
                   device=device)
    memory = p["memory"]
    worker_kwargs = dict(env_cls=p["env_cls"], actor_module_cls=p["actor_cls"], standalone=True, model_history=0,
                         max_samples_per_episode=p["max_samples"], model_path=os.devnull + "_none", **p["worker"])
    worker, tester = RolloutWorker(**worker_kwargs), RolloutWorker(**worker_kwargs)
    spaces = (worker.env.observation_space, worker.env.action_space)
    agent = p["agent"](spaces, device) if "agent" in p else _agent(label, spaces, env_name, utd, device)
    n_step = int(DEMO_OVERRIDES.get(label, {}).get("n_step", 1))
    if n_step > 1:
        _n_step_targets(agent, memory, n_step)
    if on_agent is not None:
        on_agent(agent)
    worker.env.action_space.seed(seed)
    worker.actor, tester.actor = _UniformActor(worker.env.action_space), agent.get_actor()
    episodes: list[tuple[int, float, float | None]] = []
    tests: list[tuple[int, float, float | None]] = []
    updates, t_update = 0, 0.0
    start = time.perf_counter()
    obs, _ = worker.reset(collect_samples=True)
    ep_step, ep_ret = 0, 0.0
    end = steps
    for step in range(1, steps + 1):
        if step > end:
            break
        if step == start_steps + 1:
            worker.actor = agent.get_actor()
        ep_step += 1
        obs, rew, terminated, truncated, info = worker.step(obs, test=False, collect_samples=True,
                                                            last_step=ep_step == p["max_samples"])
        ep_ret += float(rew)
        if terminated or truncated:
            lap = info.get("lap_time") if info.get("lap_completed") else None
            episodes.append((step, ep_ret, lap))
            if lap is not None and settle is not None:
                end = min(end, step + settle)
            obs, _ = worker.reset(collect_samples=True)
            ep_step, ep_ret = 0, 0.0
        done, seconds = _feed_and_train(worker, memory, agent, append_every, utd if step > start_steps else 0,
                                        batch_size)
        updates, t_update = updates + done, t_update + seconds
        if step % eval_every == 0:
            tests.append((step, *_test_episode(tester, p["max_samples"])))
            lap = tests[-1][2]
            if lap is not None and settle is not None:
                end = min(end, step + settle)
            print(f"    [{env_name} {label} seed {seed}] step {step:6d} test return {tests[-1][1]:8.1f}"
                  f"{'' if lap is None else f' lap {lap:.2f} s'} ({time.perf_counter() - start:.0f} s)",
                  file=sys.stderr, flush=True)
    observed, shapes = _observed(worker.env)
    return {"episodes": episodes, "tests": tests, "wall_s": time.perf_counter() - start, "updates": updates,
            "steps": min(end, steps),
            "updates_per_s": updates / max(t_update, 1e-9), "interface": observed, "observation": shapes}


def _test_episode(tester: Any, max_samples: int) -> tuple[float, float | None]:
    """One deterministic episode: (return, lap time or None)."""
    obs, _ = tester.reset(collect_samples=False)
    ret = 0.0
    for i in range(max_samples):
        obs, rew, terminated, truncated, info = tester.step(obs, test=True, collect_samples=False,
                                                            last_step=i == max_samples - 1)
        ret += float(rew)
        if terminated or truncated:
            return ret, (info.get("lap_time") if info.get("lap_completed") else None)
    return ret, None


def child_main(argv: list[str]) -> None:
    """``--run JSON``: one run with those keyword arguments; prints its result as JSON."""
    ap = argparse.ArgumentParser()
    ap.add_argument("--run", required=True)
    harness.print_json(run(**json.loads(ap.parse_args(argv).run)))


# --- the floor: the matrix products of a whole run ------------------------------------------------

#: Training steps over which :func:`update_gflop_per_step` counts a variant's updates (a multiple of
#: CrossQ's policy delay of 3, so that its policy updates count in their share).
FLOOR_COUNT_STEPS = 60


def update_gflop_per_step(label: str, start_steps: int | None = None, batch_size: int = 256,
                          count_steps: int = FLOOR_COUNT_STEPS) -> float:
    """The matrix products of variant ``label``'s updates, in GFLOP per environment step of
    training: every update of ``count_steps`` training steps on ``classic``, counted forward and
    backward by ``torch.utils.flop_counter`` in a real :func:`run`, divided by ``count_steps``.
    They depend on the shapes only (not on the machine, nor on when training starts: by default
    after ``batch_size + 10`` random steps, the least that fills a batch)."""
    from torch.utils.flop_counter import FlopCounterMode

    total = [0]

    def count(agent: Any) -> None:
        train = agent.train

        def counted(batch: Any) -> Any:
            with FlopCounterMode(display=False) as counter:
                out = train(batch)
            total[0] += counter.get_total_flops()
            return out

        agent.train = counted

    start = batch_size + 10 if start_steps is None else int(start_steps)
    run("classic", label, 0, start + count_steps, VARIANTS[label][2], start, 10**9, batch_size, 1, on_agent=count)
    return total[0] / count_steps / 1e9


def matmul_gflops(seconds: float = 1.0, sizes: tuple[int, ...] = (256, 512, 1024, 2048)) -> float:
    """This core's best rate of matrix products, GFLOP/s on one torch thread: square float32
    products ``(n, n) @ (n, n)`` timed by trainer_speed's floor (:func:`bench.trainer_speed.floor_ms`:
    into a preallocated output, the median of repeated timings over about ``seconds``), the
    fastest size's rate (larger than any update's own products reach)."""
    import torch

    from bench.trainer_speed import floor_ms

    torch.set_num_threads(1)
    return max(2 * n**3 / (floor_ms([(1, n, n, n)], seconds) / 1000) / 1e9 for n in sizes)


def floor_seconds(gflop_per_step: float, budget: int, start_steps: int, gflops: float) -> float:
    """Seconds of matrix products of one run that trains from ``start_steps`` to ``budget`` steps,
    at ``gflops``: the least time the run's updates can take on one core at that rate."""
    return max(0, int(budget) - int(start_steps)) * float(gflop_per_step) / float(gflops)


def floor_main(labels: list[str], budgets: dict[str, int], settle: dict[str, int | None], start: dict[str, int],
               seeds: int, jobs: int, batch_size: int, rec: Any) -> None:
    """``--floor``: the matrix products of the runs a command would start (``budgets`` per track,
    ``settle`` None where a run drives its whole budget, ``start`` random steps per variant) at
    this core's best rate, per variant and in all, against the 90 minutes the full run is asked to
    fit in."""
    tracks = list(budgets)
    gflops = matmul_gflops()
    print(f"matrix products on one torch thread: at best {gflops:.1f} GFLOP/s (square float32 products, "
          f"load average {harness.load_average():.2f}, {os.cpu_count()} CPUs)")
    rec.add("floor", "matmul_gflops", "ours", gflops, unit="GFLOP/s", echo=False)
    per_track = {t: 0.0 for t in tracks}
    print(f"\n{'agent':<16} {'updates/step':>12} {'GFLOP/step':>10} " + " ".join(f"{t + ' s':>12}" for t in tracks))
    for label in labels:
        g = update_gflop_per_step(label, batch_size=batch_size)
        rec.add("floor", "gflop_per_step", label, g, unit="GFLOP", echo=False)
        cells = []
        for t in tracks:
            budget = budgets[t]
            sec = floor_seconds(g, budget, min(start[label], budget // 2), gflops)  # the runs' own start
            per_track[t] += sec * seeds
            cells.append(f"{sec:12.0f}")
        print(f"{label:<16} {VARIANTS[label][2]:>12} {g:10.2f} " + " ".join(cells))
    whole = sum(per_track.values())
    ends_early = [t for t in tracks if settle.get(t) is not None]
    drives = [t for t in tracks if t not in ends_early]
    least = sum(per_track[t] for t in drives)
    spans = ", ".join(f"{t} {budgets[t]:,}" for t in tracks)
    print(f"\nper run: seconds of matrix products of one run to its budget ({spans} steps, training after "
          "each variant's random start)")
    if ends_early and drives:
        span = (f"between {least / jobs / 60:.0f} min (the {', '.join(drives)} runs alone: they drive their whole "
                f"budget) and {whole / jobs / 60:.0f} min (every run to its budget; {', '.join(ends_early)} runs end "
                "after their first lap)")
    else:
        span = f"{whole / jobs / 60:.0f} min (every run to its budget)"
    print(f"floor of these runs ({seeds} seed{'s' if seeds != 1 else ''}, {jobs} at once, each on a core of its own): {span}; "
          "the full run is asked to fit in 90 min")
    rec.add("floor", "floor_min_all_budgets", "ours", whole / jobs / 60, unit="min", higher_is_better=False, echo=False)
    if ends_early and drives:
        rec.add("floor", "floor_min_whole_budget_tracks", "ours", least / jobs / 60, unit="min",
                higher_is_better=False, echo=False)


# --- figures of a run -----------------------------------------------------------------------------


def laps(res: dict[str, Any]) -> list[tuple[int, float]]:
    """Every completed lap of a run, training and test episodes: (environment step, lap time)."""
    return sorted((s, lap) for s, _, lap in res["episodes"] + res["tests"] if lap is not None)


def first_step(res: dict[str, Any], within: float | None = None) -> int | None:
    """Environment step of the run's first lap (no slower than ``within`` seconds when given)."""
    return next((s for s, lap in laps(res) if within is None or lap <= within), None)


def best_lap(res: dict[str, Any]) -> float | None:
    times = [lap for _, lap in laps(res)]
    return min(times) if times else None


def steps_to_return(res: dict[str, Any], threshold: float) -> int | None:
    return next((s for s, ret, _ in res["tests"] if ret > threshold), None)


def median_or_none(values: list[int | None]) -> float | None:
    """Median where a missing value (not reached) counts as larger than every reached one;
    None when the median itself was not reached."""
    ordered = sorted(values, key=lambda v: (v is None, v or 0))
    mid = ordered[(len(ordered) - 1) // 2] if len(ordered) % 2 else None
    if len(ordered) % 2 == 0:
        a, b = ordered[len(ordered) // 2 - 1], ordered[len(ordered) // 2]
        mid = None if a is None or b is None else (a + b) / 2
    return mid


def settle_per_env(profile: dict[str, Any], envs: list[str], override: int | None) -> dict[str, int | None]:
    """Steps each run goes on after its first lap, per track (None: to the end of its budget):
    the profile's, or ``override`` on every track (0: none ends early)."""
    if override is None:
        return {e: profile["settle"].get(e) for e in envs}
    return {e: override or None for e in envs}


# --- driver ---------------------------------------------------------------------------------------


def _reference(track: str) -> float | None:
    try:
        from tmrl.sim.reference import reference_lap_time
    except ImportError:
        return None
    return reference_lap_time(track)


def _plot(path: Path, results: dict[tuple[str, str], list[dict[str, Any]]], envs: list[str], labels: list[str],
          budgets: dict[str, int]) -> bool:
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
        import numpy as np
    except ImportError:
        return False
    fig, axes = plt.subplots(1, len(envs), figsize=(5.5 * len(envs), 4.2), squeeze=False)
    mixed = any(r.get("interface", "SIMLIDAR") not in ("SIMLIDAR", "GYM") for rs in results.values() for r in rs)
    for ax, env in zip(axes[0], envs):
        grid = np.linspace(0, budgets[env], 60)
        for label in labels:
            runs = results.get((env, label), [])
            curves = []
            for res in runs:
                pts = res["tests"] if env == "pendulum" else res["episodes"]
                if not pts:
                    continue
                xs, ys = np.array([p[0] for p in pts]), np.array([p[1] for p in pts])
                if env != "pendulum":  # mean of the last 5 episodes (fewer at the start)
                    ys = np.array([ys[max(0, i - 4): i + 1].mean() for i in range(len(ys))])
                curves.append(np.interp(grid, xs, ys, left=np.nan, right=np.nan))
            if not curves:
                continue
            arr = np.array(curves)  # drawn while every seed still runs (a run may end after its first lap)
            where = _interface_of_rows(runs)
            tag = f", {where}" if mixed and env != "pendulum" else ""
            line = ax.plot(grid, np.median(arr, axis=0), label=f"{label} ({len(curves)} seeds{tag})")[0]
            if len(curves) > 1:
                ax.fill_between(grid, arr.min(axis=0), arr.max(axis=0), color=line.get_color(), alpha=0.15)
        title = "SIMFULL and SIMLIDAR" if mixed else "SIMLIDAR"
        ax.set_title(env if env == "pendulum" else f"track {env} ({title}, fast mode)")
        ax.set_xlabel("environment steps (50 ms each in real time)")
        ax.set_ylabel("test return" if env == "pendulum" else "training episode return (mean of 5)")
        ax.grid(alpha=0.3)
        if ax.get_legend_handles_labels()[0]:  # a panel with no curve (no episode ended) has no legend
            ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return True


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(prog="python -m bench track_learning", description=__doc__.split("\n\n")[0])
    ap.add_argument("--quick", action="store_true", help="CI-sized: 1 seed, classic only, short budgets")
    ap.add_argument("--interface", type=str.upper, choices=INTERFACES, default="SIMLIDAR",
                    help="SIMLIDAR (default: the lidar variants) or SIMFULL (the image variants, "
                    + ", ".join(PIXEL_VARIANTS) + ", beside lidar variants run on SIMLIDAR; default agents "
                    + ",".join(DEFAULT_PIXEL_AGENTS) + ", tracks oval,classic, 3 seeds)")
    ap.add_argument("--agents", default=None,
                    help="comma-separated among " + ", ".join(VARIANTS) + " (default: " + ",".join(DEFAULT_AGENTS)
                    + "); with --interface SIMFULL also " + ", ".join(PIXEL_VARIANTS))
    ap.add_argument("--tracks", default=None, help="comma-separated among " + ", ".join(TRACKS))
    ap.add_argument("--pendulum", action="store_true", help="also Pendulum-v1 (steps to a test return above -200)")
    ap.add_argument("--seeds", type=int, default=None)
    ap.add_argument("--first-seed", type=int, default=0, help="seeds are FIRST_SEED, FIRST_SEED + 1, ...")
    ap.add_argument("--steps", type=int, default=None, help="environment steps per run (default: the profile's per track)")
    ap.add_argument("--utd", type=int, default=None, help="updates per environment step for every agent "
                    "(default: each variant's own)")
    ap.add_argument("--start-steps", type=int, default=None, help="uniformly random actions first, for every "
                    f"agent (default: each variant's own, {START_STEPS} unless it says otherwise)")
    ap.add_argument("--eval-every", type=int, default=None)
    ap.add_argument("--batch-size", type=int, default=None, help="default 256 (8 for --interface SIMFULL --quick)")
    ap.add_argument("--append-every", type=int, default=10)
    ap.add_argument("--jobs", type=int, default=2, help="runs at once (one torch thread each)")
    ap.add_argument("--settle", type=int, default=None, help="end a run this many steps after its first lap, "
                    "on every track (default: the profile's, per track; 0: run every budget to the end)")
    ap.add_argument("--floor", action="store_true", help="run nothing to the end: the matrix products of the "
                    "runs this command would start, at this core's best rate (the least time they can take here)")
    ap.add_argument("--merge", nargs="+", type=Path, metavar="JSONL",
                    help="run nothing: one table and one PNG of the runs recorded in these files")
    harness.add_device_argument(ap, "auto")
    args = ap.parse_args(argv)
    if args.merge:
        merge_main(args.merge)
        return
    pixels = args.interface == "SIMFULL"
    if pixels and (args.floor or args.pendulum):
        ap.error("--floor and --pendulum go with --interface SIMLIDAR only")
    # --floor counts one CPU core's matrix products: its record is a CPU one whatever --device says
    device = "cpu" if args.floor else harness.resolve_device(ap, args.device)
    name = profile_name(args.interface, args.quick)
    profile = PROFILES[name]
    known = {**VARIANTS, **PIXEL_VARIANTS} if pixels else VARIANTS
    agents = args.agents or ",".join(DEFAULT_PIXEL_AGENTS if pixels else DEFAULT_AGENTS)
    labels = [a.strip().upper() for a in agents.split(",") if a.strip()]
    if set(labels) - set(known):
        hint = "" if pixels or not set(labels) & set(PIXEL_VARIANTS) else " (image variants need --interface SIMFULL)"
        ap.error(f"unknown agent(s) {sorted(set(labels) - set(known))}{hint}: use {', '.join(known)}")
    default_tracks = ",".join(profile.get("tracks", ("classic",) if args.quick else TRACKS))
    tracks = [t for t in (args.tracks or default_tracks).split(",") if t]
    if set(tracks) - set(TRACKS):
        ap.error(f"unknown track(s) {sorted(set(tracks) - set(TRACKS))}: use {', '.join(TRACKS)}")
    envs = tracks + (["pendulum"] if args.pendulum else [])
    seeds = args.seeds or profile["seeds"]
    eval_every = args.eval_every or profile["eval_every"]
    batch_size = args.batch_size or profile.get("batch_size", 256)
    budgets = {e: args.steps or profile["steps"][e] for e in envs}
    utd = {label: args.utd or utd_of(label) for label in labels}
    start = {label: start_steps_of(label) if args.start_steps is None else args.start_steps for label in labels}
    settle = settle_per_env(profile, envs, args.settle)
    interfaces = {label: interface_of(label) for label in labels}

    def run_start(label: str, env: str) -> int:
        """The random steps of one run: the variant's, at most half the budget; a profile with
        ``train_steps`` (the CI check) trains that many last steps instead."""
        if args.start_steps is None and "train_steps" in profile:
            return max(0, budgets[env] - profile["train_steps"])
        return min(start[label], budgets[env] // 2)

    settings = {"profile": name, "budgets": budgets, "utd": utd,
                "start_steps": start, "eval_every": eval_every, "batch_size": batch_size,
                "append_every": args.append_every, "jobs": args.jobs, "torch_threads_per_run": 1, "settle": settle,
                "interface": args.interface, **harness.device_settings(device)}
    if pixels:  # each row's interface, and the config keys of each image variant
        settings.update(interfaces=interfaces, start_steps={label: {e: run_start(label, e) for e in envs}
                                                            for label in labels},
                        pixel_variants={label: PIXEL_VARIANTS[label] for label in labels if label in PIXEL_VARIANTS})
    rec = harness.Recorder("track_learning", settings)
    if args.floor:
        floor_main(labels, {t: budgets[t] for t in tracks}, settle, start, seeds, args.jobs, batch_size, rec)
        rec.close()
        return
    side = harness.ours_side()
    plan = [(env, args.first_seed + seed, label) for env in envs for seed, label in harness.alternate(labels, seeds)]

    def one(job: tuple[str, int, str]) -> tuple[tuple[str, int, str], dict[str, Any]]:
        env, seed, label = job
        kwargs = {"env_name": env, "label": label, "seed": seed, "steps": budgets[env], "utd": utd[label],
                  "start_steps": run_start(label, env), "eval_every": eval_every,
                  "batch_size": batch_size, "append_every": args.append_every, "settle": settle[env],
                  "device": device}
        if pixels:
            kwargs["interface"] = interfaces[label]
        out = subprocess.run(side.command("track_learning", "--run", json.dumps(kwargs)), env=side.env,
                             cwd=side.cwd, stdout=subprocess.PIPE, text=True, check=False)
        if out.returncode != 0:
            raise SystemExit(f"the {label} run on {env}, seed {seed}, failed (exit code {out.returncode})")
        res = json.loads(out.stdout.strip().splitlines()[-1])
        asked = "GYM" if env == "pendulum" else interfaces[label]
        if res.get("interface", asked) != asked:
            raise SystemExit(f"the {label} run on {env}, seed {seed}, drove {res['interface']}, not {asked}")
        return job, res

    t0 = time.perf_counter()
    results: dict[tuple[str, str], list[dict[str, Any]]] = {}
    with ThreadPoolExecutor(max(1, args.jobs)) as pool:
        for future in as_completed([pool.submit(one, job) for job in plan]):  # recorded as they end
            (env, seed, label), res = future.result()
            results.setdefault((env, label), []).append(res)
            row = {"interface": res.get("interface", interfaces[label])}
            rec.add(env, "wall_s", label, res["wall_s"], round=seed, higher_is_better=False, unit="s", **row)
            rec.add(env, "updates_per_s_in_train", label, res["updates_per_s"], round=seed, unit="1/s", **row)
            if env == "pendulum":
                rec.add(env, "steps_to_-200", label, steps_to_return(res, -200.0), round=seed,
                        higher_is_better=False, unit="steps", curve=res["tests"], **row)
            else:
                rec.add(env, "steps_to_first_lap", label, first_step(res), round=seed, higher_is_better=False,
                        unit="steps", laps=laps(res), episodes=res["episodes"], tests=res["tests"],
                        observation=res.get("observation"), **row)
                rec.add(env, "best_lap_s", label, best_lap(res), round=seed, higher_is_better=False, unit="s", **row)
    total = time.perf_counter() - t0
    _print_table(results, envs, labels, budgets, seeds)
    print(f"\nwhole run: {total / 60:.1f} min with {args.jobs} jobs; load average {harness.load_average():.2f}")
    png = rec.path.with_suffix(".png")
    if _plot(png, results, envs, labels, budgets):
        print(f"curves: {png}")
    rec.close()


def load_results(paths: list[Path]) -> tuple[dict[tuple[str, str], list[dict[str, Any]]], dict[str, int], int]:
    """The runs recorded in track_learning JSONL files (several commands, sessions or machines):
    ``{(track, agent): [run, ...]}`` with each run's episodes, tests, wall time and updates per
    second, the largest budget per track, and the most seeds of any agent. A run recorded twice (the
    same track, agent and seed) counts once, the later record winning."""
    runs: dict[tuple[str, str, int], dict[str, Any]] = {}
    budgets: dict[str, int] = {}
    devices: dict[str, Path] = {}
    interfaces: dict[str, Path] = {}
    for path in paths:
        if not Path(path).is_file():
            raise SystemExit(f"{path}: no such record (the JSONL files are in bench/out/)")
        for line in Path(path).read_text(encoding="utf-8").splitlines():
            if not line.strip():
                continue
            rec = json.loads(line)
            if rec.get("kind") == "run":
                if rec.get("bench") != "track_learning":
                    raise SystemExit(f"{path}: not a track_learning record (bench {rec.get('bench')!r})")
                # records from before --device were all taken on the CPU
                device = rec["settings"].get("device", "cpu").split(":")[0]
                devices.setdefault(device, Path(path))
                if len(devices) > 1:
                    first, second = devices.items()
                    raise SystemExit(f"{second[1]} was recorded on {second[0]} and {first[1]} on {first[0]}: "
                                     "merge the records of one device at a time")
                # records from before --interface were all lidar ones
                interfaces.setdefault(rec["settings"].get("interface", "SIMLIDAR"), Path(path))
                if len(interfaces) > 1:
                    first, second = interfaces.items()
                    raise SystemExit(f"{second[1]} was recorded with --interface {second[0]} and {first[1]} with "
                                     f"--interface {first[0]}: merge the records of one interface at a time")
                for env, steps in rec["settings"]["budgets"].items():
                    budgets[env] = max(budgets.get(env, 0), int(steps))
                continue
            if rec.get("kind") != "measure":
                continue
            run = runs.setdefault((rec["case"], rec["side"], int(rec["round"])), {})
            if "interface" in rec:
                run["interface"] = rec["interface"]
            if rec["metric"] == "wall_s":
                run["wall_s"] = rec["value"]
            elif rec["metric"] == "updates_per_s_in_train":
                run["updates_per_s"] = rec["value"]
            elif rec["metric"] in ("steps_to_first_lap", "steps_to_-200"):
                run["episodes"] = [tuple(e) for e in rec.get("episodes", [])]
                run["tests"] = [tuple(t) for t in rec.get("tests", rec.get("curve", []))]
    results: dict[tuple[str, str], list[dict[str, Any]]] = {}
    for (env, label, _), run in sorted(runs.items()):
        if "episodes" in run and "wall_s" in run:
            results.setdefault((env, label), []).append(run)
    seeds = max((len(v) for v in results.values()), default=0)
    return results, budgets, seeds


def merge_main(paths: list[Path]) -> None:
    """``--merge FILE...``: one table and one PNG of the runs of several JSONL records."""
    results, budgets, seeds = load_results(paths)
    if not results:
        raise SystemExit("no track_learning runs in " + ", ".join(map(str, paths)))
    envs = [e for e in (*TRACKS, "pendulum") if any(env == e for env, _ in results)]
    labels = [lab for lab in (*PIXEL_VARIANTS, *VARIANTS) if any(label == lab for _, label in results)]
    _print_table(results, envs, labels, budgets, seeds)
    png = harness.OUT / f"track_learning-merged-{time.strftime('%Y%m%d-%H%M%S')}.png"
    png.parent.mkdir(parents=True, exist_ok=True)
    if _plot(png, results, envs, labels, budgets):
        print(f"curves: {png}")


def _span(values: list[Any], fmt: str = "{:.0f}") -> str:
    got = [v for v in values if v is not None]
    med = median_or_none(values)
    if not got:
        return "not reached"
    text = "-" if med is None else fmt.format(med)
    return f"{text} [{fmt.format(min(got))}..{fmt.format(max(got))}] {len(got)}/{len(values)}"


def _print_table(results: dict[tuple[str, str], list[dict[str, Any]]], envs: list[str], labels: list[str],
                 budgets: dict[str, int], seeds: int) -> None:
    print(f"\nmedian [min..max] reached/seeds over {seeds} seed(s); budgets in environment steps: {budgets}")
    for env in envs:
        print(f"\n{env}")
        if env == "pendulum":
            print(f"  {'agent':9s} {'steps to -200':>30s} {'wall s':>8s}")
            for label in labels:
                runs = results.get((env, label), [])
                print(f"  {label:9s} {_span([steps_to_return(r, -200.0) for r in runs]):>30s} "
                      f"{statistics.median(r['wall_s'] for r in runs):8.0f}")
            continue
        ref = _reference(env)
        bests = [b for runs in (results.get((env, lab), []) for lab in labels) for b in map(best_lap, runs) if b]
        overall = min(bests) if bests else None
        within = overall * 1.1 if overall else None
        print(f"  reference lap {'-' if ref is None else f'{ref:.2f} s'}; best lap of any agent "
              f"{'-' if overall is None else f'{overall:.2f} s'}")
        shown = {lab: _interface_of_rows(results.get((env, lab), [])) for lab in labels}
        mixed = any(i != "SIMLIDAR" for i in shown.values())  # a lidar-only table keeps its columns
        w = max(16, *map(len, labels)) if mixed else 16
        print(f"  {'agent':{w}s} " + (f"{'interface':9s} " if mixed else "") + f"{'steps to first lap':>30s} "
              f"{'steps to lap <= best+10%':>30s} {'best lap s':>26s} {'best/ref':>9s} {'wall s':>8s}")
        for label in labels:
            runs = results.get((env, label), [])
            firsts = [first_step(r) for r in runs]
            near = [first_step(r, within) if within else None for r in runs]
            best = [best_lap(r) for r in runs]
            med_best = median_or_none(best)
            ratio = "-" if ref is None or med_best is None else f"{med_best / ref:.2f}"
            print(f"  {label:{w}s} " + (f"{shown[label]:9s} " if mixed else "") + f"{_span(firsts):>30s} "
                  f"{_span(near):>30s} {_span(best, '{:.2f}'):>26s} {ratio:>9s} "
                  f"{statistics.median(r['wall_s'] for r in runs):8.0f}")


def _interface_of_rows(runs: list[dict[str, Any]]) -> str:
    """The interface a table row's runs drove (records from before ``--interface``: ``SIMLIDAR``)."""
    names = sorted({r.get("interface", "SIMLIDAR") for r in runs}) or ["SIMLIDAR"]
    return "/".join(names)
