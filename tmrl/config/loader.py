"""Locate the data folder, create it on request, and load a validated ``config.json``.

The data folder is ``$TMRL_DATA`` when that variable is set, else ``~/TmrlData``::

    config/config.json   the configuration (created with a fresh random PASSWORD)
    weights/             model weights (worker and trainer copies)
    checkpoints/         training checkpoints
    dataset/             recorded samples
    reward/              recorded reward trajectories
    credentials/         TLS key and certificate
    logs/                log and metrics files

Only :func:`ensure_data_folder` and :func:`install` write anything, and they never overwrite an
existing ``config.json``. :func:`load_config` reads the file (or the defaults when the file does not
exist yet), applies the overrides, and raises a one-line :class:`ConfigError` for any mistake.
"""

from __future__ import annotations

import ast
import json
import logging
import os
import secrets
import tempfile
import threading
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from tmrl import platform
from tmrl.config import schema
from tmrl.config.schema import ConfigError, SchemaViolation

__all__ = [
    "DATA_ENV",
    "ENVIRONMENTS",
    "LAYOUT",
    "OVERRIDE_ENV",
    "ConfigError",
    "DataPaths",
    "InstallReport",
    "SwitchReport",
    "apply_override",
    "config_path",
    "data_folder",
    "data_paths",
    "deep_merge",
    "default_config",
    "dumps",
    "ensure_data_folder",
    "environment_of",
    "install",
    "load_config",
    "parse_override",
    "process_config",
    "set_override_env",
    "shipped_config",
    "switch_environment",
    "validate",
]

logger = logging.getLogger(__name__)

DATA_ENV = "TMRL_DATA"
"""Environment variable naming the data folder (default ``~/TmrlData``)."""

OVERRIDE_ENV = "TMRL_CONFIG_OVERRIDE"
"""Environment variable holding a JSON override that :func:`load_config` applies; the CLI sets it
from ``-d/--config`` so that child processes see the same configuration."""

LAYOUT = ("config", "weights", "checkpoints", "dataset", "reward", "credentials", "logs")
"""Sub-folders of the data folder."""


def data_folder() -> Path:
    """The data folder: ``$TMRL_DATA`` if set (``~`` expanded, made absolute), else ``~/TmrlData``.
    Creates nothing."""
    env = os.environ.get(DATA_ENV, "").strip()
    if env:
        return Path(env).expanduser().absolute()
    return Path.home() / "TmrlData"


def config_path(folder: str | os.PathLike[str] | None = None) -> Path:
    """Path of ``config.json`` in a data folder: ``<folder>/config/config.json``. Creates nothing.

    Args:
        folder: the data folder; None for :func:`data_folder`.
    """
    root = Path(folder) if folder is not None else data_folder()
    return root / "config" / "config.json"


@dataclass(frozen=True)
class DataPaths:
    """Where a run's files live. Every attribute is a :class:`~pathlib.Path`; nothing is created.

    Attributes:
        root: the data folder.
        config_file: ``config/config.json``.
        weights: ``weights/``, the actor's weights files.
        checkpoints: ``checkpoints/``, the trainer's checkpoints.
        dataset: ``dataset/``, for datasets of your own (a memory's ``dataset_path``; tmrl writes
            nothing there).
        reward: ``reward/``, the recorded reward trajectory.
        credentials: ``credentials/``, the TLS key and certificates, or ``TLS_CREDENTIALS_DIRECTORY``
            when that key is not empty.
        logs: ``logs/``, one folder of metrics per run.
        model_worker: ``weights/<RUN_NAME>.tmod``, the weights a worker loads.
        model_trainer: ``weights/<RUN_NAME>_t.tmod``, the weights the trainer writes.
        model_history_prefix: ``weights/<RUN_NAME>_``; a worker keeping a model history appends
            a counter and ``.tmod``.
        checkpoint: ``checkpoints/<RUN_NAME>_t.tcpt``.
        reward_file: ``reward/reward.npy``, the recorded reward trajectory.
    """

    root: Path
    config_file: Path
    weights: Path
    checkpoints: Path
    dataset: Path
    reward: Path
    credentials: Path
    logs: Path
    model_worker: Path
    model_trainer: Path
    model_history_prefix: Path
    checkpoint: Path
    reward_file: Path


def data_paths(cfg: Mapping[str, Any] | None = None, folder: str | os.PathLike[str] | None = None) -> DataPaths:
    """The paths of a run. Creates nothing.

    Args:
        cfg: a loaded config, of which ``RUN_NAME`` and ``TLS_CREDENTIALS_DIRECTORY`` are read;
            None for the defaults.
        folder: the data folder; None for :func:`data_folder`.
    """
    root = Path(folder) if folder is not None else data_folder()
    run = cfg["RUN_NAME"] if cfg is not None else schema.SCHEMA.fields["RUN_NAME"].default
    cred_dir = (cfg or {}).get("TLS_CREDENTIALS_DIRECTORY", "") or ""
    weights = root / "weights"
    checkpoints = root / "checkpoints"
    reward = root / "reward"
    return DataPaths(
        root=root,
        config_file=config_path(root),
        weights=weights,
        checkpoints=checkpoints,
        dataset=root / "dataset",
        reward=reward,
        credentials=Path(cred_dir).expanduser() if cred_dir.strip() else root / "credentials",
        logs=root / "logs",
        model_worker=weights / f"{run}.tmod",
        model_trainer=weights / f"{run}_t.tmod",
        model_history_prefix=weights / f"{run}_",
        checkpoint=checkpoints / f"{run}_t.tcpt",
        reward_file=reward / "reward.npy",
    )


def default_config() -> dict[str, Any]:
    """Every key at its default (the shipped ``config/config.json``, placeholder password)."""
    return schema.defaults()


def dumps(cfg: Mapping[str, Any]) -> str:
    """The indented JSON text written to ``config.json`` (ends with a newline).

    Args:
        cfg: a config (any JSON-serialisable mapping).
    """
    return json.dumps(cfg, indent=2) + "\n"


def _create_exclusive(path: Path, text: str) -> bool:
    """Write ``text`` to ``path`` only if ``path`` does not exist, atomically: the content goes to
    a temporary file that is then hard-linked into place, which fails instead of replacing a file
    another process created meanwhile. Returns True if this call created the file."""
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "w", encoding="utf-8") as f:
            f.write(text)
            f.flush()
            os.fsync(f.fileno())
        try:
            os.link(tmp, path)
        except FileExistsError:
            return False
        except OSError:
            # File systems without hard links: exclusive create is still never an overwrite.
            try:
                with open(path, "x", encoding="utf-8") as f:
                    f.write(text)
            except FileExistsError:
                return False
        return True
    finally:
        platform.remove(tmp)


ENVIRONMENTS: dict[str, str] = {
    "simlidar": "config_simlidar.json",
    "simlidarprogress": "config_simlidarprogress.json",
    "simfull": "config_simfull.json",
    "pendulum": "config_gym_pendulum.json",
    "drone": "config_drone.json",
    "tm20full": "config.json",
    "tm20lidar": "config_tm20lidar.json",
}
"""``--install --env NAME``: the shipped config file each name selects (``config/`` of the
repository, generated from the schema)."""


def shipped_config(env: str) -> dict[str, Any]:
    """The complete shipped config of an environment (with the placeholder password).

    Args:
        env: a name of :data:`ENVIRONMENTS` (``"simlidar"``, ``"pendulum"``...), case-insensitive.

    Raises:
        ConfigError: an unknown name.
    """
    name = ENVIRONMENTS.get(str(env).lower())
    if name is None:
        raise ConfigError(f"--env {env!r} is not a shipped environment: use one of {', '.join(ENVIRONMENTS)}")
    text = schema.default_config_json() if name == "config.json" else schema.example_json(name)
    return json.loads(text)


def environment_of(cfg: Mapping[str, Any]) -> str | None:
    """The name in :data:`ENVIRONMENTS` whose shipped config has the same environment as ``cfg``
    (same ``ENV.RTGYM_INTERFACE``, and same ``ENV.GYM_ID`` for ``GYM``), or ``None``.

    Args:
        cfg: a config (only its ``ENV`` section is read).
    """
    env = cfg.get("ENV", {})
    for name in ENVIRONMENTS:
        shipped = shipped_config(name)["ENV"]
        if shipped["RTGYM_INTERFACE"] == env.get("RTGYM_INTERFACE") and (
            shipped["RTGYM_INTERFACE"] != "GYM" or shipped["GYM_ID"] == env.get("GYM_ID")
        ):
            return name
    return None


def _fresh_config_text(env: str | None = None) -> str:
    cfg = schema.defaults() if env is None else shipped_config(env)
    cfg["PASSWORD"] = secrets.token_urlsafe(24)
    return dumps(cfg)


def _kept_edits(current: Mapping[str, Any], origin: Mapping[str, Any], target: dict[str, Any],
                path: str = "") -> list[str]:
    """Copy into ``target`` every value of ``current`` that differs from ``origin`` (the user's
    edits), outside ``ENV``; returns their key paths."""
    kept = []
    for key, value in current.items():
        full = f"{path}{key}"
        if full in ("ENV", "__VERSION__") or key not in target:
            continue
        if isinstance(value, Mapping) and isinstance(origin.get(key), Mapping) and isinstance(target[key], dict):
            kept += _kept_edits(value, origin[key], target[key], full + ".")
        elif value != origin.get(key):
            target[key] = value
            kept.append(full)
    return kept


@dataclass(frozen=True)
class SwitchReport:
    """What :func:`switch_environment` did.

    Attributes:
        env: the environment name now in ``config.json``.
        changed: whether ``config.json`` was rewritten (False: it already had this environment).
        kept: key paths of the user's edits carried over (``PASSWORD`` among them).
        previous: where the former ``config.json`` was kept (``None`` when unchanged).
    """

    env: str
    changed: bool
    kept: list[str]
    previous: Path | None


def switch_environment(env: str, folder: str | os.PathLike[str] | None = None) -> SwitchReport:
    """Give the existing ``config.json`` the environment of the shipped config ``env``, keeping
    the user's own edits: every key outside ``ENV`` whose value differs from the shipped config
    the file came from (``PASSWORD``, TLS and network settings, changed hyperparameters...) keeps
    its value; ``ENV`` and the keys the user never changed take the new shipped values. The
    former file is kept as ``config.previous.json``.

    Args:
        env: a name of :data:`ENVIRONMENTS`.
        folder: the data folder; None for :func:`data_folder`. Its ``config.json`` must exist.

    Returns:
        What was done; nothing is written when the file already has that environment.

    Raises:
        ConfigError: an unknown name, or a ``config.json`` that does not validate.
    """
    target = shipped_config(env)
    root = Path(folder) if folder is not None else data_folder()
    cfg_file = config_path(root)
    current = _read_config_file(cfg_file)
    if environment_of(current) == env.lower():
        return SwitchReport(env.lower(), False, [], None)
    origin_name = environment_of(current)
    origin = shipped_config(origin_name) if origin_name is not None else schema.defaults()
    kept = _kept_edits(current, origin, target)
    if target["PASSWORD"] == schema.PASSWORD_PLACEHOLDER:  # the file had the placeholder too
        target["PASSWORD"] = secrets.token_urlsafe(24)
    validate(target, source=str(cfg_file))
    previous = cfg_file.with_name("config.previous.json")
    from tmrl.util import atomic_write_text

    atomic_write_text(previous, cfg_file.read_text(encoding="utf-8"))
    atomic_write_text(cfg_file, dumps(target))
    return SwitchReport(env.lower(), True, kept, previous)


@dataclass(frozen=True)
class InstallReport:
    """What :func:`install` found or made.

    Attributes:
        paths: the data folder's paths (default run name).
        created_config: True when ``config.json`` was written by this call (fresh password).
    """

    paths: DataPaths
    created_config: bool


def install(folder: str | os.PathLike[str] | None = None, env: str | None = None) -> InstallReport:
    """Create the data folder layout and, when ``config.json`` is missing, write the default one
    (or the shipped config of ``env``, see :data:`ENVIRONMENTS`) with a fresh random
    ``PASSWORD``. An existing ``config.json`` is never modified here (see
    :func:`switch_environment`).

    Args:
        folder: the data folder; None for :func:`data_folder`.
        env: a name of :data:`ENVIRONMENTS` for the config written, None for the default
            ``config.json`` (TrackMania 2020, full observations).

    Raises:
        ConfigError: the folder cannot be created (a file is in the way, no permission), or an
            unknown ``env``.
    """
    text = _fresh_config_text(env)  # an unknown env fails before anything is created
    root = Path(folder) if folder is not None else data_folder()
    try:
        for sub in LAYOUT:
            (root / sub).mkdir(parents=True, exist_ok=True)
        created = False
        cfg_file = config_path(root)
        if not cfg_file.exists():
            created = _create_exclusive(cfg_file, text)
            if created:
                logger.info("wrote %s with a fresh random PASSWORD", cfg_file)
    except FileExistsError as e:
        raise ConfigError(
            f"cannot create the data folder {root}: {e.filename} exists and is not a folder; "
            f"move it away or set {DATA_ENV} to another folder"
        ) from None
    except PermissionError as e:
        raise ConfigError(
            f"cannot create the data folder {root}: permission denied on {e.filename}; "
            f"set {DATA_ENV} to a folder you can write"
        ) from None
    except NotADirectoryError as e:
        raise ConfigError(
            f"cannot create the data folder {root}: a file is in the way ({e.filename}); "
            f"set {DATA_ENV} to another folder"
        ) from None
    return InstallReport(paths=data_paths(None, root), created_config=created)


def ensure_data_folder(folder: str | os.PathLike[str] | None = None) -> Path:
    """Make sure the data folder and its layout exist (see :func:`install`); returns its path.

    Args:
        folder: the data folder; None for :func:`data_folder`.

    Raises:
        ConfigError: the folder cannot be created.
    """
    return install(folder).paths.root


def _source_name(path: Path) -> str:
    return str(path)


def _violation(source: str, err: SchemaViolation) -> ConfigError:
    return ConfigError(f"{source}: {err.message}")


def validate(raw: Any, source: str = "config.json") -> dict[str, Any]:
    """Validate a complete configuration: fill missing keys with defaults, refuse unknown keys,
    wrong types and out-of-range values, then check the rules that involve several keys.

    Args:
        raw: the parsed JSON.
        source: where ``raw`` came from, put in front of error messages.

    Returns:
        A new dict with every key of the schema, values normalised.

    Raises:
        ConfigError: ``"<source>: <KEY.PATH> must be <expected>, got <value>"``.
    """
    try:
        cfg = schema.SCHEMA.check(raw, "")
        schema.check_consistency(cfg)
    except SchemaViolation as e:
        raise _violation(source, e) from None
    return cfg


def parse_override(text: str, source: str = "--config") -> dict[str, Any]:
    """Parse an override given on the command line: a JSON object, or a Python literal dict
    (``True``, ``None``, single quotes). Never evaluates code.

    Args:
        text: the override's text, e.g. ``'{"ALG": {"LR_ACTOR": 0.0001}}'``; empty gives ``{}``.
        source: where the text came from, put in front of error messages.

    Returns:
        The parsed dict (not yet checked against the schema).

    Raises:
        ConfigError: the text is neither, or not a dict.
    """
    text = text.strip()
    if not text:
        return {}
    try:
        value = json.loads(text)
    except ValueError:
        try:
            value = ast.literal_eval(text)
        except ValueError:  # an expression that is not a literal, e.g. a call: never evaluated
            raise ConfigError(
                f"{source}: not a JSON or Python dict (it holds an expression that is not a plain value: only "
                "numbers, strings, True/False/None, lists and dicts are allowed); write it like "
                "'{\"ALG\": {\"LR_ACTOR\": 0.0001}}'"
            ) from None
        except (SyntaxError, TypeError, MemoryError, RecursionError) as e:
            reason = _syntax_reason(e)
            raise ConfigError(
                f"{source}: not a JSON or Python dict ({reason}); write it like "
                "'{\"ALG\": {\"LR_ACTOR\": 0.0001}}'"
            ) from None
    if not isinstance(value, dict):
        raise ConfigError(
            f"{source}: must be a dict such as '{{\"ALG\": {{\"LR_ACTOR\": 0.0001}}}}', got {schema.show(value)}"
        )
    return value


def route_rtgym_keys(override: Mapping[str, Any]) -> dict[str, Any]:
    """``override`` with the keys of the real-time configuration moved under
    ``ENV.RTGYM_CONFIG``.

    tmrl 0.7's ``-d`` took the rtgym configuration (``{"benchmark": true}``,
    ``{"time_step_duration": 0.1}``); ours takes ``config.json`` keys. Keys that are not
    ``config.json``'s top-level keys but are ``ENV.RTGYM_CONFIG``'s are moved there, so both
    spellings work (``config.json`` keys are upper case, rtgym's lower case: they never clash).

    Args:
        override: a parsed override (not modified).
    """
    rtgym = schema.SCHEMA.fields["ENV"].fields["RTGYM_CONFIG"]
    moved = {k: v for k, v in override.items() if k not in schema.SCHEMA.fields and k in rtgym.fields}
    if not moved:
        return dict(override)
    out = {k: v for k, v in override.items() if k not in moved}
    env = dict(out.get("ENV") or {}) if isinstance(out.get("ENV", {}), Mapping) else out["ENV"]
    if isinstance(env, dict):
        rt = env.get("RTGYM_CONFIG") or {}
        env["RTGYM_CONFIG"] = {**dict(rt), **moved} if isinstance(rt, Mapping) else rt
        out["ENV"] = env
    return out


def _syntax_reason(err: BaseException) -> str:
    """A short reason for a text that is not a dict, without Python's internals."""
    if isinstance(err, SyntaxError):
        where = f" at column {err.offset}" if err.offset else ""
        return f"{err.msg}{where}"
    return type(err).__name__


def deep_merge(base: Mapping[str, Any], override: Mapping[str, Any], _spec: Any = None) -> dict[str, Any]:
    """A new dict: ``base`` with ``override`` merged in. Nested schema sections merge key by key;
    free-form objects (``GYM_KWARGS``, ``interface_kwargs``) and other values are replaced.

    Args:
        base: a config (not modified).
        override: the keys to change, nested like ``base``.
        _spec: internal, the schema section of ``base`` during the recursion (leave it out).
    """
    spec = _spec if _spec is not None else schema.SCHEMA
    out = dict(base)
    for key, value in override.items():
        sub = spec.fields.get(key) if isinstance(spec, schema.Section) else None
        if isinstance(sub, schema.Section) and isinstance(out.get(key), Mapping) and isinstance(value, Mapping):
            out[key] = deep_merge(out[key], value, sub)
        else:
            out[key] = value
    return out


def apply_override(cfg: Mapping[str, Any], override: Mapping[str, Any] | str,
                   source: str = "--config") -> dict[str, Any]:
    """Validate ``override`` (a dict, or text for :func:`parse_override`) key by key against the
    schema, merge it into the complete config ``cfg`` and re-check the multi-key rules.

    Args:
        cfg: a complete, validated config (not modified).
        override: the keys to change, as a dict or its text. Lower-case keys of the real-time
            configuration are accepted at the top level (see :func:`route_rtgym_keys`).
        source: where the override came from, put in front of error messages.

    Returns:
        A new complete config.

    Raises:
        ConfigError: naming ``source`` and the full key path of the bad entry.
    """
    if isinstance(override, str):
        override = parse_override(override, source)
    try:
        checked = schema.SCHEMA.check(route_rtgym_keys(override), "", fill=False)
        merged = deep_merge(cfg, checked)
        schema.check_consistency(merged)
    except SchemaViolation as e:
        raise _violation(source, e) from None
    return merged


def set_override_env(override: Mapping[str, Any] | str, source: str = "--config") -> dict[str, Any]:
    """Validate ``override`` and store it (merged into any override already there) as JSON in
    ``$TMRL_CONFIG_OVERRIDE``, so that :func:`load_config` in this process and in every child
    process applies it. Returns the combined override.

    Args:
        override: the keys to change, as a dict or its text.
        source: where the override came from, put in front of error messages.

    Raises:
        ConfigError: the override is malformed or names a bad key or value.
    """
    if isinstance(override, str):
        override = parse_override(override, source)
    try:
        checked = schema.SCHEMA.check(route_rtgym_keys(override), "", fill=False)
    except SchemaViolation as e:
        raise _violation(source, e) from None
    previous = _env_override()
    combined = deep_merge(previous, checked) if previous else checked
    os.environ[OVERRIDE_ENV] = json.dumps(combined)
    return combined


def _env_override() -> dict[str, Any]:
    text = os.environ.get(OVERRIDE_ENV, "")
    return parse_override(text, source=f"--config (via {OVERRIDE_ENV})") if text.strip() else {}


def _read_config_file(file: Path) -> dict[str, Any]:
    """The validated content of one config file (no override applied).

    Raises:
        ConfigError: unreadable file, invalid JSON, or a value the schema refuses (one line).
    """
    source = _source_name(file)
    try:
        text = file.read_text(encoding="utf-8-sig")
    except UnicodeDecodeError as e:
        raise ConfigError(f"{source}: not UTF-8 text (byte {e.start}); save it as UTF-8 JSON") from None
    except OSError as e:
        raise ConfigError(f"{source}: cannot be read ({e.strerror}); check its permissions") from None
    try:
        raw = json.loads(text)
    except json.JSONDecodeError as e:
        raise ConfigError(
            f"{source}: invalid JSON at line {e.lineno}, column {e.colno}: {e.msg}; "
            "fix the file (comments and trailing commas are not allowed)"
        ) from None
    return validate(raw, source)


def load_config(path: str | os.PathLike[str] | None = None,
                overrides: Mapping[str, Any] | str | None = None) -> dict[str, Any]:
    """Load and validate ``config.json``.

    Args:
        path: the file; default ``config/config.json`` of :func:`data_folder`. When no path is
            given and that file does not exist yet, the defaults are used (nothing is created;
            run ``python -m tmrl --install`` to create the folder).
        overrides: a dict (or its text) merged in after ``$TMRL_CONFIG_OVERRIDE``, both validated
            like the file.

    Returns:
        A complete config: every key of the schema, values normalised.

    Raises:
        ConfigError: missing explicit file, unreadable file, invalid JSON (with line and column),
            unknown key, wrong type, value out of range; one line each.
    """
    explicit = path is not None
    file = Path(path) if path is not None else config_path()
    source = _source_name(file)
    if file.is_file():
        cfg = _read_config_file(file)
    elif file.exists():
        raise ConfigError(f"{source}: is not a file; remove it or run `python -m tmrl --install`")
    elif explicit:
        raise ConfigError(f"{source}: file not found; check the path")
    else:
        logger.debug("%s does not exist yet: using the defaults", file)
        cfg = validate({}, "defaults")
    env_override = _env_override()
    if env_override:
        cfg = apply_override(cfg, env_override, source=f"--config (via {OVERRIDE_ENV})")
    if overrides is not None:
        cfg = apply_override(cfg, overrides, source="--config")
    return cfg


_PROCESS_CONFIG: dict[str, Any] | None = None
_PROCESS_LOCK = threading.Lock()


def process_config(reload: bool = False) -> dict[str, Any]:
    """The configuration this process runs with: the one the roles (:mod:`tmrl.roles`) build
    from and the compatibility module :mod:`tmrl.config.config_constants` exposes, so that both
    see the same. :func:`load_config` (``config.json`` of the data folder with
    ``$TMRL_CONFIG_OVERRIDE``) on the first call; the same dict on every later call.

    Args:
        reload: load it again and keep the new one for the later calls (importing
            ``config_constants`` does: that module reads the configuration when imported).

    Raises:
        ConfigError: the configuration is invalid (one line naming the key).
    """
    global _PROCESS_CONFIG
    with _PROCESS_LOCK:
        if reload or _PROCESS_CONFIG is None:
            _PROCESS_CONFIG = load_config()
        return _PROCESS_CONFIG
