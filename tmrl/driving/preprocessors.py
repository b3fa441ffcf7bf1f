"""Observation preprocessors shared by TrackMania and the simulator (tmrl 0.7's scaling).

A worker applies its preprocessor to every observation before the policy sees it and before the
sample compressor runs. Elements after the interface's own ones (the real-time action buffer)
pass through unchanged.
"""

from __future__ import annotations

import numpy as np

__all__ = ["identity_sample", "preprocess_full_obs", "preprocess_lidar_obs", "preprocess_lidar_progress_obs"]


def preprocess_lidar_obs(obs: tuple) -> tuple:
    """``(speed, lidar history (h, 19), *acts)`` -> ``(speed, flat lidars (h*19,), *acts)``."""
    return (obs[0], np.asarray(obs[1]).reshape(-1), *obs[2:])


def preprocess_lidar_progress_obs(obs: tuple) -> tuple:
    """``(speed, progress, lidars (h, 19), *acts)`` -> ``(speed, progress, flat lidars, *acts)``."""
    return (obs[0], obs[1], np.asarray(obs[2]).reshape(-1), *obs[3:])


def preprocess_full_obs(obs: tuple) -> tuple:
    """``(speed, gear, rpm, uint8 images, *acts)`` -> scaled floats: speed / 1000, gear / 10,
    rpm / 10000, images / 256 (float32), as the original full pipeline does."""
    imgs = np.asarray(obs[3]).astype(np.float32) / 256.0
    return (
        np.asarray(obs[0], dtype=np.float32) / 1000.0,
        np.asarray(obs[1], dtype=np.float32) / 10.0,
        np.asarray(obs[2], dtype=np.float32) / 10000.0,
        imgs,
        *obs[4:],
    )


def identity_sample(prev_obs: object, act: object, rew: object, new_obs: object, terminated: object,
                    truncated: object) -> tuple:
    """A sample preprocessor that changes nothing (the place where data augmentation would go)."""
    return prev_obs, act, rew, new_obs, terminated, truncated
