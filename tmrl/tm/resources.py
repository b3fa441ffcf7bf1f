"""The original tmrl's public resources archive: fetch it, and check it before anything in it is used.

The original tmrl publishes its game-side files as one archive, ``resources.zip`` of its release
``v0.6.0`` (:data:`RESOURCES_URL`). Its layout (:data:`MEMBERS`)::

    resources/Plugins/TMRL_GrabData.op      the telemetry plugin, signed by OpenPlanet
    resources/Plugins/TMRL_SaveGhost.op     the replay plugin, signed by OpenPlanet
    resources/reward.pkl                    the reward trajectory of the map tmrl-test (a pickled array)
    resources/SAC_4_LIDAR_pretrained.tmod   pretrained weights, TM20LIDAR
    resources/SAC_4_imgs_pretrained.tmod    pretrained weights, TM20FULL
    resources/config.json                   the original's configuration (kept for reference)
    resources/tmrl-test.Map.Gbx             the map tmrl-test, when the archive has it (optional)

:func:`fetch` downloads it (``http(s)://`` or ``file://``; ``$TMRL_RESOURCES_URL`` replaces the
address) with a progress bar. :func:`check_archive` reads it from memory and refuses it whole,
before anything is written, when any member's path would leave the folder it is unpacked into
(``..``, an absolute path, a link), when a member or the whole is over its size limit, when the
expected layout is missing, when the SHA-256 differs from ``$TMRL_RESOURCES_SHA256`` (when set),
or when ``reward.pkl`` holds anything but a NumPy array of numbers (read by the restricted reader
of :mod:`tmrl.tm.record`, which runs nothing). Each refusal is an :class:`ArchiveRefused`: one line
naming the member and the rule.

Files are never unpacked under a member's own name: the caller writes the checked contents to
paths it chooses (:mod:`tmrl.tm.install`).
"""

from __future__ import annotations

import hashlib
import io
import json
import os
import re
import stat
import sys
import time
import urllib.error
import urllib.request
import zipfile
from collections.abc import Callable
from dataclasses import dataclass
from typing import TextIO

import numpy as np

from tmrl.errors import UserError

__all__ = [
    "ARCHIVE_NAME",
    "MAX_ARCHIVE_BYTES",
    "MAX_MEMBER_BYTES",
    "MEMBERS",
    "PLUGINS",
    "PRETRAINED",
    "RESOURCES_URL",
    "SHA256_ENV",
    "URL_ENV",
    "ArchiveContents",
    "ArchiveRefused",
    "FetchFailed",
    "check_archive",
    "expected_sha256",
    "fetch",
    "resources_url",
]

RESOURCES_URL = "https://github.com/trackmania-rl/tmrl/releases/download/v0.6.0/resources.zip"
"""Where the original tmrl publishes its resources archive (its release v0.6.0)."""

URL_ENV = "TMRL_RESOURCES_URL"
"""Environment variable that replaces :data:`RESOURCES_URL` (a mirror, a ``file://`` address)."""

SHA256_ENV = "TMRL_RESOURCES_SHA256"
"""Environment variable holding the archive's expected SHA-256 (hex); unset: not checked."""

ARCHIVE_NAME = "resources.zip"

PLUGINS = ("TMRL_GrabData.op", "TMRL_SaveGhost.op")
"""The OpenPlanet plugins of the archive, signed by OpenPlanet."""

PRETRAINED = {"SAC_4_LIDAR_pretrained.tmod": "tm20lidar", "SAC_4_imgs_pretrained.tmod": "tm20full"}
"""The pretrained weights of the archive and the environment (``--install --env``) each was trained on."""

MEMBERS = (
    *(f"resources/Plugins/{name}" for name in PLUGINS),
    "resources/reward.pkl",
    *(f"resources/{name}" for name in PRETRAINED),
    "resources/config.json",
)
"""The members the archive must hold (any others are checked and left unused)."""

MAP_MEMBER = "resources/tmrl-test.Map.Gbx"
"""The map tmrl-test: used when the archive holds it."""

MAX_MEMBER_BYTES = 64 * 2**20
"""Largest member accepted (its size as declared and as read)."""

MAX_ARCHIVE_BYTES = 256 * 2**20
"""Largest archive accepted, and largest sum of its members' sizes."""

MAX_MEMBER_COUNT = 1000


class ArchiveRefused(UserError):
    """The archive breaks a rule; nothing of it was used. The message names the member and the rule.

    Args:
        source: where the archive came from (an address or a file).
        member: the member's name, or ``(the archive)`` for the whole.
        rule: the rule it breaks, in words.
        fix: what to do, when the rule does not say it.
    """

    def __init__(self, source: str, member: str, rule: str, fix: str = "") -> None:
        self.member = member
        self.rule = rule
        tail = f"; {fix}" if fix else ""
        super().__init__(f"refused the resources archive {source}: member {member!r}: {rule}{tail}")


class FetchFailed(Exception):
    """The archive could not be fetched (no network, an address that fails); ``str()`` says why."""


@dataclass(frozen=True)
class ArchiveContents:
    """What a checked archive holds.

    Attributes:
        plugins: plugin file name -> bytes (:data:`PLUGINS`).
        reward: the tmrl-test reward trajectory, float64 ``(N, 3)``.
        reward_pickle: ``reward.pkl`` as it is in the archive.
        weights: weights file name -> bytes (:data:`PRETRAINED`), not yet read.
        config: ``config.json`` of the original, as bytes.
        map: the map tmrl-test (``.Map.Gbx``) when the archive holds it, else None.
    """

    plugins: dict[str, bytes]
    reward: np.ndarray
    reward_pickle: bytes
    weights: dict[str, bytes]
    config: bytes
    map: bytes | None = None


def resources_url() -> str:
    """:data:`RESOURCES_URL`, or ``$TMRL_RESOURCES_URL`` when set."""
    return os.environ.get(URL_ENV, "").strip() or RESOURCES_URL


def expected_sha256() -> str | None:
    """``$TMRL_RESOURCES_SHA256`` in lower case, or None when unset."""
    value = os.environ.get(SHA256_ENV, "").strip().lower()
    return value or None


# ---------------------------------------------------------------------------------------- fetching
class _Progress:
    """A one-line progress bar on a terminal; one line at the end elsewhere."""

    def __init__(self, out: TextIO, total: int | None) -> None:
        self.out, self.total = out, total
        self.tty = bool(getattr(out, "isatty", lambda: False)())
        self.last = 0.0

    def update(self, done: int, final: bool = False) -> None:
        if not self.tty and not final:
            return
        now = time.monotonic()
        if not final and now - self.last < 0.1:
            return
        self.last = now
        mb = done / 2**20
        if self.total:
            frac = min(done / self.total, 1.0)
            bar = "#" * int(frac * 30)
            text = f"  [{bar:<30}] {frac * 100:5.1f}%  {mb:.1f} of {self.total / 2**20:.1f} MB"
        else:
            text = f"  {mb:.1f} MB"
        if self.tty:
            self.out.write("\r" + text + ("\n" if final else ""))
        else:
            self.out.write(text.strip() + " downloaded\n")
        self.out.flush()


def fetch(url: str, out: TextIO | None = None, timeout: float = 30.0,
          max_bytes: int = MAX_ARCHIVE_BYTES,
          opener: Callable[..., object] = urllib.request.urlopen) -> bytes:
    """The bytes at ``url``, with a progress bar.

    Args:
        url: an ``http``, ``https`` or ``file`` address.
        out: where the progress bar goes (default stderr; a bar on a terminal, one line elsewhere).
        timeout: seconds to wait for the server at each step.
        max_bytes: largest download accepted.
        opener: ``urllib.request.urlopen`` or a stand-in with its signature.

    Raises:
        FetchFailed: the address cannot be reached or fails (the message says why, in words).
        ArchiveRefused: the download is larger than ``max_bytes``.
    """
    out = sys.stderr if out is None else out
    try:
        response = opener(urllib.request.Request(url, headers={"User-Agent": "tmrl"}), timeout=timeout)
    except urllib.error.HTTPError as err:
        raise FetchFailed(f"HTTP {err.code} {err.reason}") from None
    except urllib.error.URLError as err:
        reason = err.reason
        raise FetchFailed(getattr(reason, "strerror", None) or str(reason)) from None
    except (OSError, ValueError) as err:
        raise FetchFailed(getattr(err, "strerror", None) or str(err)) from None
    with response as r:  # type: ignore[attr-defined]
        length = r.headers.get("Content-Length") if getattr(r, "headers", None) is not None else None
        total = int(length) if length and str(length).isdigit() else None
        if total is not None and total > max_bytes:
            raise ArchiveRefused(url, "(the archive)", f"declares {total} bytes, over the {max_bytes}-byte limit")
        progress = _Progress(out, total)
        buf = bytearray()
        try:
            while True:
                chunk = r.read(1 << 16)
                if not chunk:
                    break
                buf += chunk
                if len(buf) > max_bytes:
                    raise ArchiveRefused(url, "(the archive)", f"is larger than the {max_bytes}-byte limit")
                progress.update(len(buf))
        except (OSError, ValueError) as err:  # a connection cut mid-way
            raise FetchFailed(f"the download stopped after {len(buf)} bytes ({err})") from None
        progress.update(len(buf), final=True)
    if total is not None and len(buf) != total:
        raise FetchFailed(f"the download stopped after {len(buf)} of {total} bytes")
    return bytes(buf)


# ---------------------------------------------------------------------------------------- checking
_DRIVE = re.compile(r"^[A-Za-z]:")


def _path_rule(name: str) -> str | None:
    """The rule a member's name breaks, or None."""
    if not name:
        return "has an empty name"
    if "\x00" in name:
        return "has a NUL character in its name"
    if name.startswith(("/", "\\")) or _DRIVE.match(name):
        return "has an absolute path (it would be written outside the data folder)"
    if ".." in name.replace("\\", "/").split("/"):
        return "has '..' in its path (it would be written outside the data folder)"
    return None


def _is_link(info: zipfile.ZipInfo) -> bool:
    return stat.S_ISLNK(info.external_attr >> 16)


def check_archive(data: bytes, source: str, sha256: str | None = None) -> ArchiveContents:
    """Check an archive and return what it holds.

    Args:
        data: the archive's bytes.
        source: where it came from (an address or a file), named in messages.
        sha256: the SHA-256 it must have (hex), or None: not checked.

    The order of the checks: the SHA-256 (when given), the zip structure, then every member's
    path, type and declared size, the total size, the layout, each needed member's real size
    and checksum, ``reward.pkl`` and ``config.json``.

    Raises:
        ArchiveRefused: one line naming the member and the rule; nothing was written.
    """
    if len(data) > MAX_ARCHIVE_BYTES:
        raise ArchiveRefused(source, "(the archive)", f"is {len(data)} bytes, over the {MAX_ARCHIVE_BYTES}-byte limit")
    if sha256 is not None:
        digest = hashlib.sha256(data).hexdigest()
        if digest != sha256.lower():
            raise ArchiveRefused(source, "(the archive)", f"SHA-256 is {digest}, not the configured {sha256}",
                                 f"fetch it again, or fix ${SHA256_ENV}")
    try:
        archive = zipfile.ZipFile(io.BytesIO(data))
    except (zipfile.BadZipFile, ValueError, OSError) as err:
        raise ArchiveRefused(source, "(the archive)", f"is not a zip archive ({err})") from None
    with archive:
        infos = archive.infolist()
        if len(infos) > MAX_MEMBER_COUNT:
            raise ArchiveRefused(source, "(the archive)", f"has {len(infos)} members, over the limit of {MAX_MEMBER_COUNT}")
        total = 0
        seen: dict[str, zipfile.ZipInfo] = {}
        for info in infos:
            name = info.filename
            rule = _path_rule(name)
            if rule is not None:
                raise ArchiveRefused(source, name, rule)
            if _is_link(info):
                raise ArchiveRefused(source, name, "is a symbolic link (links are never unpacked)")
            if info.file_size > MAX_MEMBER_BYTES:
                raise ArchiveRefused(source, name, f"declares {info.file_size} bytes, over the "
                                                   f"{MAX_MEMBER_BYTES}-byte limit of a member")
            total += info.file_size
            if total > MAX_ARCHIVE_BYTES:
                raise ArchiveRefused(source, name, f"brings the unpacked size over the {MAX_ARCHIVE_BYTES}-byte limit")
            if name in seen:
                raise ArchiveRefused(source, name, "appears twice")
            seen[name] = info
        blobs: dict[str, bytes] = {}
        for name in MEMBERS:
            info = seen.get(name)
            if info is None or info.is_dir():
                raise ArchiveRefused(source, name, "is missing: this is not the tmrl resources archive (expected "
                                                   "resources/Plugins/*.op, reward.pkl, two .tmod files, config.json)")
            blobs[name] = _read_member(archive, info, source)
        map_info = seen.get(MAP_MEMBER)
        map_blob = _read_member(archive, map_info, source) if map_info is not None and not map_info.is_dir() else None
    reward_pickle = blobs["resources/reward.pkl"]
    reward = _reward_of(reward_pickle, source)
    try:
        config = json.loads(blobs["resources/config.json"].decode("utf-8-sig"))
    except (UnicodeDecodeError, ValueError) as err:
        raise ArchiveRefused(source, "resources/config.json", f"is not JSON ({type(err).__name__})") from None
    if not isinstance(config, dict):
        raise ArchiveRefused(source, "resources/config.json", "is not a JSON object")
    return ArchiveContents(
        plugins={name: blobs[f"resources/Plugins/{name}"] for name in PLUGINS},
        reward=reward,
        reward_pickle=reward_pickle,
        weights={name: blobs[f"resources/{name}"] for name in PRETRAINED},
        config=blobs["resources/config.json"],
        map=map_blob,
    )


def _read_member(archive: zipfile.ZipFile, info: zipfile.ZipInfo, source: str) -> bytes:
    """A member's bytes, never more than its declared size (and the limit) read."""
    try:
        with archive.open(info) as f:
            blob = f.read(min(info.file_size, MAX_MEMBER_BYTES) + 1)
    except (zipfile.BadZipFile, OSError, EOFError, ValueError, NotImplementedError) as err:
        raise ArchiveRefused(source, info.filename, f"cannot be read ({err})") from None
    if len(blob) != info.file_size:
        raise ArchiveRefused(source, info.filename, f"holds {len(blob)} bytes where its header says {info.file_size}")
    return blob


def _reward_of(blob: bytes, source: str) -> np.ndarray:
    from tmrl.tm.record import read_legacy_reward_bytes, trajectory_problem

    try:
        arr = read_legacy_reward_bytes(blob, MAX_MEMBER_BYTES)
    except ValueError as err:
        raise ArchiveRefused(source, "resources/reward.pkl", f"is not a NumPy array of numbers ({err}); it was "
                                     "read by tmrl's restricted reader, which ran nothing") from None
    problem = trajectory_problem(arr)
    if problem is not None:
        raise ArchiveRefused(source, "resources/reward.pkl", problem)
    return arr.astype(np.float64)
