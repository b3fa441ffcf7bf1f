"""Images of the simulator: a raster of the whole track, and cameras that look at it from the car.

The track is drawn once into a top-down grayscale raster (:class:`TrackMap`): light road with a
dashed centre line, black borders just outside the walls, dark ground beyond (below the lidar's
threshold too, so a beam that starts past a wall stops at once), and a chequered start/finish
line. A :class:`Camera` then samples that raster at the car's position and heading, nearest
neighbour, all pixels in one vectorised gather: the car sits at a fixed pixel (the *anchor*),
facing the top of the image. The full observation's 64x64 view and the lidar's view are both
cameras; the lidar camera only samples the pixels its beams read.

:func:`write_png` writes a grayscale or RGB uint8 array as a PNG with the standard library only.
"""

from __future__ import annotations

import functools
import os
import struct
import zlib

import numpy as np

from tmrl.sim.track import BORDER_WIDTH, Track
from tmrl.util import atomic_write_bytes

__all__ = [
    "BORDER",
    "GROUND",
    "ROAD",
    "Camera",
    "TrackMap",
    "draw_trajectory",
    "encode_png",
    "track_map",
    "write_png",
]

ROAD = 170
"""Gray level of the road in the raster."""
BORDER = 0
"""Gray level of the black border just outside each wall (what the lidar detects)."""
GROUND = 40
"""Gray level of the ground beyond the borders (also below the lidar's threshold)."""
CENTRE_MARK = 220
CHECKER_LIGHT = 255
CHECKER_DARK = 110  # above the lidar threshold: the start line is not a wall
CAR = 100


class TrackMap:
    """Top-down grayscale raster of a track.

    Args:
        track: the track to draw.
        resolution: metres per raster pixel.

    Attributes:
        image: ``(H, W)`` uint8 raster; row ``i``, column ``j`` covers the square whose lower-left
            corner is ``origin + (j, i) * resolution`` (rows grow with ``y``).
        origin: world coordinates of the raster's corner.
    """

    def __init__(self, track: Track, resolution: float = 0.25) -> None:
        self.track = track
        self.resolution = float(resolution)
        margin = BORDER_WIDTH + 4.0
        lo, hi = track.bounds(margin)
        self.origin = lo
        shape = np.ceil((hi - lo) / self.resolution).astype(np.int64)
        self.width, self.height = int(shape[0]), int(shape[1])
        self.image = self._draw()
        self.image.setflags(write=False)

    def _draw(self) -> np.ndarray:
        track, res = self.track, self.resolution
        reach = track.half_width + BORDER_WIDTH
        # Nearest centre point of every pixel near the road, found by stamping a disc of pixels
        # around every 0.5 m of centre line and keeping, per pixel, the smallest
        # (distance, index) key. Distances are in millimetres in the key's high bits.
        step = max(1, int(round(0.5 / track.spacing)))
        idx = np.arange(0, track.n_points, step)
        radius = int(np.ceil((reach + 0.5) / res)) + 1
        oy, ox = np.mgrid[-radius:radius + 1, -radius:radius + 1]
        keep = ox**2 + oy**2 <= radius**2
        ox, oy = ox[keep], oy[keep]
        keys = np.full(self.height * self.width, np.iinfo(np.int64).max, dtype=np.int64)
        for chunk in np.array_split(idx, max(1, len(idx) // 128)):
            c = track.centre[chunk]
            cpx = np.floor((c - self.origin) / res).astype(np.int64)
            px = cpx[:, 0:1] + ox[None, :]
            py = cpx[:, 1:2] + oy[None, :]
            wx = self.origin[0] + (px + 0.5) * res
            wy = self.origin[1] + (py + 0.5) * res
            d_mm = np.rint(np.hypot(wx - c[:, 0:1], wy - c[:, 1:2]) * 1000.0).astype(np.int64)
            ok = (px >= 0) & (px < self.width) & (py >= 0) & (py < self.height)
            key = (d_mm << 24) | np.broadcast_to(chunk[:, None], d_mm.shape)
            np.minimum.at(keys, (py * self.width + px)[ok], key[ok])
        stamped = keys != np.iinfo(np.int64).max
        img = np.full(self.height * self.width, GROUND, dtype=np.uint8)
        flat = np.flatnonzero(stamped)
        nearest = keys[flat] & ((1 << 24) - 1)
        wx = self.origin[0] + (flat % self.width + 0.5) * res
        wy = self.origin[1] + (flat // self.width + 0.5) * res
        rel = np.stack([wx, wy], axis=1) - track.centre[nearest]
        lateral = np.einsum("ij,ij->i", rel, track.normals[nearest])
        along = np.einsum("ij,ij->i", rel, track.tangents[nearest])
        s = nearest * track.spacing + along  # arc length from the start line
        s = (s + 0.5 * track.length) % track.length - 0.5 * track.length  # in [-L/2, L/2)
        a = np.abs(lateral)
        colour = np.full(len(flat), GROUND, dtype=np.uint8)
        colour[a < reach] = BORDER
        road = a < track.half_width
        colour[road] = ROAD
        dash = road & (a < 0.15) & ((np.floor(s / 3.0) % 2) == 0)
        colour[dash] = CENTRE_MARK
        square = 0.75
        line = road & (np.abs(s) < square)
        chequer = ((np.floor(lateral / square) + np.floor(s / square)) % 2) == 0
        colour[line] = np.where(chequer[line], CHECKER_LIGHT, CHECKER_DARK)
        img[flat] = colour
        return img.reshape(self.height, self.width)

    def sample(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Raster values at world coordinates, nearest pixel; :data:`GROUND` outside the raster.

        Args:
            x: x coordinates in metres (any shape).
            y: y coordinates in metres (same shape as ``x``).

        Returns:
            uint8 values of that shape.
        """
        ix = np.floor((x - self.origin[0]) / self.resolution).astype(np.int64)
        iy = np.floor((y - self.origin[1]) / self.resolution).astype(np.int64)
        inside = (ix >= 0) & (ix < self.width) & (iy >= 0) & (iy < self.height)
        out = np.full(ix.shape, GROUND, dtype=np.uint8)
        out[inside] = self.image[iy[inside], ix[inside]]
        return out

    def topdown(self, max_size: int = 800) -> np.ndarray:
        """The raster as an image with north up (row 0 = largest ``y``), downscaled by keeping
        every k-th pixel.

        Args:
            max_size: the image's largest side is at most this many pixels.
        """
        img = self.image[::-1]
        k = max(1, int(np.ceil(max(img.shape) / max_size)))
        return np.ascontiguousarray(img[::k, ::k])

    def to_topdown_pixels(self, xy: np.ndarray, max_size: int = 800) -> np.ndarray:
        """Where world positions fall in :meth:`topdown`'s image.

        Args:
            xy: ``(N, 2)`` world positions in metres.
            max_size: the ``max_size`` given to :meth:`topdown`.

        Returns:
            ``(N, 2)`` integer ``(row, col)`` pixels (possibly outside the image).
        """
        k = max(1, int(np.ceil(max(self.height, self.width) / max_size)))
        ix = (np.asarray(xy)[:, 0] - self.origin[0]) / self.resolution
        iy = (np.asarray(xy)[:, 1] - self.origin[1]) / self.resolution
        return np.stack([(self.height - 1 - iy) / k, ix / k], axis=1).astype(np.int64)


@functools.lru_cache(maxsize=8)
def _cached_map(track: Track, resolution: float) -> TrackMap:
    return TrackMap(track, resolution)


def track_map(track: Track, resolution: float = 0.25) -> TrackMap:
    """The :class:`TrackMap` of ``track``, cached (eight maps at most): drawing one takes a
    fraction of a second.

    Args:
        track: the track to draw.
        resolution: metres per raster pixel.
    """
    return _cached_map(track, float(resolution))


class Camera:
    """A view attached to the car: pixel ``(row, col)`` looks at the point
    ``(anchor_row - row) * scale`` metres ahead of the car and ``(col - anchor_col) * scale``
    metres to its right.

    Args:
        height: image height in pixels.
        width: image width in pixels.
        scale: metres per pixel.
        anchor: ``(row, col)`` of the car's position in the image (default: column centre, 85 %
            of the height).
        rows: optional array of the pixel rows to sample (with ``cols``, any same shape) instead
            of the whole image; :meth:`render` then returns values of that shape.
        cols: optional array of the pixel columns to sample, with ``rows``.
        draw_car: paint the car (a 2 m x 4 m rectangle) over the view.
    """

    def __init__(self, height: int, width: int, scale: float, anchor: tuple[int, int] | None = None,
                 rows: np.ndarray | None = None, cols: np.ndarray | None = None, draw_car: bool = False) -> None:
        self.height, self.width, self.scale = int(height), int(width), float(scale)
        self.anchor = anchor if anchor is not None else (int(0.85 * self.height), self.width // 2)
        if rows is None or cols is None:
            rows, cols = np.mgrid[0:self.height, 0:self.width]
        self.rows, self.cols = np.asarray(rows), np.asarray(cols)
        self.ahead = (self.anchor[0] - self.rows) * self.scale
        self.right = (self.cols - self.anchor[1]) * self.scale
        self.car_mask = None
        if draw_car:
            self.car_mask = (np.abs(self.right) <= 1.0) & (self.ahead >= -2.0) & (self.ahead <= 2.0)

    def render(self, tmap: TrackMap, x: float, y: float, heading: float) -> np.ndarray:
        """The view from a car.

        Args:
            tmap: the raster of the track (:func:`track_map`).
            x: the car's x position in metres.
            y: the car's y position in metres.
            heading: the direction the car points to, radians counter-clockwise from +x.

        Returns:
            uint8 values, ``(height, width)`` or the shape of the ``rows`` given.
        """
        c, s = np.cos(heading), np.sin(heading)
        wx = x + self.ahead * c + self.right * s
        wy = y + self.ahead * s - self.right * c
        img = tmap.sample(wx, wy)
        if self.car_mask is not None:
            img[self.car_mask] = CAR
        return img


def _polyline(img: np.ndarray, rows: np.ndarray, cols: np.ndarray, colour: tuple[int, int, int], width: int = 1) -> None:
    """Draw straight segments between consecutive ``(row, col)`` points on an RGB image."""
    h, w = img.shape[:2]
    for r0, c0, r1, c1 in zip(rows[:-1], cols[:-1], rows[1:], cols[1:]):
        n = int(max(abs(r1 - r0), abs(c1 - c0))) + 1
        rr = np.rint(np.linspace(r0, r1, n)).astype(np.int64)
        cc = np.rint(np.linspace(c0, c1, n)).astype(np.int64)
        for dr in range(-(width // 2), width - width // 2):
            for dc in range(-(width // 2), width - width // 2):
                ok = (rr + dr >= 0) & (rr + dr < h) & (cc + dc >= 0) & (cc + dc < w)
                img[rr[ok] + dr, cc[ok] + dc] = colour


def draw_trajectory(tmap: TrackMap, xy: np.ndarray, max_size: int = 800,
                    colour: tuple[int, int, int] = (230, 40, 40)) -> np.ndarray:
    """Top-down RGB picture of the track with a path drawn over it, for example the best lap of
    a run.

    Args:
        tmap: the raster of the track (:func:`track_map`).
        xy: ``(N, 2)`` world positions of the path, in metres (nothing is drawn below two).
        max_size: largest side of the picture in pixels (see :meth:`TrackMap.topdown`).
        colour: RGB colour of the path.

    Returns:
        A ``(h, w, 3)`` uint8 array (write it with :func:`write_png`).
    """
    img = np.repeat(tmap.topdown(max_size)[:, :, None], 3, axis=2).copy()
    if len(xy) >= 2:
        px = tmap.to_topdown_pixels(np.asarray(xy, dtype=np.float64), max_size)
        _polyline(img, px[:, 0], px[:, 1], colour, width=2)
    return img


def encode_png(img: np.ndarray) -> bytes:
    """PNG bytes of an image (standard library only).

    Args:
        img: a ``(h, w)`` grayscale or ``(h, w, 3)`` RGB uint8 array.

    Raises:
        ValueError: any other shape.
    """
    arr = np.ascontiguousarray(img, dtype=np.uint8)
    if arr.ndim == 2:
        colour_type = 0
    elif arr.ndim == 3 and arr.shape[2] == 3:
        colour_type = 2
    else:
        raise ValueError(f"expected a (h, w) or (h, w, 3) image, got shape {arr.shape}")
    h, w = arr.shape[:2]
    raw = np.concatenate([np.zeros((h, 1), dtype=np.uint8), arr.reshape(h, -1)], axis=1).tobytes()

    def chunk(tag: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + tag + data + struct.pack(">I", zlib.crc32(tag + data) & 0xFFFFFFFF)

    header = struct.pack(">IIBBBBB", w, h, 8, colour_type, 0, 0, 0)
    return b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", header) + chunk(b"IDAT", zlib.compress(raw, 6)) + chunk(b"IEND", b"")


def write_png(path: str | os.PathLike[str], img: np.ndarray) -> None:
    """Write ``img`` (see :func:`encode_png`) to ``path`` atomically."""
    atomic_write_bytes(path, encode_png(img))
