"""The physical limit of a track: a planned lap at the car's limits, and a driver that drives it.

How fast can the simulator's car go round a track? This module answers in two steps.

1. :func:`plan_lap` plans a lap that knows the car's limits (:class:`~tmrl.sim.car.CarParams`):

   - a **racing line** inside the road, the centre line moved along its normals by at most
     ``half_width - radius - margin`` (pinned to the centre at the start line, where the car
     starts), chosen to minimise the curvature (a small quadratic program with bounds, solved by
     projected Newton steps);
   - a **speed profile** along that line: the highest speed at each point that the tyres' grip
     (``sqrt(grip / |curvature|)``) and the steering lock (which shrinks with speed) allow, then
     a forward pass with the engine (its push fading to top speed, less drag and rolling
     resistance) from a standstill at the start line, and a backward pass with the brakes (plus
     drag and rolling resistance) from the finish line;
   - the **planned lap time**, the integral of ``ds / v``. It is an idealised figure: the plan
     changes curvature and pedal instantly and never leaves its line, so no driver of that line
     beats it. (Two things could, by a little: another line, and power-sliding: the tyres' grip
     bounds how fast the velocity turns, but the engine pushes along the car's heading, so a car
     pointing into the bend turns a little harder; on the same line that bounds the lap about
     0.3 % lower.)

2. :class:`PlanDriver` drives the plan in the simulator (:class:`~tmrl.sim.race.Race`): pure
   pursuit on the racing line for the steering, the planned speed a step ahead as the target for
   proportional gas and brake. Its lap time, :func:`reference_lap_time`, is the **reference lap
   time** of the track: a lap really driven with the simulator's physics, without touching a
   wall, within 0.1 % of the plan on the named tracks.

Nothing is computed on import; a plan and a driven lap take about 0.2 s per track, and
:func:`reference_lap_time` remembers its answers. ``python -m tmrl.sim.reference`` prints the
table of the named tracks.
"""

from __future__ import annotations

import hashlib
import math
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from tmrl.sim.car import CarParams
from tmrl.sim.race import PHYSICS_DT, Race, follow_centre_line
from tmrl.sim.track import TRACK_NAMES, Track, make_track

__all__ = [
    "PlanDriver",
    "RacingPlan",
    "ReferenceLap",
    "drive_lap",
    "plan_lap",
    "racing_line",
    "reference_lap",
    "reference_lap_time",
    "reference_table",
    "speed_limits",
    "speed_profile",
]

LINE_STEP = 1.0
"""Spacing in metres of the racing line's free points (the unknowns of the quadratic program)."""
PLAN_SPACING = 0.25
"""Spacing in metres of the planned line and speed profile."""
MARGIN = 0.25
"""Room in metres kept between the racing line and the walls (the car's ``radius`` excluded)."""


# ------------------------------------------------------------------------------------------------
# the racing line


def _band_matvec(d0: np.ndarray, d1: np.ndarray, d2: np.ndarray, v: np.ndarray) -> np.ndarray:
    """``H v`` for the symmetric cyclic band matrix with ``H[i, i] = d0[i]``,
    ``H[i, i+1] = d1[i]`` and ``H[i, i+2] = d2[i]`` (indices modulo the size)."""
    return (d0 * v + d1 * np.roll(v, -1) + np.roll(d1 * v, 1) + d2 * np.roll(v, -2) + np.roll(d2 * v, 2))


def _band_solve(d0: np.ndarray, d1: np.ndarray, d2: np.ndarray, free: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Solve ``H[free, free] x = b`` for the band matrix of :func:`_band_matvec`, when the free
    indices never wrap round (indices 0 and 1 held): an LDL' factorisation of a
    five-band matrix, in O(len(free))."""
    f = np.flatnonzero(free)
    gap1 = np.diff(f)
    gap2 = f[2:] - f[:-2]
    a0 = d0[f].tolist()
    a1 = np.where(gap1 == 1, d1[f[:-1]], np.where(gap1 == 2, d2[f[:-1]], 0.0)).tolist() + [0.0]
    a2 = np.where(gap2 == 2, d2[f[:-2]], 0.0).tolist() + [0.0, 0.0]
    n = len(f)
    dd, l1, l2 = [0.0] * n, [0.0] * n, [0.0] * n
    for i in range(n):
        di = a0[i]
        if i >= 1:
            di -= l1[i - 1] * l1[i - 1] * dd[i - 1]
        if i >= 2:
            di -= l2[i - 2] * l2[i - 2] * dd[i - 2]
        dd[i] = di
        c = a1[i] - (l2[i - 1] * l1[i - 1] * dd[i - 1] if i >= 1 else 0.0)
        l1[i] = c / di
        l2[i] = a2[i] / di
    z = b.tolist()
    for i in range(n):
        if i >= 1:
            z[i] -= l1[i - 1] * z[i - 1]
        if i >= 2:
            z[i] -= l2[i - 2] * z[i - 2]
    x = [0.0] * n
    for i in range(n - 1, -1, -1):
        xi = z[i] / dd[i]
        if i + 1 < n:
            xi -= l1[i] * x[i + 1]
        if i + 2 < n:
            xi -= l2[i] * x[i + 2]
        x[i] = xi
    return np.array(x)


def _box_qp(bands: tuple[np.ndarray, np.ndarray, np.ndarray], g: np.ndarray, lo: np.ndarray, hi: np.ndarray,
            iterations: int = 100) -> np.ndarray:
    """``argmin 0.5 x'Hx + g'x`` subject to ``lo <= x <= hi``, H positive definite given by its
    ``bands`` (:func:`_band_matvec`), indices 0 and 1 held: projected Newton
    steps (Bertsekas), Newton on the variables not held at a bound, a projected line search."""
    x = np.clip(np.zeros_like(g), lo, hi)

    def f(v: np.ndarray) -> float:
        return float(0.5 * v @ _band_matvec(*bands, v) + g @ v)

    fx = f(x)
    for _ in range(iterations):
        grad = _band_matvec(*bands, x) + g
        held = ((x <= lo + 1e-9) & (grad > 0.0)) | ((x >= hi - 1e-9) & (grad < 0.0))
        held[:2] = True
        free = ~held
        if not free.any() or np.max(np.abs(grad[free])) < 1e-10:
            break
        d = np.zeros_like(x)
        d[free] = -_band_solve(*bands, free, grad[free])
        t = 1.0
        while True:
            xn = np.clip(x + t * d, lo, hi)
            fn = f(xn)
            if fn <= fx + 1e-4 * float(grad @ (xn - x)) or t < 1e-8:
                break
            t *= 0.5
        done = np.max(np.abs(xn - x)) < 1e-9
        x, fx = xn, fn
        if done:
            break
    return x


def _resample_closed(points: np.ndarray, spacing: float = 0.0, count: int = 0) -> np.ndarray:
    """A closed polyline resampled evenly along its length (first point kept): ``count`` points, or
    points about ``spacing`` metres apart."""
    closed = np.concatenate([points, points[:1]], axis=0)
    cum = np.concatenate(([0.0], np.cumsum(np.linalg.norm(np.diff(closed, axis=0), axis=1))))
    n = count or max(round(cum[-1] / spacing), 3)
    s = np.linspace(0.0, cum[-1], n, endpoint=False)
    return np.stack([np.interp(s, cum, closed[:, 0]), np.interp(s, cum, closed[:, 1])], axis=1)


def _spline_loop(ctrl: np.ndarray, per_segment: int) -> np.ndarray:
    """Dense points of the closed uniform cubic B-spline of the control points ``ctrl``: its
    curvature is continuous, and it stays within millimetres of control points a metre apart."""
    p0, p1, p2, p3 = np.roll(ctrl, 1, axis=0), ctrl, np.roll(ctrl, -1, axis=0), np.roll(ctrl, -2, axis=0)
    t = np.linspace(0.0, 1.0, per_segment, endpoint=False)[None, :, None]
    b0, b1 = (1 - t) ** 3 / 6, (3 * t ** 3 - 6 * t ** 2 + 4) / 6
    b2, b3 = (-3 * t ** 3 + 3 * t ** 2 + 3 * t + 1) / 6, t ** 3 / 6
    return (b0 * p0[:, None] + b1 * p1[:, None] + b2 * p2[:, None] + b3 * p3[:, None]).reshape(-1, 2)


def _lateral(track: Track, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The nearest centre point of each point of a line round the track, and the point's signed
    distance from the centre line."""
    index, lateral, hint = np.empty(len(points), dtype=int), np.empty(len(points)), 0
    for k, q in enumerate(points):
        hint, lateral[k], _ = track.locate(q, hint, window=400)
        index[k] = hint
    return index, lateral


def racing_line(track: Track, params: CarParams | None = None, margin: float = MARGIN,
                step: float = LINE_STEP, iterations: int = 5) -> tuple[np.ndarray, np.ndarray]:
    """The minimum-curvature line inside the road.

    The line is a closed loop of points about ``step`` metres apart, each moved from a reference
    line along its normal; the moves minimise the sum of squared second differences of the points
    (the curvature, for evenly spaced points), subject to staying within
    ``half_width - radius - margin`` of the centre line, and to the first point being the centre of
    the start line (where the car starts): a quadratic program with bounds. The reference line is
    the centre line at first, then the previous solution respaced evenly (``iterations`` solves:
    moves towards the inside of a bend bunch the points up, which the next solve corrects).

    Args:
        track: the track.
        params: the car (its ``radius``); default :class:`~tmrl.sim.car.CarParams`.
        margin: room kept between the car's side and the walls, in metres.
        step: spacing of the line's points, in metres.
        iterations: quadratic programs solved, each around the previous line.

    Returns:
        ``(points, lateral)``: the ``(M, 2)`` points of the line, ``points[0]`` the start line's
        centre, and their signed distances from the centre line (m, positive to the left).
    """
    params = params or CarParams()
    m = max(round(track.length / step), 8)
    room = max(track.half_width - params.radius - margin, 0.0)
    # evenly spread round the loop, the start line first (no short gap where the loop closes)
    idx = np.round(np.linspace(0, track.n_points, m, endpoint=False)).astype(int)
    ref, nrm, lat = track.centre[idx], track.normals[idx], np.zeros(m)
    # squared second differences of the closed line, d[i] = p[i-1] - 2 p[i] + p[i+1] with
    # p = ref + move * normal: sum |d|^2 = move' ((A'A) o (N N')) move + 2 (N o A'A ref)' move + const
    # (A the cyclic second difference, A'A the cyclic band 1 -4 6 -4 1, o the elementwise product)
    for it in range(iterations):
        # bounds on the move along the reference's normal: the walls, less the reference's own offset
        tilt = np.maximum(np.abs(np.sum(nrm * track.normals[idx], axis=1)), 0.5)
        lo, hi = (-room - lat) / tilt, (room - lat) / tilt
        # the car starts on the centre of the start line, heading along the track: the line's first
        # two points stay on the centre line (and the free points never wrap round the band matrix)
        lo[:2] = hi[:2] = -lat[:2] / tilt[:2]
        bands = (np.full(m, 6.0 + 1e-9), -4.0 * np.sum(nrm * np.roll(nrm, -1, axis=0), axis=1),
                 np.sum(nrm * np.roll(nrm, -2, axis=0), axis=1))
        ata_ref = 6.0 * ref - 4.0 * (np.roll(ref, 1, axis=0) + np.roll(ref, -1, axis=0)) \
            + np.roll(ref, 2, axis=0) + np.roll(ref, -2, axis=0)
        g = np.sum(nrm * ata_ref, axis=1)
        line = ref + _box_qp(bands, g, lo, hi)[:, None] * nrm
        if it + 1 < iterations:
            ref = _resample_closed(line, count=m)
            d = np.roll(ref, -1, axis=0) - np.roll(ref, 1, axis=0)
            d /= np.linalg.norm(d, axis=1, keepdims=True)
            nrm = np.stack([-d[:, 1], d[:, 0]], axis=1)
            idx, lat = _lateral(track, ref)
    return line, _lateral(track, line)[1]


# ------------------------------------------------------------------------------------------------
# the speed profile


def speed_limits(curvature: np.ndarray, params: CarParams | None = None) -> np.ndarray:
    """The highest speed (m/s) at which the car can follow each curvature: the lower of the
    tyres' grip, ``sqrt(grip / |curvature|)``, and the steering lock, which at speed ``u`` gives at
    most ``tan(max_steer / (1 + u / steer_speed)) / wheelbase``; never above ``top_speed``.

    Args:
        curvature: curvatures in 1/m (any sign).
        params: the car; default :class:`~tmrl.sim.car.CarParams`.
    """
    p = params or CarParams()
    k = np.maximum(np.abs(np.asarray(curvature, dtype=np.float64)), 1e-9)
    grip = np.sqrt(p.grip / k)
    lock = np.arctan(k * p.wheelbase)  # the steering angle the curvature needs
    steer = np.where(lock < p.max_steer, p.steer_speed * (p.max_steer / lock - 1.0), 0.0)
    return np.minimum(np.minimum(grip, steer), p.top_speed)


def _engine(v: np.ndarray | float, p: CarParams) -> np.ndarray | float:
    """Acceleration at full gas (m/s^2): the engine less drag and rolling resistance."""
    return p.engine * np.maximum(0.0, 1.0 - v / p.top_speed) - p.drag * v * v - p.rolling


def _brakes(v: np.ndarray | float, p: CarParams) -> np.ndarray | float:
    """Deceleration at full brake (m/s^2): the brakes plus drag and rolling resistance."""
    return p.brake + p.drag * v * v + p.rolling


def speed_profile(limit: np.ndarray, ds: float, params: CarParams | None = None) -> np.ndarray:
    """The fastest speeds along a lap under pointwise limits, from a standstill.

    A backward pass from the finish (the speed at each point is at most what the brakes can bring
    down to the next point's speed) and a forward pass from rest at the start (at most what full
    gas reaches from the previous point's speed), each integrating ``d(v^2)/ds = 2 a(v)`` with a
    midpoint step.

    Args:
        limit: ``(M + 1,)`` speed limits in m/s at points ``ds`` apart, from the start line
            (``limit[0]``) round to the finish line (``limit[M]``, the same place).
        ds: spacing of the points in metres.
        params: the car; default :class:`~tmrl.sim.car.CarParams`.

    Returns:
        ``(M + 1,)`` speeds in m/s, ``0`` at the start.
    """
    p = params or CarParams()
    v = np.array(limit, dtype=np.float64)
    v[0] = 0.0
    lim = v.tolist()
    out = list(lim)
    # backward: braking into each point from the one before it
    for i in range(len(out) - 2, -1, -1):
        nxt = out[i + 1]
        mid = math.sqrt(nxt * nxt + _brakes(nxt, p) * ds)
        out[i] = min(out[i], math.sqrt(nxt * nxt + 2.0 * _brakes(mid, p) * ds))
    # forward: accelerating out of each point into the next
    for i in range(len(out) - 1):
        cur = out[i]
        mid = math.sqrt(max(cur * cur + _engine(cur, p) * ds, 0.0))
        out[i + 1] = min(out[i + 1], math.sqrt(max(cur * cur + 2.0 * _engine(mid, p) * ds, 0.0)))
    return np.array(out)


def _lap_time(v: np.ndarray, ds: float) -> float:
    """``integral ds / v`` with the speed linear in time between points (constant acceleration)."""
    mean = 0.5 * (v[1:] + v[:-1])
    return float(np.sum(ds / np.maximum(mean, 1e-9)))


@dataclass(frozen=True, eq=False)
class RacingPlan:
    """A planned lap: the racing line, its speeds and the planned lap time.

    Attributes:
        track: the track.
        params: the car the plan is for.
        points: ``(M, 2)`` racing line points ``spacing`` apart, ``points[0]`` on the start line,
            the loop closing from ``points[-1]`` back to ``points[0]``.
        spacing: distance between consecutive points (m).
        curvature: ``(M,)`` signed curvature of the line at each point (1/m, positive left).
        limit: ``(M,)`` highest speed at each point from grip and steering (m/s).
        speed: ``(M + 1,)`` planned speed at each point and at the finish line (m/s).
        lap_time: the planned lap time (s): ``integral ds / speed``.
        offsets: signed distances of the racing line's control points (1 m apart) from the
            centre line (m, positive to the left).
    """

    track: Track
    params: CarParams
    points: np.ndarray
    spacing: float
    curvature: np.ndarray
    limit: np.ndarray
    speed: np.ndarray
    lap_time: float
    offsets: np.ndarray = field(repr=False)

    @property
    def length(self) -> float:
        """Length of the racing line (m)."""
        return self.spacing * len(self.points)


def _curvature(points: np.ndarray, spacing: float) -> np.ndarray:
    """Signed curvature of a closed line of evenly spaced points, from its heading changes."""
    d = np.roll(points, -1, axis=0) - np.roll(points, 1, axis=0)
    heading = np.arctan2(d[:, 1], d[:, 0])
    dh = (np.roll(heading, -1) - np.roll(heading, 1) + np.pi) % (2 * np.pi) - np.pi
    return dh / (2.0 * spacing)


def plan_lap(track: Track | str | int, params: CarParams | None = None, margin: float = MARGIN) -> RacingPlan:
    """Plan a lap at the car's limits: racing line (:func:`racing_line`), speed limits
    (:func:`speed_limits`), speed profile from a standstill (:func:`speed_profile`), lap time.

    Args:
        track: a :class:`~tmrl.sim.track.Track`, or a name or seed for
            :func:`~tmrl.sim.track.make_track`.
        params: the car; default :class:`~tmrl.sim.car.CarParams`.
        margin: room kept between the car's side and the walls, in metres.
    """
    track = track if isinstance(track, Track) else make_track(track)
    params = params or CarParams()
    ctrl, offsets = racing_line(track, params, margin)
    points = _resample_closed(_spline_loop(ctrl, 40), PLAN_SPACING)
    spacing = float(np.sum(np.linalg.norm(np.diff(points, axis=0, append=points[:1]), axis=1)) / len(points))
    kappa = _curvature(points, spacing)
    limit = speed_limits(kappa, params)
    speed = speed_profile(np.append(limit, limit[0]), spacing, params)
    return RacingPlan(track=track, params=params, points=points, spacing=spacing, curvature=kappa, limit=limit,
                      speed=speed, lap_time=_lap_time(speed, spacing), offsets=offsets)


# ------------------------------------------------------------------------------------------------
# driving the plan


class PlanDriver:
    """A driver for :class:`~tmrl.sim.race.Race` that follows a :class:`RacingPlan`.

    Steering is pure pursuit on the racing line (the arc through a point ``look_ahead + look_time *
    speed`` metres ahead, turned into a steering input through the bicycle model and the lock at
    the current speed); gas and brake are proportional, aiming at the planned speed (times
    ``pace``) where the car will be when it acts next.

    Args:
        plan: the planned lap.
        look_ahead: base distance to the aimed point (m).
        look_time: seconds of travel added to the distance to the aimed point.
        pace: share of the planned speed aimed at.
        control_dt: seconds between two actions (default: the race's physics step, an action at
            every step).
    """

    def __init__(self, plan: RacingPlan, look_ahead: float = 3.0, look_time: float = 0.12,
                 pace: float = 1.0, control_dt: float | None = None) -> None:
        self.plan = plan
        self.control_dt = control_dt
        self.look_ahead = float(look_ahead)
        self.look_time = float(look_time)
        self.pace = float(pace)
        self._xs = plan.points[:, 0].tolist()
        self._ys = plan.points[:, 1].tolist()
        self._speed = (np.asarray(plan.speed) * self.pace).tolist()
        self.index = 0

    def reset(self) -> None:
        """Start again from the start line (call it with :meth:`~tmrl.sim.race.Race.reset`)."""
        self.index = 0

    def _locate(self, x: float, y: float) -> int:
        xs, ys, n = self._xs, self._ys, len(self._xs)
        i = self.index % n
        best = (xs[i] - x) ** 2 + (ys[i] - y) ** 2
        for step in (1, -1):
            moved = False
            for _ in range(400):
                j = (i + step) % n
                d = (xs[j] - x) ** 2 + (ys[j] - y) ** 2
                if d >= best:
                    break
                i, best, moved = j, d, True
            if moved:
                break
        self.index = i
        return i

    def __call__(self, race: Race) -> np.ndarray:
        """The action ``[gas, brake, steer]`` (float32) for the race's current state.

        Args:
            race: the race (the driver reads the car's state and the physics step).
        """
        p, s, dt = race.car.params, race.car.state, self.control_dt or race.physics_dt
        n, ds = len(self._xs), self.plan.spacing
        i = self._locate(s.x, s.y)
        u = max(s.forward_speed, 0.0)
        # steering: pure pursuit towards a point of the line ahead
        j = (i + max(1, round((self.look_ahead + self.look_time * u) / ds))) % n
        dx, dy = self._xs[j] - s.x, self._ys[j] - s.y
        dist = max(math.hypot(dx, dy), 1e-6)
        angle = math.atan2(dy, dx) - s.heading
        kappa = 2.0 * math.sin(angle) / dist
        lock = p.max_steer / (1.0 + u / p.steer_speed)
        steer = min(max(-math.atan(kappa * p.wheelbase) / lock, -1.0), 1.0)
        # speed: the planned speed where the car will be after this step
        k = i + 1 + int(u * dt / ds)
        target = self._speed[min(k, n)]  # speed[n]: the finish line
        if u < target:
            push = p.engine * max(0.0, 1.0 - u / p.top_speed)
            need = (target - u) / dt + p.drag * u * u + p.rolling
            gas, brake = min(max(need / max(push, 1e-6), 0.0), 1.0), 0.0
        else:
            need = (u - target) / dt - p.drag * u * u - p.rolling
            gas, brake = 0.0, min(max(need / p.brake, 0.0), 1.0)
        return np.array([gas, brake, steer], dtype=np.float32)


@dataclass(frozen=True)
class ReferenceLap:
    """The reference figures of one track.

    Attributes:
        track: the track's name.
        planned: the planned lap time (s), an idealised bound (:func:`plan_lap`).
        driven: the lap time of :class:`PlanDriver` in the simulator (s): the reference lap time.
        wall_hits: wall contacts during the driven lap.
        centre_line: the lap time of :func:`~tmrl.sim.race.follow_centre_line` (s), or None when
            not measured.
    """

    track: str
    planned: float
    driven: float
    wall_hits: int
    centre_line: float | None = None


def drive_lap(track: Track, driver: Callable[[Race], np.ndarray], max_time: float = 300.0,
              control_dt: float = PHYSICS_DT) -> tuple[float, int]:
    """Drive one lap of ``track`` from the start line (physics step :data:`~tmrl.sim.race.PHYSICS_DT`).

    Args:
        track: the track.
        driver: a callable ``driver(race) -> [gas, brake, steer]`` (such as :class:`PlanDriver` or
            :func:`~tmrl.sim.race.follow_centre_line`).
        max_time: simulated seconds after which the lap is given up.
        control_dt: seconds between two actions (default: one physics step).

    Returns:
        ``(lap_time, wall_hits)``.

    Raises:
        RuntimeError: the lap was not completed within ``max_time``.
    """
    race = Race(track)
    while not race.finished:
        if race.time > max_time:
            raise RuntimeError(f"no lap of {track.name} within {max_time:g} s")
        race.advance(driver(race), control_dt)
    return float(race.lap_time), race.car.state.wall_hits  # type: ignore[arg-type]


_CACHE: dict[tuple, ReferenceLap] = {}


def _key(track: Track) -> tuple:
    digest = hashlib.blake2b(np.ascontiguousarray(track.centre).tobytes(), digest_size=16).hexdigest()
    return track.name, float(track.half_width), digest


def reference_lap(track: Track | str | int, centre_line: bool = False) -> ReferenceLap:
    """Plan a lap of ``track`` and drive it: the planned bound, the driven reference lap time and
    its wall hits (remembered per track: the second call is free).

    Args:
        track: a :class:`~tmrl.sim.track.Track`, or a name or seed for
            :func:`~tmrl.sim.track.make_track`.
        centre_line: also drive a lap with :func:`~tmrl.sim.race.follow_centre_line`.

    Raises:
        RuntimeError: a driver did not complete the lap (see :func:`drive_lap`).
    """
    track = track if isinstance(track, Track) else make_track(track)
    key = _key(track)
    ref = _CACHE.get(key)
    if ref is None:
        plan = plan_lap(track)
        driven, hits = drive_lap(track, PlanDriver(plan))
        ref = ReferenceLap(track=track.name, planned=plan.lap_time, driven=driven, wall_hits=hits)
    if centre_line and ref.centre_line is None:
        ref = ReferenceLap(ref.track, ref.planned, ref.driven, ref.wall_hits, drive_lap(track, follow_centre_line)[0])
    _CACHE[key] = ref
    return ref


def reference_lap_time(track: Track | str | int) -> float:
    """The reference lap time of ``track`` in simulated seconds: a lap driven at the car's limits by
    :class:`PlanDriver` on the planned racing line (see :func:`reference_lap`).

    Args:
        track: a :class:`~tmrl.sim.track.Track`, or a name or seed for
            :func:`~tmrl.sim.track.make_track`.
    """
    return reference_lap(track).driven


def reference_table(names: tuple[str, ...] = TRACK_NAMES) -> list[ReferenceLap]:
    """The reference figures of the named tracks (the centre-line driver's time included).

    Args:
        names: track names or seeds.
    """
    return [reference_lap(name, centre_line=True) for name in names]


if __name__ == "__main__":
    print(f"{'track':10s} {'planned':>8s} {'driven':>8s} {'ratio':>6s} {'walls':>5s} {'centre line':>11s}")
    for r in reference_table():
        print(f"{r.track:10s} {r.planned:8.2f} {r.driven:8.2f} {r.driven / r.planned:6.3f} {r.wall_hits:5d} "
              f"{r.centre_line:11.2f}")
