"""Sample compressors shared by TrackMania and the simulator.

A worker runs its compressor on every sample before sending it (see docs/internals.md):
``compressor(prev_act, obs, rew, terminated, truncated, info) -> same tuple``. The observation
arrives already preprocessed (:mod:`tmrl.driving.preprocessors`): histories flattened, images
scaled to float. Only what the memory cannot rebuild crosses the wire: the newest lidar or the
newest image (as uint8), the scalars, and not the action buffer (the memory rebuilds histories and
action buffers by index, :mod:`tmrl.driving.memories`).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from tmrl.driving.lidar import LIDAR_BEAMS

__all__ = [
    "compress_full_sample",
    "compress_lidar_progress_sample",
    "compress_lidar_sample",
    "image_to_uint8",
]

Sample = tuple[Any, tuple, Any, bool, bool, dict]


def image_to_uint8(img: np.ndarray) -> np.ndarray:
    """A grayscale or colour image as uint8: uint8 input is returned as is, float input is taken
    as preprocessed (``pixel / 256``, the full preprocessor's scale) and scaled back.

    Args:
        img: the image, any shape.
    """
    img = np.asarray(img)
    if img.dtype == np.uint8:
        return img
    return np.clip(np.rint(img * 256.0), 0, 255).astype(np.uint8)


def compress_lidar_sample(prev_act: Any, obs: tuple, rew: float, terminated: bool, truncated: bool,
                          info: dict) -> Sample:
    """Keep ``(speed, newest lidar (19,))``; drop the older lidars and the action buffer.

    Args:
        prev_act: the action taken (kept).
        obs: the preprocessed observation, ``(speed, lidars (h*19,), *action buffer)``.
        rew: the reward (sent as float32).
        terminated: whether the episode ended (kept).
        truncated: whether the episode was cut (kept).
        info: the step's info dict (kept).

    Returns:
        ``(prev_act, (speed, newest lidar), rew, terminated, truncated, info)``.
    """
    newest = np.asarray(obs[1], dtype=np.float32).reshape(-1)[-LIDAR_BEAMS:]
    return prev_act, (obs[0], newest), np.float32(rew), terminated, truncated, info


def compress_lidar_progress_sample(prev_act: Any, obs: tuple, rew: float, terminated: bool, truncated: bool,
                                   info: dict) -> Sample:
    """Keep ``(speed, progress, newest lidar (19,))``; drop older lidars and the action buffer.

    Args:
        prev_act: the action taken (kept).
        obs: the preprocessed observation, ``(speed, progress, lidars (h*19,), *action buffer)``.
        rew: the reward (sent as float32).
        terminated: whether the episode ended (kept).
        truncated: whether the episode was cut (kept).
        info: the step's info dict (kept).

    Returns:
        ``(prev_act, (speed, progress, newest lidar), rew, terminated, truncated, info)``.
    """
    newest = np.asarray(obs[2], dtype=np.float32).reshape(-1)[-LIDAR_BEAMS:]
    return prev_act, (obs[0], obs[1], newest), np.float32(rew), terminated, truncated, info


def compress_full_sample(prev_act: Any, obs: tuple, rew: float, terminated: bool, truncated: bool,
                         info: dict) -> Sample:
    """Keep ``(speed, gear, rpm, newest image as uint8)``; drop older images and the action buffer.

    Args:
        prev_act: the action taken (kept).
        obs: the preprocessed observation, ``(speed, gear, rpm, images (h, height, width), *action buffer)``.
        rew: the reward (sent as float32).
        terminated: whether the episode ended (kept).
        truncated: whether the episode was cut (kept).
        info: the step's info dict (kept).

    Returns:
        ``(prev_act, (speed, gear, rpm, newest image), rew, terminated, truncated, info)``.
    """
    newest = image_to_uint8(np.asarray(obs[3])[-1])
    return prev_act, (obs[0], obs[1], obs[2], newest), np.float32(rew), terminated, truncated, info
