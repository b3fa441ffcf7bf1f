"""The 19-beam lidar shared by TrackMania and the simulator.

The lidar reads an image in which the track borders are dark. From the road point, at the bottom
centre of the image (row ``44 * h // 49``, column ``w // 2``), 19 beams leave at angles 90, 100,
..., 270 degrees (90 points right, 180 straight up, 270 left). Each beam is the list of pixels at
integer distances 20, 21, ... from the road point (coordinates truncated toward zero), up to the
image edge. A beam's value is the position, in that list, of its first dark pixel (all channels
below the threshold), or the list's last position when it has none. These are tmrl 0.7's rules,
so a policy trained on one pipeline reads the same numbers on the other.

The beams are precomputed once per image size as a padded index array, so measuring an image is
one gather and one ``argmax``: no Python loop over beams or pixels.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

__all__ = ["DEFAULT_BLACK_THRESHOLD", "LIDAR_BEAMS", "LIDAR_MIN_DIST", "Lidar"]

LIDAR_BEAMS = 19
"""Number of beams (angles 90 to 270 degrees every 10 degrees)."""
LIDAR_MIN_DIST = 20
"""Distance in pixels from the road point to the first pixel of every beam."""
DEFAULT_BLACK_THRESHOLD = (55, 55, 55)
"""A pixel is dark when every channel is below this (the original's ``LIDAR_BLACK_THRESHOLD``)."""


class Lidar:
    """Beam geometry for one image size, and the measurement of images of that size.

    Args:
        height: image height in pixels.
        width: image width in pixels.
        black_threshold: per-channel threshold (a sequence, one value per channel, or one number
            for grayscale images); a pixel is dark when all its channels are strictly below it.

    Attributes:
        road_point: ``(row, col)`` the beams start from.
        rows: ``(19, L)`` int array, the pixel rows of each beam padded to the longest beam.
        cols: ``(19, L)`` int array, the pixel columns of each beam, padded likewise.
        lengths: ``(19,)`` number of pixels of each beam.
        valid: ``(19, L)`` bool mask of the real (non-padding) entries.
    """

    def __init__(self, height: int, width: int, black_threshold: float | Sequence[float] = DEFAULT_BLACK_THRESHOLD):
        self.height = int(height)
        self.width = int(width)
        self.black_threshold = np.asarray(black_threshold, dtype=np.float64)
        self.road_point = (44 * self.height // 49, self.width // 2)
        self.rows, self.cols, self.lengths = self._beams(self.height, self.width, self.road_point)
        self.valid = np.arange(self.rows.shape[1])[None, :] < self.lengths[:, None]

    @classmethod
    def for_image(cls, img: np.ndarray, black_threshold: float | Sequence[float] = DEFAULT_BLACK_THRESHOLD) -> Lidar:
        """A lidar sized for ``img`` (``(h, w)`` or ``(h, w, c)``)."""
        return cls(img.shape[0], img.shape[1], black_threshold)

    @staticmethod
    def _beams(h: int, w: int, road_point: tuple[int, int]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        r0, c0 = road_point
        beams_r, beams_c = [], []
        for angle in range(90, 280, 10):
            dr = math.cos(math.radians(angle))
            dc = math.sin(math.radians(angle))
            # A beam ends at the first distance whose pixel leaves the image (top row, first or
            # last column excluded, as in the original); the longest possible beam is the diagonal.
            dist = np.arange(LIDAR_MIN_DIST, LIDAR_MIN_DIST + h + w + 2, dtype=np.float64)
            r = (r0 + dist * dr).astype(np.int64)  # truncation toward zero, like int()
            c = (c0 + dist * dc).astype(np.int64)
            out = (r <= 0) | (c <= 0) | (c >= w - 1)
            end = int(np.argmax(out)) if out.any() else len(dist)
            beams_r.append(r[:end])
            beams_c.append(c[:end])
        lengths = np.array([len(b) for b in beams_r], dtype=np.int64)
        longest = max(1, int(lengths.max()))
        rows = np.zeros((LIDAR_BEAMS, longest), dtype=np.int64)
        cols = np.zeros((LIDAR_BEAMS, longest), dtype=np.int64)
        for i, (br, bc) in enumerate(zip(beams_r, beams_c)):
            rows[i, : len(br)] = br
            cols[i, : len(bc)] = bc
            # Padding points at the road point keep gathers in bounds; `valid` masks them out.
            rows[i, len(br):] = r0
            cols[i, len(bc):] = c0
        return rows, cols, lengths

    def dark(self, values: np.ndarray) -> np.ndarray:
        """Which pixel values are dark: ``values`` is ``(..., c)`` or ``(...)`` for grayscale."""
        thr = self.black_threshold
        if values.ndim == self.rows.ndim + 1:  # colour: every channel below its threshold
            c = values.shape[-1]
            thr = np.full(c, float(thr)) if thr.ndim == 0 else thr[:c]
            return np.all(values < thr, axis=-1)
        # Grayscale: the first channel's threshold (all three are equal in the shipped configs).
        return values < float(thr.flat[0])

    def distances_from_dark(self, dark: np.ndarray) -> np.ndarray:
        """Beam values from a ``(19, L)`` bool array telling which beam pixels are dark.

        Returns:
            ``(19,)`` float32: index of the first dark pixel of each beam, or the beam's last
            index when it has none (tmrl 0.7's rule).
        """
        dark = dark & self.valid
        first = np.argmax(dark, axis=1)
        none = ~dark.any(axis=1)
        first = np.where(none, self.lengths - 1, first)
        return first.astype(np.float32)

    def beam_values(self, img: np.ndarray) -> np.ndarray:
        """The pixels of ``img`` along every beam: ``(19, L)`` or ``(19, L, c)``."""
        return img[self.rows, self.cols]

    def measure(self, img: np.ndarray) -> np.ndarray:
        """The 19 beam values of ``img``.

        Args:
            img: ``(h, w)`` grayscale or ``(h, w, c)`` image; a different size than the lidar's
                rebuilds the beams for that size.

        Returns:
            ``(19,)`` float32 array, in pixels along each beam (see the module docstring).
        """
        if img.shape[0] != self.height or img.shape[1] != self.width:
            self.__init__(img.shape[0], img.shape[1], self.black_threshold)  # type: ignore[misc]
        return self.distances_from_dark(self.dark(self.beam_values(img)))

    # the original's name
    lidar_20 = measure

    def endpoints(self, distances: np.ndarray) -> np.ndarray:
        """Where each beam stops, for drawing the rays.

        Args:
            distances: the 19 distances the lidar measured (pixels along each beam).

        Returns:
            ``(19, 2)`` pixel ``(row, col)`` of each beam's end.
        """
        idx = np.clip(np.asarray(distances).astype(np.int64), 0, np.maximum(self.lengths - 1, 0))
        beams = np.arange(LIDAR_BEAMS)
        return np.stack([self.rows[beams, idx], self.cols[beams, idx]], axis=1)
