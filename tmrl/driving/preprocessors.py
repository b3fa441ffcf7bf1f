"""Observation preprocessors shared by TrackMania and the simulator (tmrl 0.7's scaling).

A worker applies its preprocessor to every observation before the policy sees it and before the
sample compressor runs. Elements after the interface's own ones (the real-time action buffer)
pass through unchanged.
"""

from __future__ import annotations

import numpy as np

__all__ = [
    "identity_sample", "preprocess_full_obs", "preprocess_full_obs_uint8", "preprocess_lidar_obs",
    "preprocess_lidar_progress_obs",
]


def preprocess_lidar_obs(obs: tuple) -> tuple:
    """Flatten the lidar history of a ``TM20LIDAR``/``SIMLIDAR`` observation.

    Args:
        obs: ``(speed, lidar history (h, 19), *action buffer)``.

    Returns:
        ``(speed, lidars (h*19,), *action buffer)``.
    """
    return (obs[0], np.asarray(obs[1]).reshape(-1), *obs[2:])


def preprocess_lidar_progress_obs(obs: tuple) -> tuple:
    """Flatten the lidar history of a ``TM20LIDARPROGRESS``/``SIMLIDARPROGRESS`` observation.

    Args:
        obs: ``(speed, progress, lidar history (h, 19), *action buffer)``.

    Returns:
        ``(speed, progress, lidars (h*19,), *action buffer)``.
    """
    return (obs[0], obs[1], np.asarray(obs[2]).reshape(-1), *obs[3:])


def preprocess_full_obs(obs: tuple) -> tuple:
    """Scale a ``TM20FULL``/``SIMFULL`` observation to floats of order one, as the original full
    pipeline does: speed / 1000, gear / 10, rpm / 10000, images / 256 (all float32).

    Args:
        obs: ``(speed, gear, rpm, uint8 images (h, height, width), *action buffer)``.

    Returns:
        The same elements scaled (the action buffer unchanged).
    """
    imgs = np.asarray(obs[3]).astype(np.float32) / 256.0
    return (
        np.asarray(obs[0], dtype=np.float32) / 1000.0,
        np.asarray(obs[1], dtype=np.float32) / 10.0,
        np.asarray(obs[2], dtype=np.float32) / 10000.0,
        imgs,
        *obs[4:],
    )


def preprocess_full_obs_uint8(obs: tuple) -> tuple:
    """:func:`preprocess_full_obs` with the frames kept as uint8 (the DrQ pipeline: the model
    divides them by 255 itself, on the worker and on the trainer alike).

    Args:
        obs: ``(speed, gear, rpm, uint8 images (h, height, width), *action buffer)``.

    Returns:
        The scalars scaled as :func:`preprocess_full_obs` does, the frames as uint8, the action
        buffer unchanged.
    """
    imgs = np.asarray(obs[3])
    if imgs.dtype != np.uint8:
        imgs = np.clip(np.rint(imgs), 0, 255).astype(np.uint8)
    return (
        np.asarray(obs[0], dtype=np.float32) / 1000.0,
        np.asarray(obs[1], dtype=np.float32) / 10.0,
        np.asarray(obs[2], dtype=np.float32) / 10000.0,
        imgs,
        *obs[4:],
    )


def identity_sample(prev_obs: object, act: object, rew: object, new_obs: object, terminated: object,
                    truncated: object) -> tuple:
    """A memory's ``sample_preprocessor`` that changes nothing (the place where data
    augmentation would go). Returns its arguments as a tuple, in order.

    Args:
        prev_obs: the observation the action was taken in.
        act: the action.
        rew: the reward.
        new_obs: the observation that followed.
        terminated: whether the episode ended there.
        truncated: whether the episode was cut there.
    """
    return prev_obs, act, rew, new_obs, terminated, truncated
