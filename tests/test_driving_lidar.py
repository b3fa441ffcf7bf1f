"""Tests of tmrl.driving.lidar against synthetic images with known distances."""

from __future__ import annotations

import math

import numpy as np
import pytest

from tmrl.driving.lidar import LIDAR_BEAMS, Lidar

H, W = 488, 958
ROAD_ROW, ROAD_COL = 44 * H // 49, W // 2  # 438, 479


def road(h: int = H, w: int = W, channels: int | None = 3) -> np.ndarray:
    shape = (h, w, channels) if channels else (h, w)
    return np.full(shape, 170, dtype=np.uint8)


def reference(img: np.ndarray, threshold=(55, 55, 55)) -> np.ndarray:
    """tmrl 0.7's lidar rules, one beam and one pixel at a time."""
    h, w = img.shape[:2]
    r0, c0 = 44 * h // 49, w // 2
    out = []
    for angle in range(90, 280, 10):
        dr, dc = math.cos(math.radians(angle)), math.sin(math.radians(angle))
        pix, dist = [], 20
        while True:
            r, c = int(r0 + dist * dr), int(c0 + dist * dc)
            if r <= 0 or c <= 0 or c >= w - 1:
                break
            pix.append((r, c))
            dist += 1
        vals = np.array([img[r, c] for r, c in pix])
        dark = np.all(vals < np.asarray(threshold), axis=-1) if vals.ndim == 2 else vals < threshold[0]
        hits = np.flatnonzero(dark)
        out.append(hits[0] if len(hits) else len(pix) - 1)
    return np.array(out, dtype=np.float32)


def test_geometry_of_the_original():
    lidar = Lidar(H, W)
    assert lidar.road_point == (ROAD_ROW, ROAD_COL)
    assert lidar.rows.shape[0] == LIDAR_BEAMS
    # beam 9 points straight up: its pixels are the column above the road point, from 20 px
    up = lidar.rows[9, : lidar.lengths[9]]
    assert up[0] == ROAD_ROW - 20 and np.all(lidar.cols[9, : lidar.lengths[9]] == ROAD_COL)
    assert lidar.lengths[9] == ROAD_ROW - 20  # rows 418 .. 1 (row 0 is outside, as in the original)
    # beam 0 points right along the row
    assert lidar.cols[0, 0] == ROAD_COL + 20 and lidar.cols[0, lidar.lengths[0] - 1] == W - 2


def test_no_wall_gives_the_last_index():
    lidar = Lidar(H, W)
    assert np.array_equal(lidar.measure(road()), (lidar.lengths - 1).astype(np.float32))


def test_horizontal_wall_ahead():
    img = road()
    img[ROAD_ROW - 120] = 0  # a black row 120 px above the road point
    d = Lidar(H, W).measure(img)
    assert d[9] == 100  # straight up: first dark pixel at distance 120, index 120 - 20
    # the beam at 180 +- 10 degrees reaches that row when dist * cos(10 deg) >= 120 (truncated)
    expected = next(k for k in range(20, 400) if int(ROAD_ROW + k * math.cos(math.radians(170))) <= ROAD_ROW - 120) - 20
    assert d[8] == expected and d[10] == expected
    assert d[8] > d[9]  # slanted beams travel farther to the same wall


def test_vertical_walls_left_and_right():
    img = road()
    img[:, ROAD_COL + 60] = (10, 20, 30)
    img[:, ROAD_COL - 35] = (0, 0, 0)
    d = Lidar(H, W).measure(img)
    assert d[0] == 40  # right, 60 px away
    assert d[18] == 15  # left, 35 px away (the 270 degree beam starts one row up, same column rule)


def test_threshold_is_per_channel_and_strict():
    img = road()
    img[ROAD_ROW - 50, :] = (50, 50, 60)  # one channel too bright: not dark
    img[ROAD_ROW - 80, :] = (54, 54, 54)  # dark
    d = Lidar(H, W).measure(img)
    assert d[9] == 60
    img[ROAD_ROW - 80, :] = (55, 55, 55)  # equal to the threshold: not dark
    assert Lidar(H, W).measure(img)[9] == Lidar(H, W).lengths[9] - 1


def test_grayscale_images():
    img = road(channels=None)
    img[ROAD_ROW - 70] = 20
    lidar = Lidar(H, W, black_threshold=55)
    assert lidar.measure(img)[9] == 50


@pytest.mark.parametrize("shape", [(488, 958), (64, 64), (120, 300), (300, 90)])
def test_matches_the_pixel_by_pixel_reading(shape):
    rng = np.random.default_rng(shape[0])
    img = np.full((*shape, 3), 200, dtype=np.uint8)
    dark = rng.random(shape) < 0.01
    img[dark] = rng.integers(0, 60, size=(int(dark.sum()), 3))
    lidar = Lidar(*shape)
    assert np.array_equal(lidar.measure(img), reference(img))


def test_resizes_to_a_new_image_size_and_draws_endpoints():
    lidar = Lidar(100, 100)
    img = road(H, W)
    img[ROAD_ROW - 120] = 0
    assert lidar.measure(img)[9] == 100 and lidar.height == H
    ends = lidar.endpoints(lidar.measure(img))
    assert tuple(ends[9]) == (ROAD_ROW - 120, ROAD_COL)
