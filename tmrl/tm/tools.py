"""Entry functions of the TrackMania commands, called by the CLI.

====================================  ============================================================
command                               function
====================================  ============================================================
``--doctor``                          :func:`doctor` ``(cfg) -> int``
``--record-reward [--use-keyboard]``  :func:`record_reward` ``(cfg, use_keyboard=False) -> int``
``--check-environment``               :func:`check_environment` ``(cfg, steps=None) -> int``
``--benchmark`` (TrackMania)          :func:`benchmark` ``(cfg, steps=500) -> int``
====================================  ============================================================

Each returns the process exit code and raises :class:`~tmrl.errors.UserError` (one line) for a
setup problem. :func:`benchmark_capture` prints the capture time per frame of a window.
"""

from __future__ import annotations

import logging
import struct
import sys
import time
import zlib
from pathlib import Path
from typing import Any, Callable, Mapping, TextIO

import numpy as np

from tmrl.errors import UserError
from tmrl.util import atomic_write_bytes

__all__ = ["benchmark", "benchmark_capture", "check_environment", "doctor", "record_reward", "write_png"]

logger = logging.getLogger(__name__)


def _load(cfg: Mapping[str, Any] | None) -> Mapping[str, Any]:
    if cfg is not None:
        return cfg
    from tmrl.config.loader import load_config

    return load_config()


def doctor(cfg: Mapping[str, Any] | None = None, out: TextIO | None = None, **kwargs: Any) -> int:
    """``--doctor``: print the pass/fail list of :mod:`tmrl.tm.doctor`; 0 when nothing failed, else 3."""
    from tmrl.tm.doctor import run_doctor

    return run_doctor(_load(cfg), out=out, **kwargs)


def record_reward(
    cfg: Mapping[str, Any] | None = None,
    use_keyboard: bool = False,
    *,
    path: str | Path | None = None,
    host: str | None = None,
    port: int | None = None,
    out: TextIO | None = None,
    wait_start: Callable[[], None] | None = None,
) -> int:
    """``--record-reward``: record the reward trajectory while the user drives one lap.

    Without ``use_keyboard``, recording starts at once (respawn at the start line first) and stops
    by itself at the finish line. With ``use_keyboard``, it starts when the user presses Enter in
    this terminal. A respawn during the recording restarts it. The file goes to
    ``reward/reward.npy`` in the data folder (or ``path``).

    Returns:
        0 once the file is saved.

    Raises:
        tmrl.tm.record.DegenerateRecording: the recording is unusable (message: what to do).
        tmrl.tm.openplanet.TelemetryTimeout: the plugin does not answer (message: what to check).
    """
    from tmrl.tm.openplanet import OpenPlanetClient
    from tmrl.tm.record import record_reward as _record

    out = sys.stdout if out is None else out
    cfg = _load(cfg)
    if path is None:
        from tmrl.config.loader import data_paths

        path = data_paths(cfg).reward_file
    if use_keyboard and wait_start is None:

        def wait_start() -> None:
            try:
                input("Respawn at the start line, then press Enter here and drive to the finish... ")
            except EOFError:
                raise UserError(
                    "--use-keyboard waits for Enter but this process has no terminal input: "
                    "run it in a terminal, or leave out --use-keyboard (recording then starts at once)"
                ) from None
    else:
        print("Recording: drive from the start line to the finish (Ctrl+C aborts).", file=out, flush=True)
    with OpenPlanetClient(host, port) as client:
        saved = _record(client, path, wait_start=wait_start)
    print(f"Reward trajectory saved to {saved}", file=out, flush=True)
    return 0


# ---------------------------------------------------------------------------------------- images
def write_png(path: str | Path, img: np.ndarray) -> Path:
    """Write a uint8 grayscale ``(h, w)`` or RGB ``(h, w, 3)`` image as PNG (no extra package)."""
    img = np.ascontiguousarray(img, dtype=np.uint8)
    if img.ndim == 2:
        color_type = 0
    elif img.ndim == 3 and img.shape[2] == 3:
        color_type = 2
    else:
        raise ValueError(f"write_png takes (h, w) or (h, w, 3) uint8 images, got {img.shape}")
    h, w = img.shape[:2]
    raw = b"".join(b"\x00" + img[row].tobytes() for row in range(h))  # filter type 0 per row

    def chunk(kind: bytes, data: bytes) -> bytes:
        return (
            struct.pack(">I", len(data))
            + kind
            + data
            + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF)
        )

    png = (
        b"\x89PNG\r\n\x1a\n"
        + chunk(b"IHDR", struct.pack(">IIBBBBB", w, h, 8, color_type, 0, 0, 0))
        + chunk(b"IDAT", zlib.compress(raw, 6))
        + chunk(b"IEND", b"")
    )
    return atomic_write_bytes(path, png)


def _draw_rays(rgb: np.ndarray, lidar: Any, distances: np.ndarray) -> np.ndarray:
    """Red lidar rays from the road point to where each beam stops."""
    img = rgb.copy()
    r0, c0 = lidar.road_point
    for r1, c1 in lidar.endpoints(distances):
        n = int(max(abs(r1 - r0), abs(c1 - c0))) + 1
        rr = np.linspace(r0, r1, n).round().astype(int)
        cc = np.linspace(c0, c1, n).round().astype(int)
        img[rr, cc] = (255, 0, 0)
    return img


def _view(interface: Any, obs: tuple) -> np.ndarray:
    """What the policy sees, as one RGB or grayscale image."""
    lidar = getattr(interface, "lidar", None)
    if lidar is not None and getattr(interface, "screenshot", None) is not None:
        return _draw_rays(np.ascontiguousarray(interface.screenshot[..., ::-1]), lidar, interface.img)
    imgs = np.asarray(obs[3])
    return np.concatenate(list(imgs), axis=1)  # the image history, oldest on the left


def check_environment(
    cfg: Mapping[str, Any] | None = None,
    steps: int | None = None,
    out_dir: str | Path | None = None,
    every: int = 20,
    out: TextIO | None = None,
    **interface_kwargs: Any,
) -> int:
    """``--check-environment``: the environment runs with no action (drive by hand) and shows what
    the policy sees: the lidar rays or the image history, saved as PNG files in ``out_dir``
    (default ``<data folder>/check_environment``) every ``every`` steps; rewards are printed.

    Args:
        steps: stop after this many steps (default: until Ctrl+C).
        interface_kwargs: passed to the interface (tests inject fakes).

    Returns:
        0.
    """
    import warnings

    from tmrl.realtime import RealTimeEnv
    from tmrl.tm.interfaces import realtime_config

    out = sys.stdout if out is None else out
    cfg = _load(cfg)
    if out_dir is None:
        from tmrl.config.loader import data_paths

        out_dir = data_paths(cfg).root / "check_environment"
    out_dir = Path(out_dir)
    interface_kwargs.setdefault("gamepad", False)  # the user drives; respawns go through the keyboard
    rt = realtime_config(cfg, **interface_kwargs)
    rt["wait_on_done"] = False
    env = RealTimeEnv(rt)
    print(
        f"Drive by hand; what the policy sees is saved to {out_dir} every {every} steps (Ctrl+C stops).",
        file=out,
        flush=True,
    )
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # driving by hand: a late step is expected, not a problem
            obs, _ = env.reset()
            total, step = 0.0, 0
            while steps is None or step < steps:
                obs, rew, terminated, truncated, _ = env.step(None)
                step += 1
                total += float(rew)
                print(f"step {step:5d}  reward {float(rew):+.3f}  return {total:+.2f}", file=out, flush=True)
                if step % every == 0 or terminated or truncated:
                    write_png(out_dir / f"step_{step:06d}.png", _view(env.interface, obs))
                if terminated or truncated:
                    print(f"episode ended (return {total:+.2f}); resetting", file=out, flush=True)
                    obs, _ = env.reset()
                    total = 0.0
    except KeyboardInterrupt:
        pass
    finally:
        env.close()
    return 0


def benchmark(
    cfg: Mapping[str, Any] | None = None, steps: int = 500, out: TextIO | None = None, **interface_kwargs: Any
) -> int:
    """``--benchmark`` for TrackMania: run ``steps`` steps with the default action and print the
    real-time environment's timing report (rtgym-style averages, in seconds)."""
    from tmrl.realtime import RealTimeEnv
    from tmrl.tm.interfaces import realtime_config

    out = sys.stdout if out is None else out
    rt = realtime_config(_load(cfg), **interface_kwargs)
    rt["benchmark"] = True
    env = RealTimeEnv(rt)
    try:
        env.reset()
        act = env.default_action
        for _ in range(steps):
            _, _, terminated, truncated, _ = env.step(act)
            if terminated or truncated:
                env.reset()
        report = env.benchmarks()
    finally:
        env.close()
    print("real-time environment timings (s):", file=out)
    for key, value in report.items():
        print(f"  {key}: {value}", file=out)
    return 0


def benchmark_capture(
    title: str = "Trackmania",
    width: int = 256,
    height: int = 128,
    img_width: int = 64,
    img_height: int = 64,
    grayscale: bool = True,
    frames: int = 200,
    out: TextIO | None = None,
) -> float:
    """Capture ``frames`` frames of the window plus preprocessing; print and return ms per frame."""
    from tmrl.tm.capture import WindowCapture, preprocess

    out = sys.stdout if out is None else out
    with WindowCapture(title, width, height) as cap:
        preprocess(cap.screenshot(), img_width, img_height, grayscale)
        t0 = time.perf_counter()
        for _ in range(frames):
            preprocess(cap.screenshot(), img_width, img_height, grayscale)
        ms = (time.perf_counter() - t0) / frames * 1e3
    print(
        f"capture {width}x{height} + preprocess to {img_width}x{img_height}: {ms:.2f} ms per frame", file=out
    )
    return ms
