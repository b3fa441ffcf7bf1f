"""Array-shaped replay memories for driving observations (TrackMania and the simulator).

The sample compressors (:mod:`tmrl.driving.compressors`) send one frame per sample: the newest
lidar or image, the scalars, and no action buffer. These memories store that one frame per slot
and rebuild, by index arithmetic over the ``prev`` pointers of
:class:`tmrl.memory.GenericTorchMemory`, both the frame history and the action buffer of every
observation, exactly as the environment built them:

- the history of sample ``j`` is the frames of the ``hist_len`` samples of its episode ending at
  ``j``, oldest first, with the episode's first frame repeated before the episode starts (what
  the interfaces do at reset);
- the action buffer is rebuilt by :class:`tmrl.memory.RealTimeTorchMemory`.

A transition never mixes two episodes or two workers. Rebuilt observations have the preprocessed
layout the policy sees: lidar histories flattened to ``(hist_len * 19,)`` float32, image
histories ``(hist_len, h, w)`` float32 scaled by 1/256 (stored as uint8, one byte per pixel).
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from typing import Any

from tmrl.errors import UserError
from tmrl.memory import RealTimeTorchMemory
from tmrl.memory.resident import as_float32, take

__all__ = ["HistoryMemory", "ImageMemory", "LidarMemory", "LidarProgressMemory", "RawImageMemory"]

logger = logging.getLogger(__name__)


_noted_imgs_obs = False


def _history_length(hist_len: int | None, imgs_obs: int | None) -> int:
    """``hist_len``, or tmrl 0.7's ``imgs_obs`` (noted once in the log), or the default 4."""
    global _noted_imgs_obs
    if imgs_obs is None:
        return 4 if hist_len is None else int(hist_len)
    if hist_len is not None and int(hist_len) != int(imgs_obs):
        raise UserError(f"imgs_obs={imgs_obs} and hist_len={hist_len} disagree: imgs_obs is the old name of "
                        "hist_len, give only hist_len")
    if not _noted_imgs_obs:
        _noted_imgs_obs = True
        logger.info("imgs_obs is tmrl 0.7's name of the memory's hist_len; it still works, hist_len is the "
                    "name to use in new code")
    return int(imgs_obs)


class HistoryMemory(RealTimeTorchMemory):
    """A real-time memory whose observations hold a history of one stored element.

    Args:
        hist_len: frames in each observation's history (``IMG_HIST_LEN``).
        act_buf_len: actions in each observation's buffer (rtgym's ``act_buf_len``).
        frame_index: position of the frame in the stored (compressed) observation.
        flatten: return histories flattened to one dimension (the lidar preprocessors' layout).
        scale: multiply rebuilt histories by this, as float32 (1/256 for uint8 images); None
            keeps the stored dtype.
        imgs_obs: tmrl 0.7's name of ``hist_len`` (accepted, with a note in the log once).
        **kwargs: :class:`tmrl.memory.RealTimeTorchMemory`'s other arguments (``memory_size``,
            ``batch_size``, ``device``, ``sample_preprocessor``, ``dataset_path``, ``crc_debug``...).

    Raises:
        UserError: ``hist_len`` or ``act_buf_len`` below 1, or ``imgs_obs`` and a different
            ``hist_len`` both given.
    """

    frame_index: int = 1
    flatten: bool = False
    scale: float | None = None

    def __init__(self, hist_len: int | None = None, act_buf_len: int = 2, frame_index: int | None = None,
                 flatten: bool | None = None, scale: float | None = None, imgs_obs: int | None = None,
                 **kwargs: Any) -> None:
        hist_len = _history_length(hist_len, imgs_obs)
        if int(hist_len) < 1:
            raise UserError(f"the history length must be at least 1, got {hist_len}: fix ENV.IMG_HIST_LEN")
        super().__init__(act_buf_len=act_buf_len, **kwargs)
        self.hist_len = int(hist_len)
        if frame_index is not None:
            self.frame_index = int(frame_index)
        if flatten is not None:
            self.flatten = bool(flatten)
        if scale is not None:
            self.scale = float(scale)
        # Sampled transitions need this many prev links intact (histories and action buffers).
        self.history_depth = max(self.hist_len, self.act_buf_len)

    def build_from(self, rings: Any, hist: Any) -> tuple:
        """Stored elements with the frame replaced by its history (the frames at the last
        ``hist_len`` columns of ``hist``), then the action buffer.

        Args:
            rings: as in :meth:`tmrl.memory.GenericTorchMemory.build_from`.
            hist: as in :meth:`tmrl.memory.GenericTorchMemory.build_from`.

        Raises:
            UserError: the stored observations have no frame at ``frame_index`` (the sample
                compressor and the memory do not match).
        """
        elements = list(super().build_from(rings, hist))
        n_stored = len(elements) - self.act_buf_len
        if not 0 <= self.frame_index < n_stored:
            raise UserError(
                f"the stored observation has {n_stored} elements, no frame at position {self.frame_index}: "
                "the sample compressor and the memory do not match"
            )
        frames = take(rings.obs[self.frame_index], hist[:, -self.hist_len:])  # (n, hist_len, *frame_shape)
        if self.scale is not None:
            frames = as_float32(frames, self.scale)
        if self.flatten:
            frames = frames.reshape(len(hist), -1)
        elements[self.frame_index] = frames
        return tuple(elements)


class LidarMemory(HistoryMemory):
    """For ``(speed, newest lidar (19,))`` samples (``compress_lidar_sample``); rebuilds
    ``(speed, lidars (hist_len * 19,), *act_buf)``, the ``TM20LIDAR``/``SIMLIDAR`` layout."""

    frame_index = 1
    flatten = True


class LidarProgressMemory(HistoryMemory):
    """For ``(speed, progress, newest lidar)`` samples; rebuilds
    ``(speed, progress, lidars (hist_len * 19,), *act_buf)``."""

    frame_index = 2
    flatten = True


class ImageMemory(HistoryMemory):
    """For ``(speed, gear, rpm, newest uint8 image)`` samples (``compress_full_sample``); rebuilds
    ``(speed, gear, rpm, images (hist_len, h, w) float32 / 256, *act_buf)``, the full
    preprocessor's layout. Stores one uint8 frame per sample."""

    frame_index = 3
    scale = 1.0 / 256.0


class RawImageMemory(ImageMemory):
    """:class:`ImageMemory` that rebuilds the image histories as stored, uint8 (the DrQ pipeline:
    the frames reach the batch as bytes and the model scales them)."""

    scale = None


MEMORY_FOR: dict[str, Callable[..., HistoryMemory]] = {
    "LIDAR": LidarMemory,
    "LIDARPROGRESS": LidarProgressMemory,
    "FULL": ImageMemory,
}
"""``RTGYM_INTERFACE`` family -> memory class."""
