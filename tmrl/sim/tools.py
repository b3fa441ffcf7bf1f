"""``--check-environment`` for the simulator: what the policy sees, as PNG files.

The built-in driver (:func:`tmrl.sim.race.follow_centre_line`) drives the configured simulator
interface in fast mode, the reward of each step is printed, and every ``every`` steps the view is
saved: for the lidar interfaces, the grayscale view the lidar reads with its 19 rays drawn in
red; for the full interface, the image history side by side (oldest on the left), enlarged.
No display is needed.
"""

from __future__ import annotations

import sys
from collections.abc import Mapping
from pathlib import Path
from typing import Any, TextIO

import numpy as np

__all__ = ["check_environment", "observation_picture"]


def observation_picture(env: Any, obs: tuple) -> np.ndarray:
    """An RGB picture of what the policy sees in ``obs`` (from a :class:`~tmrl.sim.interfaces.SimEnv`)."""
    from tmrl.sim.interfaces import SimFullInterface
    from tmrl.sim.render import _polyline

    itf = env.interface
    if isinstance(itf, SimFullInterface):
        strip = np.concatenate(list(np.asarray(obs[3])), axis=1)
        big = np.kron(strip, np.ones((4, 4), dtype=np.uint8))
        return np.repeat(big[:, :, None], 3, axis=2)
    view = itf.lidar_view()
    img = np.repeat(view[:, :, None], 3, axis=2)
    lidar = itf.lidar
    distances = np.asarray(obs[-1 - env.act_buf_len])[-1]  # newest scan of the lidar history
    r0, c0 = lidar.road_point
    for (r, c) in lidar.endpoints(distances):
        _polyline(img, np.array([r0, r]), np.array([c0, c]), (230, 40, 40), width=2)
    return img


def check_environment(cfg: Mapping[str, Any] | None = None, steps: int | None = None,
                      out_dir: str | Path | None = None, every: int = 20, out: TextIO | None = None) -> int:
    """Drive the configured simulator with the built-in driver, print the rewards and save what
    the policy sees to ``out_dir`` (default ``<data folder>/check_environment``).

    Args:
        cfg: a loaded config (default: the data folder's config.json).
        steps: steps to run (default: one episode, at most 2000 steps).
        out_dir: where the PNG files go.
        every: save a picture every ``every`` steps (and at the end of the episode).
        out: where to print (default stdout).

    Returns:
        0.
    """
    from tmrl.sim.interfaces import fast_env
    from tmrl.sim.race import follow_centre_line
    from tmrl.sim.render import write_png

    out = sys.stdout if out is None else out
    if cfg is None:
        from tmrl.config.loader import load_config

        cfg = load_config()
    if out_dir is None:
        from tmrl.config.loader import data_paths

        out_dir = data_paths(cfg).root / "check_environment"
    out_dir = Path(out_dir)
    env = fast_env(cfg)
    print(f"The built-in driver drives {cfg['ENV']['RTGYM_INTERFACE']} on track {env.race.track.name}; "
          f"what the policy sees is saved to {out_dir} every {every} steps.", file=out, flush=True)
    obs, _ = env.reset()
    total, limit = 0.0, steps if steps is not None else 2000
    for step in range(1, limit + 1):
        obs, rew, terminated, truncated, info = env.step(follow_centre_line(env.race))
        total += rew
        print(f"step {step:5d}  reward {rew:+.3f}  return {total:+.2f}", file=out, flush=True)
        done = terminated or truncated
        if step % every == 0 or done or step == limit:
            write_png(out_dir / f"step_{step:06d}.png", observation_picture(env, obs))
        if done:
            lap = f", lap time {info['lap_time']:.2f} s" if info.get("lap_completed") else ""
            print(f"episode ended (return {total:+.2f}{lap})", file=out, flush=True)
            if steps is None:
                break
            obs, _ = env.reset()
            total = 0.0
    env.close()
    return 0
