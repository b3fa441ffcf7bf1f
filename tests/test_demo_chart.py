"""The demo's learning curve explains itself (issue 40): a line says what a return counts (1 per
10 m driven along the track, the lap bonus per lap), and the episode axis always shows at least
three whole-number ticks, however many episodes ran."""

from __future__ import annotations

import numpy as np
import pytest

from tmrl.sim.charts import _nice_ticks, _render, learning_curve_image, return_note


@pytest.mark.parametrize("episodes", [*range(2, 200), 999, 1000, 1001, 9_999, 123_456])
def test_the_episode_axis_has_at_least_three_whole_ticks(episodes):
    ticks = _nice_ticks(1, episodes, integer=True)
    assert len(ticks) >= min(3, episodes), ticks
    assert all(t == int(t) and 1 <= t <= episodes for t in ticks), ticks
    assert len(ticks) <= 11


@pytest.mark.parametrize("lo,hi", [(0.0, 1.0), (-3.0, 9.5), (0.0, 160.0), (12.0, 13.0), (-50.0, -49.1)])
def test_the_return_axis_has_at_least_three_ticks(lo, hi):
    ticks = _nice_ticks(lo, hi)
    assert len(ticks) >= 3 and all(lo - 1e-9 <= t <= hi + 1e-9 for t in ticks), ticks
    assert all(str(t) != "-0.0" for t in ticks)


def _has_text(img: np.ndarray, text: str, row: int, col: int) -> bool:
    mask = _render(text, 2)
    region = img[row:row + mask.shape[0], col:col + mask.shape[1]]
    return bool(((region.sum(axis=2) < 300) == mask).all())


def test_the_curve_says_what_a_return_counts():
    note = return_note(100.0)
    assert note == "RETURN: 1 PER 10 M DRIVEN ALONG THE TRACK, +100 PER LAP"
    chart = learning_curve_image([1.0, 5.0, 12.0, 30.0, 160.0] * 4, "TITLE", ["FIRST LAP AFTER 60 S"])
    assert _has_text(chart, "FIRST LAP AFTER 60 S", 30, 70)
    assert _has_text(chart, note, 48, 70)  # the line under the key figures
    other = learning_curve_image([1.0, 5.0], "TITLE", [], explain=return_note(50.0))
    assert _has_text(other, "RETURN: 1 PER 10 M DRIVEN ALONG THE TRACK, +50 PER LAP", 30, 70)
