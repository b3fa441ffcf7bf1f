"""``--install --env tm20lidar`` (or ``tm20full``): set up the game side from the original's resources.

After the CLI has created the data folder and ``config.json`` (which this module never writes),
:func:`install_game_side`:

1. takes the resources archive from ``<data folder>/resources/resources.zip`` when it is there
   (a copy downloaded by hand, or by an earlier run), else fetches it
   (:func:`tmrl.tm.resources.fetch`, ``$TMRL_RESOURCES_URL`` replacing the address); offline, it
   says in one line what to download and where to save it, and stops there: running the
   command again finishes the job;
2. checks the whole archive before anything is written (:func:`tmrl.tm.resources.check_archive`),
   then keeps it and its members under ``resources/`` (the pretrained weights are read there by
   PyTorch's restricted loader, :func:`tmrl.legacy_weights.read_legacy_file`, which refuses a
   file that holds more than tensors);
3. copies the signed plugins into ``OpenplanetNext/Plugins`` (:mod:`tmrl.tm.plugins`), replacing
   a copy only when it differs;
4. writes the tmrl-test reward trajectory as ``reward/tmrl-test.npy`` and, when no reward file is
   in use yet, as ``reward/reward.npy``;
5. imports both pretrained weights for their environments' actors into
   ``weights/<name>.tmod``, where ``--worker --test`` reads them.

A file this command wrote is replaced by a later run only when it is still the one it wrote (its
SHA-256 is kept in ``resources/installed.json``): weights trained since, or a reward recorded
for another map, are kept and the summary says so.
"""

from __future__ import annotations

import hashlib
import json
import logging
import sys
from collections.abc import Mapping
from pathlib import Path
from typing import Any, TextIO

from tmrl.tm import resources as res

__all__ = ["GAME_ENVIRONMENTS", "MANIFEST", "REWARD_MAP", "install_game_side"]

logger = logging.getLogger(__name__)

GAME_ENVIRONMENTS = ("tm20lidar", "tm20full")
"""The ``--install --env`` names that set up the game side."""

MANIFEST = "installed.json"
REWARD_MAP = "tmrl-test"
"""The map whose reward trajectory the archive holds."""


def _sha(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


def _file_sha(path: Path) -> str | None:
    return _sha(path.read_bytes()) if path.is_file() else None


class _Manifest:
    """``resources/installed.json``: data-folder-relative path -> SHA-256 of what this command wrote."""

    def __init__(self, root: Path) -> None:
        self.root = root
        self.path = root / "resources" / MANIFEST
        try:
            data = json.loads(self.path.read_text(encoding="utf-8"))
        except (OSError, ValueError):
            data = {}
        self.entries: dict[str, str] = {k: v for k, v in data.items() if isinstance(k, str) and isinstance(v, str)} \
            if isinstance(data, dict) else {}

    def ours(self, path: Path) -> bool:
        """Whether ``path`` still holds what this command wrote there."""
        key = path.relative_to(self.root).as_posix()
        return key in self.entries and self.entries[key] == _file_sha(path)

    def record(self, path: Path) -> None:
        self.entries[path.relative_to(self.root).as_posix()] = _file_sha(path) or ""

    def save(self) -> None:
        from tmrl.util import atomic_write_text

        atomic_write_text(self.path, json.dumps(self.entries, indent=2, sort_keys=True) + "\n")


def _write_if_changed(path: Path, data: bytes) -> None:
    from tmrl.util import atomic_write_bytes

    if not (path.is_file() and path.read_bytes() == data):
        atomic_write_bytes(path, data)


def _obtain(archive: Path, env: str, out: TextIO, err: TextIO) -> tuple[bytes, str, bool] | None:
    """``(bytes, source, downloaded)`` of the archive, or None after the offline line."""
    if archive.is_file():
        size = archive.stat().st_size
        if size > res.MAX_ARCHIVE_BYTES:
            raise res.ArchiveRefused(str(archive), "(the archive)",
                                     f"is {size} bytes, over the {res.MAX_ARCHIVE_BYTES}-byte limit")
        print(f"  resources     using {archive} (already here: delete it to fetch it again)", file=out, flush=True)
        return archive.read_bytes(), str(archive), False
    url = res.resources_url()
    print(f"  resources     fetching the original tmrl's public resources from {url}", file=out, flush=True)
    try:
        data = res.fetch(url, out=err)
    except res.FetchFailed as e:
        print(f"  offline: could not fetch {url} ({e}); download it by hand and save it as {archive}, then run "
              f"`python -m tmrl --install --env {env}` again", file=out, flush=True)
        return None
    return data, url, True


def _unpack(contents: res.ArchiveContents, folder: Path) -> dict[str, Path]:
    """Write the checked members under ``folder`` (our names, never the archive's); returns where
    the pretrained weights are."""
    for name, data in contents.plugins.items():
        _write_if_changed(folder / "Plugins" / name, data)
    _write_if_changed(folder / "reward.pkl", contents.reward_pickle)
    _write_if_changed(folder / "config.json", contents.config)
    if contents.map is not None:
        _write_if_changed(folder / Path(res.MAP_MEMBER).name, contents.map)
    weights = {}
    for name, data in contents.weights.items():
        weights[name] = folder / name
        _write_if_changed(weights[name], data)
    return weights


def _read_weights(weights: dict[str, Path], source: str) -> dict[str, Any]:
    """Every pretrained file read as tensors only, before anything leaves the data folder."""
    from tmrl.legacy_weights import LegacyWeightsError, read_legacy_file

    states = {}
    for name, path in weights.items():
        try:
            states[name] = read_legacy_file(path)
        except LegacyWeightsError as e:
            path.unlink(missing_ok=True)  # never left where a later run would pick it up
            raise res.ArchiveRefused(source, f"resources/{name}", f"is not a tmrl 0.7 weights file ({e})") from None
    return states


def _plugins_line(contents: res.ArchiveContents, cfg: Mapping[str, Any] | None, resources_dir: Path) -> list[str]:
    from tmrl.tm.plugins import find_openplanet, install_plugin

    found = find_openplanet(str((cfg or {}).get("OPENPLANET_FOLDER", "") or ""))
    if found.plugins is None:
        how = ("OPENPLANET_FOLDER in config.json names a folder that does not exist" if found.from_setting
               else f"no OpenplanetNext folder in {found.where()}")
        return [(f"  plugins       not copied: {how}; install OpenPlanet (https://openplanet.dev), start the game "
                 f"once, then run this again, or copy {resources_dir / 'Plugins'}/*.op into OpenplanetNext/Plugins "
                 "yourself (OPENPLANET_FOLDER in config.json names that folder)")]
    done = [install_plugin(name, data, found.plugins) for name, data in contents.plugins.items()]
    return [f"  plugins       {found.plugins}: " + "; ".join(done)]


def _reward_lines(contents: res.ArchiveContents, root: Path, manifest: _Manifest) -> list[str]:
    import numpy as np

    from tmrl.errors import UserError
    from tmrl.tm.record import load_reward, save_reward

    folder = root / "reward"
    named = folder / f"{REWARD_MAP}.npy"
    if not (named.is_file() and np.array_equal(load_reward(named), contents.reward)):
        save_reward(contents.reward, named)
    in_use = folder / "reward.npy"
    legacy = folder / "reward.pkl"
    current = in_use if in_use.is_file() else legacy if legacy.is_file() else None
    if current is None:
        save_reward(contents.reward, in_use)
        manifest.record(in_use)
        return [f"  reward        {in_use}: the {REWARD_MAP} map's trajectory ({len(contents.reward)} points)"]
    try:
        same = np.array_equal(load_reward(current), contents.reward)
    except UserError:
        same = False
    if same:
        return [f"  reward        {current}: the {REWARD_MAP} map's trajectory, already there"]
    if current == in_use and manifest.ours(in_use):
        save_reward(contents.reward, in_use)
        manifest.record(in_use)
        return [f"  reward        {in_use}: the {REWARD_MAP} map's trajectory, updated"]
    return [(f"  reward        kept your {current} (another map's?); the {REWARD_MAP} map's trajectory is {named}: "
             f"copy it to {in_use} to drive on {REWARD_MAP}")]


def _actor_for(cfg: Mapping[str, Any]) -> Any:
    """A fresh actor of the configuration ``cfg`` (no game is touched)."""
    from tmrl.assembly import actor_for, assemble

    parts = assemble(cfg)
    return actor_for(parts.ENV_CLS, parts.POLICY)


def _weights_lines(weights: dict[str, Path], states: dict[str, Any], cfg: Mapping[str, Any] | None,
                   root: Path, manifest: _Manifest) -> list[str]:
    from tmrl.config import loader
    from tmrl.legacy_weights import LegacyWeightsError, import_state

    lines = []
    current = loader.environment_of(cfg) if cfg is not None else None
    for name, env in res.PRETRAINED.items():
        run = Path(name).stem
        target = root / "weights" / name
        if target.is_file() and manifest.ours(target):
            lines.append(f"  weights       {target}: the pretrained {env} actor, already imported")
            continue
        # The original's installer copied the .tmod there as it is: that copy is converted in place.
        if target.is_file() and target.read_bytes() != weights[name].read_bytes():
            lines.append(f"  weights       kept your {target} (not the file --install wrote: trained since?); the "
                         f"pretrained one is {weights[name]} (`python -m tmrl --import-weights` converts it)")
            continue
        env_cfg = cfg if current == env and cfg is not None else loader.validate(loader.shipped_config(env), env)
        try:
            actor = _actor_for(env_cfg)
            actor.load_state_dict(import_state(states[name], actor))
        except LegacyWeightsError as e:
            lines.append(f"  weights       {name} not imported: {e}")
            continue
        target.parent.mkdir(parents=True, exist_ok=True)
        actor.save(str(target))
        manifest.record(target)
        note = ""
        if current == env and cfg is not None:
            note = ("; `python -m tmrl --worker --test` drives with it" if cfg["RUN_NAME"] == run
                    else f"; set RUN_NAME to {run} in config.json to drive with it (yours is {cfg['RUN_NAME']})")
        lines.append(f"  weights       {target}: the pretrained {env} actor, imported{note}")
    return lines


def install_game_side(env: str, cfg: Mapping[str, Any] | None, root: Path,
                      out: TextIO | None = None, err: TextIO | None = None) -> bool:
    """Set up the game side in the data folder ``root`` for ``--install --env env``.

    Args:
        env: one of :data:`GAME_ENVIRONMENTS`.
        cfg: the loaded configuration (its ``OPENPLANET_FOLDER``, environment and ``RUN_NAME``),
            None when it does not load.
        root: the data folder.
        out: where the summary goes (default stdout).
        err: where the download's progress bar goes (default stderr).

    Returns:
        True when everything is in place, False when the archive could not be fetched (the one
        line saying what to download was printed).

    Raises:
        tmrl.tm.resources.ArchiveRefused: the archive breaks a rule (one line naming the member
            and the rule); nothing was written outside the data folder.
    """
    out = sys.stdout if out is None else out
    err = sys.stderr if err is None else err
    resources_dir = root / "resources"
    archive = resources_dir / res.ARCHIVE_NAME
    print("TrackMania (the original tmrl's resources):", file=out, flush=True)
    got = _obtain(archive, env, out, err)
    if got is None:
        return False
    data, source, downloaded = got
    contents = res.check_archive(data, source, res.expected_sha256())
    if downloaded:
        from tmrl.util import atomic_write_bytes

        atomic_write_bytes(archive, data)
    weights = _unpack(contents, resources_dir)
    states = _read_weights(weights, source)
    manifest = _Manifest(root)
    lines = _plugins_line(contents, cfg, resources_dir)
    lines += _reward_lines(contents, root, manifest)
    lines += _weights_lines(weights, states, cfg, root, manifest)
    if contents.map is not None:
        lines.append(f"  map           {resources_dir / Path(res.MAP_MEMBER).name}: copy it into Documents\\Trackmania"
                     "\\Maps\\My Maps, then open it in the game (Create > Map editor > Edit a map)")
    manifest.save()
    print("\n".join(lines), file=out, flush=True)
    return True
