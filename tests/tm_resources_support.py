"""Test support (not a test module): a stand-in of the original tmrl's resources archive, built in
the test with the original's layout, and a loopback HTTP server that serves it.

The real archive (release v0.6.0 of trackmania-rl/tmrl, ``resources.zip``) holds
``resources/Plugins/TMRL_GrabData.op`` and ``TMRL_SaveGhost.op``, ``resources/reward.pkl`` (a
pickled NumPy array, as the original's recorder writes it), ``resources/SAC_4_LIDAR_pretrained.tmod``
and ``SAC_4_imgs_pretrained.tmod`` (``torch.save`` of an actor's state_dict) and
``resources/config.json``. The stand-ins have the same names and formats, with made-up contents.
"""

from __future__ import annotations

import http.server
import io
import json
import pickle
import threading
import zipfile
from collections import OrderedDict

import numpy as np

LIDAR_OBS = 1 + 4 * 19 + 3 + 3  # speed, 4 lidar scans of 19 beams, two past actions
STAMP = (2023, 4, 1, 12, 0, 0)
REWARD = np.c_[np.arange(1001) * 0.1, np.zeros(1001), np.zeros(1001)]  # 100 m straight along x


def plugin_bytes(name: str, version: str) -> bytes:
    """An ``.op`` plugin as OpenPlanet ships them: a zip holding ``info.toml`` and the script."""
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w") as z:  # fixed dates: the same plugin gives the same bytes
        z.writestr(zipfile.ZipInfo("info.toml", STAMP), f'[meta]\nname = "{name}"\nversion = "{version}"\n')
        z.writestr(zipfile.ZipInfo("main.as", STAMP), "void Main() {}\n")
    return buf.getvalue()


def lidar_state(seed: int = 0, scale: float = 0.02) -> OrderedDict[str, object]:
    """tmrl 0.7's SquashedGaussianMLPActor for TM20LIDAR, in its own names and shapes: ``net`` is
    Linear, ReLU, Linear, ReLU (hidden 256, 256), then the ``mu_layer`` and ``log_std_layer`` heads."""
    import torch

    g = torch.Generator().manual_seed(seed)

    def t(*shape: int) -> torch.Tensor:
        return torch.randn(*shape, generator=g) * scale

    return OrderedDict([
        ("net.0.weight", t(256, LIDAR_OBS)), ("net.0.bias", t(256)),
        ("net.2.weight", t(256, 256)), ("net.2.bias", t(256)),
        ("mu_layer.weight", t(3, 256)), ("mu_layer.bias", t(3)),
        ("log_std_layer.weight", t(3, 256)), ("log_std_layer.bias", t(3)),
    ])


def tmod_bytes(state: dict) -> bytes:
    import torch

    buf = io.BytesIO()
    torch.save(OrderedDict(state), buf)
    return buf.getvalue()


def imgs_state() -> dict:
    """tmrl 0.7's CNN actor for TM20FULL (``net.conv1..4``, ``net.mlp``), written by this project's
    export (whose layout tests/test_compat checks against the original's)."""
    from tmrl.config import loader
    from tmrl.legacy_weights import export_state
    from tmrl.tm.install import _actor_for

    cfg = loader.validate(loader.shipped_config("tm20full"), "tm20full")
    return export_state(_actor_for(cfg))


_IMGS_CACHE: dict[str, bytes] = {}


def members() -> dict[str, bytes]:
    """The stand-in archive's members, name -> bytes (a fresh dict: change it freely)."""
    if "imgs" not in _IMGS_CACHE:
        _IMGS_CACHE["imgs"] = tmod_bytes(imgs_state())
    return {
        "resources/Plugins/TMRL_GrabData.op": plugin_bytes("TMRL Grab Data", "0.3"),
        "resources/Plugins/TMRL_SaveGhost.op": plugin_bytes("TMRL Save Ghost", "0.2"),
        "resources/reward.pkl": pickle.dumps(REWARD),
        "resources/SAC_4_LIDAR_pretrained.tmod": tmod_bytes(lidar_state()),
        "resources/SAC_4_imgs_pretrained.tmod": _IMGS_CACHE["imgs"],
        "resources/config.json": json.dumps({"RUN_NAME": "SAC_4_imgs_pretrained", "PASSWORD": "x"}).encode(),
    }


def archive(contents: dict[str, bytes] | None = None, extra: list[zipfile.ZipInfo | tuple] | None = None) -> bytes:
    """A zip of ``contents`` (default :func:`members`), plus ``extra`` members given as
    ``(ZipInfo or name, bytes)``."""
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", zipfile.ZIP_DEFLATED) as z:
        z.writestr(zipfile.ZipInfo("resources/"), b"")
        for name, data in (members() if contents is None else contents).items():
            z.writestr(name, data)
        for info, data in extra or []:
            z.writestr(info, data)
    return buf.getvalue()


def declare_size(data: bytes, member: str, size: int) -> bytes:
    """``data`` (a zip) with ``member``'s uncompressed size in the local header and the central
    directory rewritten to ``size``: the archive declares it without holding it."""
    out = bytearray(data)
    name = member.encode()
    for sig, size_at, name_at in ((b"PK\x03\x04", 22, 30), (b"PK\x01\x02", 24, 46)):
        pos = out.find(sig)
        while pos != -1:
            if out[pos + name_at: pos + name_at + len(name)] == name:
                out[pos + size_at: pos + size_at + 4] = size.to_bytes(4, "little")
            pos = out.find(sig, pos + 4)
    return bytes(out)


class ArchiveServer:
    """A loopback HTTP server answering every GET with ``body``; counts the requests."""

    def __init__(self, body: bytes) -> None:
        self.body = body
        self.requests = 0
        outer = self

        class Handler(http.server.BaseHTTPRequestHandler):
            def do_GET(self) -> None:
                outer.requests += 1
                self.send_response(200)
                self.send_header("Content-Length", str(len(outer.body)))
                self.end_headers()
                self.wfile.write(outer.body)

            def log_message(self, *args: object) -> None:
                pass

        self.httpd = http.server.ThreadingHTTPServer(("127.0.0.1", 0), Handler)
        self.url = f"http://127.0.0.1:{self.httpd.server_address[1]}/trackmania-rl/resources.zip"
        self.thread = threading.Thread(target=self.httpd.serve_forever, daemon=True)
        self.thread.start()

    def close(self) -> None:
        self.httpd.shutdown()
        self.httpd.server_close()

    def __enter__(self) -> ArchiveServer:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
