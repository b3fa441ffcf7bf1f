"""Charts that explain themselves, drawn with NumPy only (no plotting library to install): a
learning curve with its title, axis titles with units, ticks, a legend and the run's key figures,
and the best lap over the track with its lap time and a scale bar.

Text uses a built-in 5x7 pixel font (upper-case letters, digits and common signs).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from tmrl.sim.render import _polyline

__all__ = ["Series", "draw_label", "lap_chart", "lap_image", "learning_curve_chart", "learning_curve_image",
           "return_note", "text_width"]

Colour = tuple[int, int, int]

# 5x7 glyphs: 7 rows of 5 pixels ("#" on).
_FONT_ROWS: dict[str, tuple[str, ...]] = {
    'A': (' ### ', '#   #', '#   #', '#####', '#   #', '#   #', '#   #'),
    'B': ('#### ', '#   #', '#   #', '#### ', '#   #', '#   #', '#### '),
    'C': (' ### ', '#   #', '#    ', '#    ', '#    ', '#   #', ' ### '),
    'D': ('#### ', '#   #', '#   #', '#   #', '#   #', '#   #', '#### '),
    'E': ('#####', '#    ', '#    ', '#### ', '#    ', '#    ', '#####'),
    'F': ('#####', '#    ', '#    ', '#### ', '#    ', '#    ', '#    '),
    'G': (' ### ', '#   #', '#    ', '# ###', '#   #', '#   #', ' ####'),
    'H': ('#   #', '#   #', '#   #', '#####', '#   #', '#   #', '#   #'),
    'I': (' ### ', '  #  ', '  #  ', '  #  ', '  #  ', '  #  ', ' ### '),
    'J': ('  ###', '   # ', '   # ', '   # ', '   # ', '#  # ', ' ##  '),
    'K': ('#   #', '#  # ', '# #  ', '##   ', '# #  ', '#  # ', '#   #'),
    'L': ('#    ', '#    ', '#    ', '#    ', '#    ', '#    ', '#####'),
    'M': ('#   #', '## ##', '# # #', '# # #', '#   #', '#   #', '#   #'),
    'N': ('#   #', '#   #', '##  #', '# # #', '#  ##', '#   #', '#   #'),
    'O': (' ### ', '#   #', '#   #', '#   #', '#   #', '#   #', ' ### '),
    'P': ('#### ', '#   #', '#   #', '#### ', '#    ', '#    ', '#    '),
    'Q': (' ### ', '#   #', '#   #', '#   #', '# # #', '#  # ', ' ## #'),
    'R': ('#### ', '#   #', '#   #', '#### ', '# #  ', '#  # ', '#   #'),
    'S': (' ####', '#    ', '#    ', ' ### ', '    #', '    #', '#### '),
    'T': ('#####', '  #  ', '  #  ', '  #  ', '  #  ', '  #  ', '  #  '),
    'U': ('#   #', '#   #', '#   #', '#   #', '#   #', '#   #', ' ### '),
    'V': ('#   #', '#   #', '#   #', '#   #', '#   #', ' # # ', '  #  '),
    'W': ('#   #', '#   #', '#   #', '# # #', '# # #', '# # #', ' # # '),
    'X': ('#   #', '#   #', ' # # ', '  #  ', ' # # ', '#   #', '#   #'),
    'Y': ('#   #', '#   #', ' # # ', '  #  ', '  #  ', '  #  ', '  #  '),
    'Z': ('#####', '    #', '   # ', '  #  ', ' #   ', '#    ', '#####'),
    '0': (' ### ', '#   #', '#  ##', '# # #', '##  #', '#   #', ' ### '),
    '1': ('  #  ', ' ##  ', '  #  ', '  #  ', '  #  ', '  #  ', ' ### '),
    '2': (' ### ', '#   #', '    #', '   # ', '  #  ', ' #   ', '#####'),
    '3': ('#####', '   # ', '  #  ', '   # ', '    #', '#   #', ' ### '),
    '4': ('   # ', '  ## ', ' # # ', '#  # ', '#####', '   # ', '   # '),
    '5': ('#####', '#    ', '#### ', '    #', '    #', '#   #', ' ### '),
    '6': ('  ## ', ' #   ', '#    ', '#### ', '#   #', '#   #', ' ### '),
    '7': ('#####', '    #', '   # ', '  #  ', ' #   ', ' #   ', ' #   '),
    '8': (' ### ', '#   #', '#   #', ' ### ', '#   #', '#   #', ' ### '),
    '9': (' ### ', '#   #', '#   #', ' ####', '    #', '   # ', ' ##  '),
    '.': ('     ', '     ', '     ', '     ', '     ', ' ##  ', ' ##  '),
    ',': ('     ', '     ', '     ', '     ', ' ##  ', '  #  ', ' #   '),
    ':': ('     ', ' ##  ', ' ##  ', '     ', ' ##  ', ' ##  ', '     '),
    '-': ('     ', '     ', '     ', ' ### ', '     ', '     ', '     '),
    '+': ('     ', '  #  ', '  #  ', '#####', '  #  ', '  #  ', '     '),
    '(': ('   # ', '  #  ', ' #   ', ' #   ', ' #   ', '  #  ', '   # '),
    ')': (' #   ', '  #  ', '   # ', '   # ', '   # ', '  #  ', ' #   '),
    '/': ('    #', '    #', '   # ', '  #  ', ' #   ', '#    ', '#    '),
    '%': ('##   ', '##  #', '   # ', '  #  ', ' #   ', '#  ##', '   ##'),
    '=': ('     ', '     ', '#####', '     ', '#####', '     ', '     '),
    "'": ('  #  ', '  #  ', ' #   ', '     ', '     ', '     ', '     '),
    '_': ('     ', '     ', '     ', '     ', '     ', '     ', '#####'),
    ' ': ('     ', '     ', '     ', '     ', '     ', '     ', '     '),
}
_FONT = {ch: np.array([[c == "#" for c in row] for row in rows], dtype=bool) for ch, rows in _FONT_ROWS.items()}


def text_width(text: str, scale: int = 2) -> int:
    """Width in pixels of ``text`` drawn with :func:`draw_label`."""
    return len(text) * 6 * scale


def _render(text: str, scale: int) -> np.ndarray:
    """A boolean mask of ``text`` (upper-cased; unknown characters become spaces)."""
    cells = [_FONT.get(ch, _FONT[" "]) for ch in text.upper()]
    if not cells:
        return np.zeros((7 * scale, 0), dtype=bool)
    row = np.concatenate([np.pad(c, ((0, 0), (0, 1))) for c in cells], axis=1)
    return np.kron(row, np.ones((scale, scale), dtype=bool))


def draw_label(img: np.ndarray, text: str, row: int, col: int, scale: int = 2, colour: Colour = (0, 0, 0),
               vertical: bool = False) -> None:
    """Write ``text`` on an RGB image with its top-left corner at ``(row, col)``; ``vertical``
    writes it bottom to top (a y-axis title). Pixels outside the image are clipped."""
    mask = _render(text, scale)
    if vertical:
        mask = np.rot90(mask)
    h, w = img.shape[:2]
    r0, c0 = max(row, 0), max(col, 0)
    r1, c1 = min(h, row + mask.shape[0]), min(w, col + mask.shape[1])
    if r1 > r0 and c1 > c0:
        img[r0:r1, c0:c1][mask[r0 - row: r1 - row, c0 - col: c1 - col]] = colour


def _nice_ticks(lo: float, hi: float, count: int = 5, minimum: int = 3, integer: bool = False) -> list[float]:
    """Round tick values covering ``[lo, hi]`` (steps of 1, 2 or 5 times a power of ten): about
    ``count`` of them, at least ``minimum`` (a single tick says nothing about the scale), whole
    numbers only when ``integer`` (episodes)."""
    span = max(hi - lo, 1e-9)
    raw = span / max(count - 1, 1)
    power = 10.0 ** np.floor(np.log10(raw))
    step = next(m * power for m in (1.0, 2.0, 5.0, 10.0) if m * power >= raw)
    if integer:
        step = max(step, 1.0)

    def ticks(step: float) -> list[float]:
        first = np.ceil(lo / step - 1e-9) * step + 0.0  # + 0.0: never a "-0" tick
        return [float(v) for v in np.arange(first, hi + step * 0.5, step) if lo - 1e-9 <= v <= hi + 1e-9]

    out = ticks(step)
    for _ in range(6):  # a finer step while too few ticks show: 5 -> 2 -> 1 -> 0.5 ...
        if len(out) >= minimum:
            break
        exponent = np.floor(np.log10(step) + 1e-9)
        mantissa = round(step / 10.0 ** exponent)
        finer = {1: 0.5, 2: 1.0, 5: 2.0}.get(mantissa, 1.0) * 10.0 ** exponent
        if integer and finer < 1.0:
            break
        step, out = finer, ticks(finer)
    return out


def _tick_label(v: float) -> str:
    if abs(v) >= 10000:
        return f"{v / 1000:.0f}K"
    return f"{v:.0f}" if v == int(v) else f"{v:.1f}"


@dataclass
class Series:
    """One line of a chart: ``y`` against ``x``, its colour, its legend label and its width."""

    x: np.ndarray
    y: np.ndarray
    colour: Colour
    label: str
    width: int = 2


def learning_curve_chart(series: Sequence[Series], title: str, x_title: str, y_title: str,
                         notes: Sequence[str] = (), width: int = 800, height: int = 480,
                         x_integer: bool = False) -> np.ndarray:
    """An RGB line chart: title and notes (key figures) at the top, both axes with ticks and
    titles (units belong in the titles, e.g. ``"RETURN"``, ``"TRAINING TIME (S)"``), and a legend
    when there is more than one line. ``x_integer``: whole-number ticks on the x axis (episodes)."""
    img = np.full((height, width, 3), 255, dtype=np.uint8)
    legend = len(series) > 1
    top = 22 + 18 * (1 + len(notes)) + (20 if legend else 0)
    left, right, bottom = 70, 20, 56
    draw_label(img, title, 8, left, scale=2, colour=(0, 0, 0))
    for i, note in enumerate(notes):
        draw_label(img, note, 30 + 18 * i, left, scale=2, colour=(60, 60, 60))
    if legend:
        _legend(img, series, 30 + 18 * len(notes), left)
    plot_w, plot_h = width - left - right, height - top - bottom
    xs = [np.asarray(s.x, dtype=np.float64) for s in series if len(s.x)]
    ys = [np.asarray(s.y, dtype=np.float64) for s in series if len(s.y)]
    x0, x1 = (min(float(x.min()) for x in xs), max(float(x.max()) for x in xs)) if xs else (0.0, 1.0)
    y0, y1 = (min(0.0, *(float(y.min()) for y in ys)), max(0.0, *(float(y.max()) for y in ys))) if ys else (0.0, 1.0)
    x1, y1 = (x1 if x1 > x0 else x0 + 1.0), (y1 if y1 > y0 else y0 + 1.0)

    def to_px(x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return top + plot_h - (y - y0) / (y1 - y0) * plot_h, left + (x - x0) / (x1 - x0) * plot_w

    for v in _nice_ticks(y0, y1):
        r = int(round(to_px(np.array(x0), np.array(v))[0]))
        img[r, left:left + plot_w] = 230 if v else 180
        label = _tick_label(v)
        draw_label(img, label, r - 7, left - 8 - text_width(label), colour=(80, 80, 80))
    for v in _nice_ticks(x0, x1, integer=x_integer):
        c = int(round(to_px(np.array(v), np.array(y0))[1]))
        img[top + plot_h: top + plot_h + 5, c] = 120
        label = _tick_label(v)
        draw_label(img, label, top + plot_h + 8, c - text_width(label) // 2, colour=(80, 80, 80))
    img[top:top + plot_h, left] = 120
    img[top + plot_h, left:left + plot_w] = 120
    draw_label(img, x_title, height - 22, left + (plot_w - text_width(x_title)) // 2)
    draw_label(img, y_title, top + (plot_h + text_width(y_title)) // 2, 12, vertical=True)
    for s in series:
        if len(s.x):
            rows, cols = to_px(np.asarray(s.x, dtype=np.float64), np.asarray(s.y, dtype=np.float64))
            if len(rows) == 1:  # one point: a dot
                rows, cols = np.repeat(rows, 2), np.repeat(cols, 2)
            _polyline(img, rows, cols, s.colour, s.width)
    return img


def _legend(img: np.ndarray, series: Sequence[Series], row: int, col: int) -> None:
    """A one-row legend from ``(row, col)``: a line sample, then the label, for each series."""
    for s in series:
        img[row + 6: row + 6 + max(s.width, 2), col: col + 24] = s.colour
        draw_label(img, s.label, row, col + 30)
        col += 30 + text_width(s.label) + 24


def lap_chart(topdown: np.ndarray, path_px: np.ndarray, title: str, notes: Sequence[str], metres_per_pixel: float,
              colour: Colour = (230, 40, 40)) -> np.ndarray:
    """The top-down track (grayscale ``topdown``) with the lap drawn over it (``path_px``:
    ``(N, 2)`` pixel rows and columns), a title, notes (the lap time) and a scale bar."""
    h, w = topdown.shape
    band = 24 + 18 * (1 + len(notes))
    img = np.full((h + band + 30, max(w, 420), 3), 255, dtype=np.uint8)
    img[band:band + h, :w] = topdown[:, :, None]
    if len(path_px) >= 2:
        _polyline(img, path_px[:, 0] + band, path_px[:, 1], colour, width=2)
    draw_label(img, title, 8, 8)
    for i, note in enumerate(notes):
        draw_label(img, note, 30 + 18 * i, 8, colour=(60, 60, 60))
    target = w * metres_per_pixel / 4.0  # a bar of about a quarter of the picture, rounded
    power = 10.0 ** np.floor(np.log10(max(target, 1e-9)))
    metres = next(m * power for m in (5.0, 2.0, 1.0) if m * power <= target)
    length = int(round(metres / metres_per_pixel))
    r = band + h + 12
    img[r:r + 3, 8:8 + length] = 0
    img[r - 4:r + 7, 8] = img[r - 4:r + 7, 8 + length - 1] = 0
    draw_label(img, f"{_tick_label(metres)} M", r - 4, 16 + length)
    return img


def return_note(lap_bonus: float = 100.0) -> str:
    """What the return of a driving episode counts, for a chart: the trajectory reward gives 1 per
    10 m along the track, and ``lap_bonus`` (``REWARD_CONFIG.END_OF_TRACK``) for a completed lap."""
    return f"RETURN: 1 PER 10 M DRIVEN ALONG THE TRACK, +{lap_bonus:g} PER LAP"


def learning_curve_image(returns: Sequence[float], title: str, notes: Sequence[str],
                         explain: str | None = None) -> np.ndarray:
    """A learning curve: the return of every episode and its running mean, against episodes.

    Args:
        returns: each episode's return, in order.
        title: the chart's title.
        notes: key figures, one line each under the title.
        explain: what a return counts (default :func:`return_note`), a line under the notes.
    """
    y = np.asarray(returns, dtype=np.float64)
    x = np.arange(1, len(y) + 1)
    k = max(1, min(20, len(y) // 5))
    mean = np.convolve(y, np.ones(k) / k, mode="valid") if len(y) >= k else y
    series = [Series(x, y, (150, 180, 230), "EACH EPISODE", 1)]
    if k > 1:  # under 10 episodes, the mean of one would only draw the same line again
        series.append(Series(x[len(x) - len(mean):], mean, (20, 60, 180), f"MEAN OF {k} EPISODES", 3))
    lines = [*notes, return_note() if explain is None else explain]
    return learning_curve_chart(series, title, "EPISODE", "RETURN", lines, x_integer=True)


def lap_image(track: Any, path: np.ndarray, title: str, notes: Sequence[str], size: int = 800) -> np.ndarray:
    """A lap (``path``: ``(N, 2)`` world positions) over the top-down ``track`` (a
    :class:`tmrl.sim.track.Track`), with a title, notes and a scale bar."""
    from tmrl.sim.render import track_map

    tmap = track_map(track)
    shrink = max(1, int(np.ceil(max(tmap.height, tmap.width) / size)))
    pixels = tmap.to_topdown_pixels(np.asarray(path), size) if len(path) else np.zeros((0, 2))
    return lap_chart(tmap.topdown(size), pixels, title, notes, tmap.resolution * shrink)
