"""Where OpenPlanet keeps its plugins, and the TMRL plugins in it.

OpenPlanet (the TrackMania 2020 scripting platform) reads plugins from
``OpenplanetNext/Plugins``. The game puts ``OpenplanetNext`` in the user's home folder
(``%USERPROFILE%`` on Windows); under Linux, where the game runs through Steam's Proton, the home
folder is the Proton prefix's ``drive_c/users/steamuser``. :func:`find_openplanet` looks there in
that order; the config key ``OPENPLANET_FOLDER`` overrides the search.

The two plugins the original tmrl publishes, ``TMRL_GrabData.op`` (telemetry on
``127.0.0.1:9000``) and ``TMRL_SaveGhost.op`` (saves a replay when asked on ``127.0.0.1:10000``),
are signed by OpenPlanet: they load without developer mode and without paid Club access.
:func:`install_plugin` copies one in and replaces an existing copy only when it differs;
:func:`plugin_version` reads the version a plugin file declares (``.op`` files are zip archives
holding an ``info.toml``).
"""

from __future__ import annotations

import io
import os
import platform
import re
import zipfile
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

__all__ = [
    "FOLDER_NAME",
    "GRABDATA",
    "SAVEGHOST",
    "OpenPlanetFolder",
    "PluginState",
    "candidate_folders",
    "find_openplanet",
    "install_plugin",
    "plugin_state",
    "plugin_version",
]

FOLDER_NAME = "OpenplanetNext"
GRABDATA = "TMRL_GrabData.op"
SAVEGHOST = "TMRL_SaveGhost.op"

# Steam's folders on Linux (native package, the Debian/Ubuntu link, Flatpak); Proton makes one
# prefix per game under steamapps/compatdata/<app id>/pfx.
_STEAM_ROOTS = (".steam/steam", ".local/share/Steam", ".var/app/com.valvesoftware.Steam/.local/share/Steam")
_PREFIX_HOME = Path("pfx/drive_c/users/steamuser")


@dataclass(frozen=True)
class OpenPlanetFolder:
    """The result of the search.

    Attributes:
        folder: the ``OpenplanetNext`` folder found, or None.
        searched: every place looked at, in order.
        from_setting: whether ``OPENPLANET_FOLDER`` named it.
    """

    folder: Path | None
    searched: tuple[Path, ...]
    from_setting: bool = False

    @property
    def plugins(self) -> Path | None:
        """``OpenplanetNext/Plugins`` (None when no folder was found)."""
        return None if self.folder is None else self.folder / "Plugins"

    def where(self) -> str:
        """The searched places, for a message."""
        return ", ".join(str(p) for p in self.searched) or "nowhere"


def candidate_folders(home: Path | None = None, environ: Mapping[str, str] | None = None,
                      system: str | None = None) -> list[Path]:
    """The places ``OpenplanetNext`` may be, in the order :func:`find_openplanet` tries them:
    the home folder (``%USERPROFILE%`` first on Windows), then on Linux the Proton prefixes of
    Steam's games.

    Args:
        home: the home folder (default: this user's).
        environ: the environment variables (default: this process's).
        system: the OS as :func:`platform.system` names it (default: this one).
    """
    environ = os.environ if environ is None else environ
    system = system or platform.system()
    home = Path.home() if home is None else Path(home)
    places: list[Path] = []
    if system == "Windows" and environ.get("USERPROFILE"):
        places.append(Path(environ["USERPROFILE"]) / FOLDER_NAME)
    places.append(home / FOLDER_NAME)
    if system == "Linux":
        for root in _STEAM_ROOTS:
            compat = home / root / "steamapps" / "compatdata"
            if compat.is_dir():
                places += sorted(compat.glob(f"*/{_PREFIX_HOME.as_posix()}/{FOLDER_NAME}"))
    unique: list[Path] = []
    for p in places:
        if p not in unique:
            unique.append(p)
    return unique


def find_openplanet(setting: str = "", home: Path | None = None, environ: Mapping[str, str] | None = None,
                    system: str | None = None) -> OpenPlanetFolder:
    """Find the ``OpenplanetNext`` folder. Creates nothing.

    Args:
        setting: the config key ``OPENPLANET_FOLDER`` (empty: search).
        home: the home folder (default: this user's).
        environ: the environment variables (default: this process's).
        system: the OS as :func:`platform.system` names it (default: this one).
    """
    if setting.strip():
        folder = Path(setting).expanduser()
        return OpenPlanetFolder(folder if folder.is_dir() else None, (folder,), from_setting=True)
    places = candidate_folders(home, environ, system)
    found = next((p for p in places if p.is_dir()), None)
    return OpenPlanetFolder(found, tuple(places))


_VERSION = re.compile(r'^\s*version\s*=\s*"([^"]*)"', re.MULTILINE)


def plugin_version(data: bytes) -> str | None:
    """The version an ``.op`` plugin declares in its ``info.toml``, or None when it declares none
    (or is not a zip archive).

    Args:
        data: the plugin file's bytes.
    """
    try:
        with zipfile.ZipFile(io.BytesIO(data)) as z:
            info = next((i for i in z.infolist() if i.filename.lower().endswith("info.toml")), None)
            if info is None or info.file_size > 1 << 16:
                return None
            text = z.read(info).decode("utf-8", "replace")
    except (zipfile.BadZipFile, OSError, ValueError, KeyError):
        return None
    match = _VERSION.search(text)
    return match.group(1) if match else None


def _named(name: str, data: bytes) -> str:
    version = plugin_version(data)
    return f"{name} v{version}" if version else name


def install_plugin(name: str, data: bytes, plugins: Path) -> str:
    """Put a plugin in the plugin folder, replacing an existing copy only when it differs.

    Args:
        name: the plugin's file name (``TMRL_GrabData.op``).
        data: its bytes.
        plugins: the folder ``OpenplanetNext/Plugins`` (created when missing).

    Returns:
        What was done, in words (for the summary).
    """
    from tmrl.util import atomic_write_bytes

    target = plugins / name
    if target.is_file():
        old = target.read_bytes()
        if old == data:
            return f"{_named(name, data)} already there, unchanged"
        atomic_write_bytes(target, data)
        before = plugin_version(old)
        return f"{_named(name, data)} replaced a different copy" + (f" (v{before})" if before else "")
    atomic_write_bytes(target, data)
    return f"{_named(name, data)} installed"


@dataclass(frozen=True)
class PluginState:
    """One plugin in the plugin folder.

    Attributes:
        name: its file name.
        present: whether the file is there.
        version: the version its ``info.toml`` declares (None: none, or not there).
        matches_reference: whether it is the copy ``--install`` fetched (None: not compared).
    """

    name: str
    present: bool
    version: str | None = None
    matches_reference: bool | None = None


def plugin_state(plugins: Path, name: str, reference: Path | None = None) -> PluginState:
    """What is in the plugin folder under a plugin's name.

    Args:
        plugins: the folder ``OpenplanetNext/Plugins``.
        name: the plugin's file name.
        reference: the copy the archive brought (``resources/Plugins/<name>``), to tell whether the
            installed one is that one; None: not compared.
    """
    path = plugins / name
    if not path.is_file():
        return PluginState(name, False)
    data = path.read_bytes()
    same = None
    if reference is not None and reference.is_file():
        same = reference.read_bytes() == data
    return PluginState(name, True, plugin_version(data), same)
