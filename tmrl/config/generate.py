"""The files generated from the configuration schema: ``docs/config.md`` (the reference table),
``config/config.json`` (the defaults) and the example ``config/*.json`` files (the defaults with the
changes of :data:`EXAMPLES`).

Each generator takes the table (:data:`tmrl.config.schema.SCHEMA`), which
:mod:`tmrl.config.schema` passes in; regenerate the files after a change with::

    python -m tmrl.config.schema --write

Nothing here reads a file or touches the disk at import.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

from tmrl.config.checks import check_consistency
from tmrl.config.spec import NO_CLASS_DEFAULT, Section, Spec, join_key, show

__all__ = ["EXAMPLES", "default_config_json", "example_json", "generated_files", "main", "markdown_reference"]

_DESCRIPTION = "``python -m tmrl.config.schema``: print or write the generated reference and default file."



def default_config_json(table: Section) -> str:
    """The text of the shipped ``config/config.json``: the defaults, indented, ending in a newline.

    Args:
        table: the schema (:data:`tmrl.config.schema.SCHEMA`).
    """
    return json.dumps(table.default_value(), indent=2) + "\n"


_GENERIC_TRAINING: dict[str, Any] = {
    "RW_MAX_SAMPLES_PER_EPISODE": 200,
    "MAX_EPOCHS": 20,
    "ROUNDS_PER_EPOCH": 10,
    "TRAINING_STEPS_PER_ROUND": 100,
    "MAX_TRAINING_STEPS_PER_ENVIRONMENT_STEP": 1.0,
    "ENVIRONMENT_STEPS_BEFORE_TRAINING": 1000,
    "UPDATE_MODEL_INTERVAL": 100,
    "UPDATE_BUFFER_INTERVAL": 100,
    "MEMORY_SIZE": 100000,
    "BATCH_SIZE": 256,
}
_GENERIC_ALG: dict[str, Any] = {
    "LEARN_ENTROPY_COEF": True,
    "LR_ACTOR": 0.001,
    "LR_CRITIC": 0.001,
    "LR_ENTROPY": 0.001,
    "GAMMA": 0.99,
    "ALPHA": 0.2,
    "TARGET_ENTROPY": None,
    "BETAS_ACTOR": [0.9, 0.999],
    "BETAS_CRITIC": [0.9, 0.999],
}

# The simulator's files: the demo's settings (tmrl.sim.demo.DEMO_SETTINGS), under which a server,
# a trainer and a worker on one machine learn to drive the default track within minutes on a CPU.
_SIM_TRAINING: dict[str, Any] = {
    **_GENERIC_TRAINING,
    "RW_MAX_SAMPLES_PER_EPISODE": 1000,
    "MAX_EPOCHS": 10000,
    "ROUNDS_PER_EPOCH": 10,
    "TRAINING_STEPS_PER_ROUND": 200,
    "UPDATE_MODEL_INTERVAL": 20,
    "UPDATE_BUFFER_INTERVAL": 20,
    "MEMORY_SIZE": 200000,
    # The fast simulator runs far faster than the trainer: keep three samples per update at most.
    "MAX_ENVIRONMENT_STEPS_PER_TRAINING_STEP": 3.0,
    # In real time (SIM_FAST_MODE false) the clock sets the pace and the trainer, otherwise idle, does
    # up to 4 updates per sample: SAC laps in fewer environment steps so (bench/track_learning.py).
    # In fast mode the line above binds first and this one changes nothing. (In real time, set ALG's
    # ALPHA 0.01 and LEARN_ENTROPY_COEF false too, as the demo does: docs/simulator.md.)
    "MAX_TRAINING_STEPS_PER_ENVIRONMENT_STEP": 4.0,
}
_SIM_RTGYM: dict[str, Any] = {
    "time_step_duration": 0.05,
    "start_obs_capture": 0.04,
    "time_step_timeout_factor": 1.0,
    "act_buf_len": 2,
    "benchmark": False,
    "wait_on_done": True,
    "ep_max_length": 1000,
    "interface_kwargs": {"track": "classic"},
}


def _sim_example(interface: str, **env: Any) -> dict[str, Any]:
    return {
        "RUN_NAME": f"{interface.lower()}_sac",
        **_SIM_TRAINING,
        "ALG": _GENERIC_ALG,
        "ENV": {"RTGYM_INTERFACE": interface, "SIM_FAST_MODE": True, "IMG_HIST_LEN": 4, **env,
                "RTGYM_CONFIG": _SIM_RTGYM},
    }


# The benchmark's recommendations for TrackMania's lidar (docs/trackmania.md, "Recommended training
# settings"; bench/track_learning.py names the variant each was measured as): one for a trainer on
# a CPU, one for a trainer on a GPU. The rest is the TrackMania file's.
_RECOMMENDED_ALG: dict[str, Any] = {
    **_GENERIC_ALG,
    "ALPHA_MAX": 0.01,
}
_TM_LIDAR_ENV: dict[str, Any] = {"RTGYM_INTERFACE": "TM20LIDAR", "WINDOW_WIDTH": 958, "WINDOW_HEIGHT": 488}
TM_CPU_SETTING = "SAC-UTD4-FA"
"""The ``track_learning`` variant ``config_tm20lidar_cpu.json`` trains."""
TM_GPU_SETTING = "REDQSAC-UTD8-CAP-R250"
"""The ``track_learning`` variant ``config_tm20lidar_gpu.json`` trains."""

EXAMPLES: dict[str, dict[str, Any]] = {
    "config_tm20lidar.json": {
        "RUN_NAME": "SAC_4_LIDAR_pretrained",
        "ENV": _TM_LIDAR_ENV,
    },
    "config_tm20lidar_cpu.json": {
        "RUN_NAME": "SAC_LIDAR_cpu",
        "MAX_TRAINING_STEPS_PER_ENVIRONMENT_STEP": 4.0,
        "ENVIRONMENT_STEPS_BEFORE_TRAINING": 1000,
        "ALG": {**_GENERIC_ALG, "ALGORITHM": "SAC", "ALPHA": 0.01, "LEARN_ENTROPY_COEF": False},
        "ENV": _TM_LIDAR_ENV,
    },
    "config_tm20lidar_gpu.json": {
        "RUN_NAME": "REDQ_LIDAR_gpu",
        "MAX_TRAINING_STEPS_PER_ENVIRONMENT_STEP": 8.0,
        "ENVIRONMENT_STEPS_BEFORE_TRAINING": 250,
        "ALG": {**_RECOMMENDED_ALG, "ALGORITHM": "REDQSAC", "REDQ_Q_UPDATES_PER_POLICY_UPDATE": 1},
        "ENV": _TM_LIDAR_ENV,
    },
    "config_gym_pendulum.json": {
        "RUN_NAME": "pendulum_sac",
        **_GENERIC_TRAINING,
        "ALG": _GENERIC_ALG,
        "ENV": {"RTGYM_INTERFACE": "GYM", "GYM_ID": "Pendulum-v1", "GYM_KWARGS": {}},
    },
    "config_drone.json": {
        "RUN_NAME": "drone_sac",
        **_GENERIC_TRAINING,
        "ALG": _GENERIC_ALG,
        "ENV": {
            "RTGYM_INTERFACE": "DRONE",
            "RTGYM_CONFIG": {"time_step_duration": 0.05, "start_obs_capture": 0.05, "act_buf_len": 2,
                             "wait_on_done": False, "ep_max_length": 100, "interface_kwargs": {}},
        },
    },
    "config_simlidar.json": _sim_example("SIMLIDAR"),
    "config_simlidarprogress.json": _sim_example("SIMLIDARPROGRESS"),
    "config_simfull.json": _sim_example("SIMFULL", IMG_WIDTH=64, IMG_HEIGHT=64, IMG_GRAYSCALE=True),
}
"""Example files shipped beside the default ``config/config.json``: the defaults with these keys
changed (starting points: copy one over your ``config.json``)."""


def example_json(table: Section, name: str) -> str:
    """The text of the shipped example ``config/<name>``: a complete, valid config.

    Args:
        table: the schema (:data:`tmrl.config.schema.SCHEMA`).
        name: a file name among the keys of :data:`EXAMPLES` (``"config_simlidar.json"``).

    Raises:
        KeyError: ``name`` is not one of :data:`EXAMPLES`.
    """
    cfg = table.check(table.default_value(), "")
    delta = table.check(EXAMPLES[name], "", fill=False)

    def merge(base: dict[str, Any], upd: dict[str, Any], spec: Section) -> dict[str, Any]:
        out = dict(base)
        for k, v in upd.items():
            sub = spec.fields[k]
            out[k] = merge(out[k], v, sub) if isinstance(sub, Section) else v
        return out

    full = merge(cfg, delta, table)
    check_consistency(full)
    return json.dumps(full, indent=2) + "\n"


def generated_files(table: Section) -> dict[str, str]:
    """Repository-relative path -> text of every file generated from the schema.

    Args:
        table: the schema (:data:`tmrl.config.schema.SCHEMA`).
    """
    files = {"docs/config.md": markdown_reference(table), "config/config.json": default_config_json(table)}
    for name in EXAMPLES:
        files[f"config/{name}"] = example_json(table, name)
    return files


def _md_escape(text: str) -> str:
    return text.replace("|", "\\|")


def _feeds_cell(spec: Spec) -> str:
    """``SACAgent(lr_actor=0.001)``-style list of the arguments a key sets, with the class's own
    default where it has one."""
    parts = []
    for target in spec.feeds:
        owner, _, arg = target.partition(".")
        if spec.class_default is NO_CLASS_DEFAULT:
            parts.append(f"`{owner}({arg})`")
        else:
            parts.append(f"`{owner}({arg}={show(spec.class_default, 30)})`")
    return ", ".join(parts)


def _rows(section: Section, path: str, rows: list[str]) -> None:
    for name, spec in section.fields.items():
        key = join_key(path, name)
        if isinstance(spec, Section):
            rows.append(f"| `{key}` | object | | {_md_escape(spec.doc)} (keys below) | |")
            _rows(spec, key, rows)
        else:
            default = "" if spec.default is None and not spec.nullable else f"`{show(spec.default, 60)}`"
            rows.append(f"| `{key}` | {_md_escape(spec.describe())} | {_md_escape(default)} | {_md_escape(spec.doc)} "
                        f"| {_md_escape(_feeds_cell(spec))} |")


def markdown_reference(table: Section) -> str:
    """The text of ``docs/config.md``: one table row per key.

    Args:
        table: the schema (:data:`tmrl.config.schema.SCHEMA`).
    """
    rows: list[str] = []
    _rows(table, "", rows)
    head = [
        "# config.json reference",
        "",
        "<!-- Generated from tmrl/config/schema.py by `python -m tmrl.config.schema --write`; do not edit. -->",
        "",
        "`config.json` lives in `config/` of the data folder (`$TMRL_DATA`, or `~/TmrlData` when it is",
        "not set); `python -m tmrl --install` creates it with a fresh random `PASSWORD`. A file written for",
        "the original tmrl 0.7 loads unchanged.",
        "",
        "- A missing key takes the default below.",
        "- An unknown key, a value of the wrong type or out of range stops the command with exit code 2",
        "  and one line naming the key path, the value found and what is expected.",
        "- `python -m tmrl ... -d '{\"ALG\": {\"LR_ACTOR\": 0.0001}}'` (JSON or a Python literal) overrides",
        "  keys for one run. Sections merge key by key; free-form objects (`GYM_KWARGS`,",
        "  `interface_kwargs`) are replaced as a whole. `python -m tmrl --print-config` shows the result.",
        "- Choices (`ALGORITHM`, `RTGYM_INTERFACE`, optimizers) are matched without regard to case.",
        "",
        "- The last column names the constructor argument each key sets when `python -m tmrl` builds",
        "  the objects, and that argument's own default in the class (what a script gets when it builds",
        "  the class itself without that argument; the defaults of tmrl 0.7.1's classes and of its",
        "  `config.json` differ in places, and both are kept).",
        "",
        "| key | expected | default | meaning | sets (class default) |",
        "|---|---|---|---|---|",
    ]
    return "\n".join(head + rows) + "\n"


def _repo_root() -> Path:
    return Path(__file__).resolve().parents[2]


def main(table: Section, argv: list[str] | None = None) -> int:
    """``python -m tmrl.config.schema``: print or write the generated reference and default file.

    Args:
        table: the schema (:data:`tmrl.config.schema.SCHEMA`).
        argv: the command-line arguments (default: ``sys.argv[1:]``).
    """
    parser = argparse.ArgumentParser(prog="python -m tmrl.config.schema", description=_DESCRIPTION)
    group = parser.add_mutually_exclusive_group(required=True)
    group.add_argument("--markdown", action="store_true", help="print docs/config.md")
    group.add_argument("--json", action="store_true", help="print the default config.json")
    group.add_argument("--write", action="store_true",
                       help="write docs/config.md and the config/*.json files of the source checkout")
    args = parser.parse_args(argv)
    if args.markdown:
        sys.stdout.write(markdown_reference(table))
    elif args.json:
        sys.stdout.write(default_config_json(table))
    else:
        root = _repo_root()
        for rel, text in generated_files(table).items():
            (root / rel).parent.mkdir(parents=True, exist_ok=True)
            (root / rel).write_text(text, encoding="utf-8")
            print(f"wrote {root / rel}")
    return 0
