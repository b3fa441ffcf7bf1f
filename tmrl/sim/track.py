"""Race tracks of the built-in simulator.

A track is a closed loop of road of constant width between two walls, described by its centre
line sampled every 0.1 m. The start and finish line is at the first centre point: the car starts
on it, heading along the loop, and completes a lap when it crosses it again after going round.
The reward trajectory is the centre line from the start line round to the finish line, the same
object a TrackMania user records with ``--record-reward``.

Tracks come from a seed (:func:`track_from_seed`, any integer gives a valid track) or by name
(:data:`TRACK_NAMES`: ``"oval"`` easy, ``"classic"`` the default, ``"technical"`` hard).
:func:`make_track` accepts either. Every track is checked when built: its tightest bend is wider
than the road and two parts of the loop never come close enough for their walls to meet.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass, field

import numpy as np

from tmrl.errors import UserError

__all__ = [
    "DEFAULT_TRACK",
    "POINT_SPACING",
    "TRACK_NAMES",
    "Track",
    "make_track",
    "named_track",
    "track_from_seed",
]

POINT_SPACING = 0.1
"""Distance between consecutive centre points, in metres (the reward recorder's spacing)."""
BORDER_WIDTH = 1.0
"""Width of the black border drawn outside each wall, in metres."""

DEFAULT_TRACK = "classic"
"""The track :func:`make_track` gives when none is named."""


@dataclass(frozen=True, eq=False)
class Track:
    """A closed-loop track.

    Attributes:
        name: the track's name (``"seed-<n>"`` for generated ones).
        centre: ``(N, 2)`` centre points in metres, ``POINT_SPACING`` apart, ``centre[0]`` on the
            start/finish line; the loop closes from ``centre[-1]`` back to ``centre[0]``.
        half_width: distance from the centre line to each wall, in metres.
        difficulty: ``"easy"``, ``"medium"`` or ``"hard"``.
        spacing: distance between consecutive centre points, in metres (default
            :data:`POINT_SPACING`).
        tangents: ``(N, 2)`` unit vectors along the loop at each centre point (computed).
        normals: ``(N, 2)`` unit vectors to the left of the tangents (computed).
        curvature: ``(N,)`` signed curvature at each centre point, in 1/m, positive in left bends
            (computed).

    Every array is read-only. Build tracks with :func:`make_track` rather than by hand.
    """

    name: str
    centre: np.ndarray
    half_width: float
    difficulty: str = "medium"
    spacing: float = POINT_SPACING
    tangents: np.ndarray = field(init=False, repr=False)
    normals: np.ndarray = field(init=False, repr=False)
    curvature: np.ndarray = field(init=False, repr=False)

    def __post_init__(self) -> None:
        c = self.centre
        d = np.roll(c, -1, axis=0) - np.roll(c, 1, axis=0)
        t = d / np.linalg.norm(d, axis=1, keepdims=True)
        object.__setattr__(self, "tangents", t)
        # Left normal: the tangent turned by +90 degrees.
        object.__setattr__(self, "normals", np.stack([-t[:, 1], t[:, 0]], axis=1))
        heading = np.arctan2(t[:, 1], t[:, 0])
        dh = (np.roll(heading, -1) - heading + np.pi) % (2 * np.pi) - np.pi
        object.__setattr__(self, "curvature", dh / self.spacing)
        for arr in (self.centre, self.tangents, self.normals, self.curvature):
            arr.setflags(write=False)
        # Plain float lists: the per-substep nearest-point walk reads a handful of points, which is
        # much faster from Python lists than from NumPy arrays.
        object.__setattr__(self, "_xs", self.centre[:, 0].tolist())
        object.__setattr__(self, "_ys", self.centre[:, 1].tolist())
        object.__setattr__(self, "_txs", t[:, 0].tolist())
        object.__setattr__(self, "_tys", t[:, 1].tolist())

    @property
    def n_points(self) -> int:
        """Number of centre points."""
        return len(self.centre)

    @property
    def length(self) -> float:
        """Length of one lap along the centre line, in metres."""
        return float(np.sum(np.linalg.norm(np.diff(self.centre, axis=0, append=self.centre[:1]), axis=1)))

    @property
    def start_position(self) -> np.ndarray:
        """Where the car starts: the centre of the start line."""
        return self.centre[0].copy()

    @property
    def start_heading(self) -> float:
        """The car's heading at the start, in radians (counter-clockwise from +x)."""
        t = self.tangents[0]
        return float(np.arctan2(t[1], t[0]))

    def reward_trajectory(self) -> np.ndarray:
        """The centre line from the start line round to the finish line, ``(N + 1, 2)``, spaced
        ``spacing`` apart (the last gap closes the loop and may be a little shorter)."""
        return np.concatenate([self.centre, self.centre[:1]], axis=0)

    def locate(self, pos: np.ndarray, hint: int, window: int = 100) -> tuple[int, float, float]:
        """The centre point nearest ``pos``, found by walking from ``hint`` along the line while
        the distance decreases (at most ``window`` points; the line's bends are wider than the
        road, so the distance has a single minimum near a car on the road).

        Returns:
            ``(index, lateral, along)``: the point's index, the signed distance to the centre line
            (positive to the left of the driving direction) and the offset along the tangent.
        """
        xs, ys, n = self._xs, self._ys, self.n_points  # type: ignore[attr-defined]
        px, py = float(pos[0]), float(pos[1])
        i = hint % n
        best = (xs[i] - px) ** 2 + (ys[i] - py) ** 2
        for step in (1, -1):
            moved = False
            for _ in range(window):
                j = (i + step) % n
                d = (xs[j] - px) ** 2 + (ys[j] - py) ** 2
                if d >= best:
                    break
                i, best, moved = j, d, True
            if moved:
                break
        rx, ry = px - xs[i], py - ys[i]
        tx, ty = self._txs[i], self._tys[i]  # type: ignore[attr-defined]
        return i, -ty * rx + tx * ry, tx * rx + ty * ry

    def bounds(self, margin: float) -> tuple[np.ndarray, np.ndarray]:
        """``(low, high)`` corners of the box holding the track, widened by ``margin`` metres."""
        lo = self.centre.min(axis=0) - self.half_width - margin
        hi = self.centre.max(axis=0) + self.half_width + margin
        return lo, hi


# ---------------------------------------------------------------------------------------------
# construction


def _catmull_rom_loop(ctrl: np.ndarray, per_segment: int = 200) -> np.ndarray:
    """Dense points of the closed centripetal Catmull-Rom spline through ``ctrl``."""
    p = np.asarray(ctrl, dtype=np.float64)
    n = len(p)
    out = []
    t = np.linspace(0.0, 1.0, per_segment, endpoint=False)[:, None]
    for i in range(n):
        p0, p1, p2, p3 = p[i - 1], p[i], p[(i + 1) % n], p[(i + 2) % n]
        # centripetal parameterisation avoids cusps and loops between unevenly spaced points
        d01 = max(np.linalg.norm(p1 - p0) ** 0.5, 1e-6)
        d12 = max(np.linalg.norm(p2 - p1) ** 0.5, 1e-6)
        d23 = max(np.linalg.norm(p3 - p2) ** 0.5, 1e-6)
        m1 = (p2 - p1 + d12 * ((p1 - p0) / d01 - (p2 - p0) / (d01 + d12)))
        m2 = (p2 - p1 + d12 * ((p3 - p2) / d23 - (p3 - p1) / (d12 + d23)))
        t2, t3 = t * t, t * t * t
        out.append((2 * t3 - 3 * t2 + 1) * p1 + (t3 - 2 * t2 + t) * m1 + (-2 * t3 + 3 * t2) * p2 + (t3 - t2) * m2)
    return np.concatenate(out, axis=0)


def _resample_loop(dense: np.ndarray, spacing: float) -> np.ndarray:
    closed = np.concatenate([dense, dense[:1]], axis=0)
    seg = np.linalg.norm(np.diff(closed, axis=0), axis=1)
    cum = np.concatenate(([0.0], np.cumsum(seg)))
    s = np.arange(0.0, cum[-1] - 0.5 * spacing, spacing)
    return np.stack([np.interp(s, cum, closed[:, 0]), np.interp(s, cum, closed[:, 1])], axis=1)


def _problems(track: Track) -> list[str]:
    """Reasons why ``track`` cannot be driven (empty when it is fine)."""
    problems = []
    min_radius = 1.0 / max(float(np.max(np.abs(track.curvature))), 1e-9)
    if min_radius < 1.6 * track.half_width:
        problems.append(f"tightest bend radius {min_radius:.1f} m is too tight for a {2 * track.half_width:.0f} m road")
    # Parts of the loop more than a road width apart along the line must stay that far apart in
    # space, or their walls would meet; checked on a 1 m subsample.
    step = max(1, int(round(1.0 / track.spacing)))
    sub = track.centre[::step]
    m = len(sub)
    d = np.linalg.norm(sub[:, None, :] - sub[None, :, :], axis=2)
    k = np.arange(m)
    along = np.abs(k[:, None] - k[None, :])
    along = np.minimum(along, m - along) * step * track.spacing
    clearance = 2 * (track.half_width + BORDER_WIDTH) + 2.0
    close = (d < clearance) & (along > np.pi * clearance)
    if close.any():
        problems.append("two parts of the loop come too close to each other")
    return problems


def _build(name: str, ctrl: np.ndarray, half_width: float, difficulty: str, start_index: int = 0) -> Track:
    centre = _resample_loop(_catmull_rom_loop(ctrl), POINT_SPACING)
    centre = np.roll(centre, -start_index, axis=0).copy()
    return Track(name=name, centre=centre, half_width=half_width, difficulty=difficulty)


def _straightest_start(track: Track) -> int:
    """Index of the point in the middle of the longest stretch with little curvature."""
    n = track.n_points
    win = int(round(40.0 / track.spacing))
    k = np.abs(track.curvature)
    # mean absolute curvature over the 40 m ahead of each point (circular moving sum)
    csum = np.concatenate(([0.0], np.cumsum(np.concatenate([k, k[:win]]))))
    ahead = (csum[win:win + n] - csum[:n]) / win
    return int(np.argmin(ahead))


_DIFFICULTY = {
    # (control points, radius in m, radial jitter, half width in m)
    "easy": (7, 70.0, 0.18, 8.0),
    "medium": (11, 80.0, 0.30, 6.0),
    "hard": (13, 85.0, 0.32, 5.0),
}


def track_from_seed(seed: int, difficulty: str = "medium") -> Track:
    """A random valid track, the same for the same ``seed`` and ``difficulty``.

    Args:
        seed: any integer.
        difficulty: ``"easy"`` (few wide bends, 16 m road), ``"medium"`` (12 m road) or ``"hard"``
            (more and tighter bends, 10 m road).

    Raises:
        UserError: an unknown difficulty.
    """
    if difficulty not in _DIFFICULTY:
        raise UserError(f"unknown track difficulty {difficulty!r}: use one of {sorted(_DIFFICULTY)}")
    return _track_from_seed(int(seed), difficulty)


@functools.lru_cache(maxsize=16)
def _track_from_seed(seed: int, difficulty: str) -> Track:
    n_ctrl, radius, jitter, half_width = _DIFFICULTY[difficulty]
    rng = np.random.default_rng([seed, n_ctrl])
    for _attempt in range(200):
        ang = 2 * np.pi * (np.arange(n_ctrl) + rng.uniform(-0.3, 0.3, n_ctrl)) / n_ctrl
        r = radius * (1.0 + jitter * rng.uniform(-1.0, 1.0, n_ctrl))
        # an ellipse rather than a circle gives long straights
        stretch = rng.uniform(1.0, 1.6)
        ctrl = np.stack([stretch * r * np.cos(ang), r * np.sin(ang)], axis=1)
        track = _build(f"seed-{seed}", ctrl, half_width, difficulty)
        if not _problems(track):
            start = _straightest_start(track)
            # resample from the new start so that the short closing gap stays at the end
            centre = _resample_loop(np.roll(track.centre, -start, axis=0), POINT_SPACING)
            return Track(name=track.name, centre=centre, half_width=half_width, difficulty=difficulty)
    raise RuntimeError(f"could not generate a valid track for seed {seed}")  # pragma: no cover


# Named tracks. The oval is given by control points (metres); the others are generated tracks
# pinned by seed, and tests pin their lengths so that a change of the generator is noticed.
_OVAL = [(0, 0), (60, 0), (105, 8), (122, 40), (105, 72), (60, 80), (0, 80), (-45, 72), (-62, 40), (-45, 8)]
_NAMED: dict[str, tuple[str, int]] = {
    "oval": ("easy", -1),
    "classic": ("medium", 0),
    "technical": ("hard", 2),
}

TRACK_NAMES: tuple[str, ...] = tuple(_NAMED)
"""Names accepted by :func:`named_track`, easiest first."""


@functools.lru_cache(maxsize=8)
def named_track(name: str) -> Track:
    """One of the fixed tracks of :data:`TRACK_NAMES`: ``"oval"`` (easy, 16 m road, 454 m),
    ``"classic"`` (the default, 12 m road, 617 m) and ``"technical"`` (hard, 10 m road, 617 m).

    Raises:
        UserError: an unknown name.
    """
    if name not in _NAMED:
        raise UserError(f"unknown track {name!r}: use one of {list(TRACK_NAMES)} or an integer seed")
    difficulty, seed = _NAMED[name]
    if name == "oval":
        return _build(name, np.array(_OVAL, dtype=np.float64), _DIFFICULTY[difficulty][3], difficulty)
    generated = track_from_seed(seed, difficulty)
    return Track(name=name, centre=generated.centre, half_width=generated.half_width, difficulty=difficulty)


def make_track(spec: str | int | None = None) -> Track:
    """A track from a name, a seed, or the default.

    Args:
        spec: a name of :data:`TRACK_NAMES`, a seed (an int, a string of digits such as ``"42"``,
            or ``"seed-42"``), or None for :data:`DEFAULT_TRACK`.

    Raises:
        UserError: neither a known name nor an integer.
    """
    if spec is None:
        return named_track(DEFAULT_TRACK)
    if isinstance(spec, (int, np.integer)):
        return track_from_seed(int(spec))
    text = str(spec).strip()
    if text.lstrip("-").isdigit():
        return track_from_seed(int(text))
    if text.startswith("seed-") and text[5:].lstrip("-").isdigit():
        return track_from_seed(int(text[5:]))
    return named_track(text)
