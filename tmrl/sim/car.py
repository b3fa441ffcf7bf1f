"""Car dynamics of the built-in simulator.

A planar model, simple enough to step thousands of times per second in plain Python and rich
enough to need driving: the heading turns like a bicycle model whose steering lock shrinks with
speed, while the velocity only follows the heading as fast as the tyres' grip allows, so a car
that turns too hard at speed slides (and scrubs speed). Gas pushes with an engine whose force
fades towards top speed, brakes are strong, braking at a standstill reverses slowly, and air drag
and rolling resistance slow the car. The walls (at the track's edges) stop the part of the
velocity that goes into them and cost a share of the rest. Gear and rpm are derived from speed.

Actions are TrackMania's: ``[gas, brake, steer]`` in [-1, 1]; gas and brake act on their positive
part (as the analog triggers do), steer > 0 turns right.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from tmrl.sim.track import Track

__all__ = ["Car", "CarParams", "CarState"]


@dataclass(frozen=True)
class CarParams:
    """Physical constants of the car (SI units).

    Attributes:
        wheelbase: distance between axles (m).
        radius: half width of the car, used against the walls (m).
        max_steer: steering lock at a standstill (rad).
        steer_speed: speed at which the lock has halved (m/s).
        grip: lateral acceleration the tyres can give before sliding (m/s^2).
        engine: forward acceleration at full gas from a standstill (m/s^2).
        top_speed: speed at which the engine no longer pushes (m/s).
        brake: deceleration at full brake (m/s^2).
        reverse: acceleration when braking at a standstill (m/s^2).
        max_reverse: top speed in reverse (m/s).
        drag: air drag coefficient (1/m), deceleration = drag * speed^2.
        rolling: rolling resistance (m/s^2).
        wall_loss: share of the speed along a wall lost at each hit.
        gear_speeds: speeds (m/s) at which gears 2, 3, ... engage.
        idle_rpm: the rpm at the bottom of each gear's speed range.
        max_rpm: the rpm at the top of each gear's speed range.
    """

    wheelbase: float = 2.6
    radius: float = 1.0
    max_steer: float = 0.6
    steer_speed: float = 15.0
    grip: float = 14.0
    engine: float = 9.0
    top_speed: float = 45.0
    brake: float = 18.0
    reverse: float = 4.0
    max_reverse: float = 8.0
    drag: float = 0.0015
    rolling: float = 0.3
    wall_loss: float = 0.2
    gear_speeds: tuple[float, ...] = (12.0, 20.0, 28.0, 36.0)
    idle_rpm: float = 2000.0
    max_rpm: float = 11000.0


@dataclass
class CarState:
    """Where the car is and how it moves.

    Attributes:
        x: position along the world's x axis (m).
        y: position along the world's y axis (m).
        heading: direction the car points to, radians counter-clockwise from +x.
        vx: velocity along x in the world frame (m/s).
        vy: velocity along y in the world frame (m/s).
        index: nearest centre point of the track.
        lateral: signed distance from the centre line, positive to the left (m).
        wall_hits: wall contacts since the car was placed.
    """

    x: float = 0.0
    y: float = 0.0
    heading: float = 0.0
    vx: float = 0.0
    vy: float = 0.0
    index: int = 0
    lateral: float = 0.0
    wall_hits: int = field(default=0)

    @property
    def speed(self) -> float:
        """Norm of the velocity (m/s)."""
        return math.hypot(self.vx, self.vy)

    @property
    def forward_speed(self) -> float:
        """Velocity along the car's heading (m/s, negative in reverse)."""
        return self.vx * math.cos(self.heading) + self.vy * math.sin(self.heading)

    @property
    def position(self) -> np.ndarray:
        """``[x, y]`` as a float64 array."""
        return np.array([self.x, self.y])


class Car:
    """The car on a track.

    Args:
        track: the track it drives on (walls at ``track.half_width``).
        params: physical constants (default :class:`CarParams`).
    """

    def __init__(self, track: Track, params: CarParams | None = None) -> None:
        self.track = track
        self.params = params or CarParams()
        self.state = CarState()
        self.reset()

    def reset(self) -> None:
        """Put the car at rest on the start line, facing along the track."""
        pos = self.track.start_position
        self.state = CarState(x=float(pos[0]), y=float(pos[1]), heading=self.track.start_heading)

    def step(self, gas: float, brake: float, steer: float, dt: float) -> bool:
        """Advance the car by ``dt`` seconds with constant inputs.

        Args:
            gas: in [-1, 1]; only the positive part acts.
            brake: in [-1, 1]; only the positive part acts (at a standstill it reverses).
            steer: in [-1, 1]; > 0 turns right.
            dt: duration in seconds (small: 0.0125 s or so).

        Returns:
            True if the car touched a wall during the step.
        """
        p, s = self.params, self.state
        gas = min(max(gas, 0.0), 1.0)
        brake = min(max(brake, 0.0), 1.0)
        steer = min(max(steer, -1.0), 1.0)
        c, sn = math.cos(s.heading), math.sin(s.heading)
        u = s.vx * c + s.vy * sn  # along the heading
        w = -s.vx * sn + s.vy * c  # to the left of the heading

        # Heading: bicycle model, lock shrinking with speed (steer > 0 turns right = clockwise).
        delta = -steer * p.max_steer / (1.0 + abs(u) / p.steer_speed)
        s.heading += u * math.tan(delta) / p.wheelbase * dt
        # The velocity stays where it was in the world: re-express it in the new heading frame.
        c2, s2 = math.cos(s.heading), math.sin(s.heading)
        u, w = s.vx * c2 + s.vy * s2, -s.vx * s2 + s.vy * c2

        # Longitudinal forces.
        if u >= 0.0:
            acc = gas * p.engine * max(0.0, 1.0 - u / p.top_speed)
            if brake > 0.0:
                acc -= brake * (p.brake if u > 0.3 else p.reverse)
        else:
            acc = gas * p.brake - brake * p.reverse * (1.0 if u > -p.max_reverse else 0.0)
        acc -= p.drag * u * abs(u) + (p.rolling * math.copysign(1.0, u) if abs(u) > 0.05 else 0.0)
        new_u = u + acc * dt
        if u > 0.3 and new_u < 0.0 and gas == 0.0:
            new_u = 0.0  # brakes stop the car; reversing needs a fresh press from rest
        u = new_u

        # Lateral grip pulls the velocity towards the heading, at most `grip` m/s^2.
        pull = p.grip * dt
        w = 0.0 if abs(w) <= pull else w - math.copysign(pull, w)

        s.vx, s.vy = u * c2 - w * s2, u * s2 + w * c2
        s.x += s.vx * dt
        s.y += s.vy * dt
        return self._walls()

    def _walls(self) -> bool:
        s, p, t = self.state, self.params, self.track
        s.index, s.lateral, _ = t.locate(np.array([s.x, s.y]), s.index)
        limit = t.half_width - p.radius
        over = abs(s.lateral) - limit
        if over <= 0.0:
            return False
        side = math.copysign(1.0, s.lateral)
        nx, ny = t.normals[s.index] * side  # points into the wall
        s.x -= over * nx
        s.y -= over * ny
        s.lateral = side * limit
        into = s.vx * nx + s.vy * ny
        if into > 0.0:
            s.vx -= into * nx
            s.vy -= into * ny
            speed = math.hypot(s.vx, s.vy)
            keep = max(0.0, 1.0 - p.wall_loss - 0.5 * into / max(speed + into, 1e-6))
            s.vx *= keep
            s.vy *= keep
        s.wall_hits += 1
        return True

    @property
    def gear(self) -> int:
        """Gear from speed: 0 in reverse, 1 at rest, up to ``len(gear_speeds) + 1``."""
        u = self.state.forward_speed
        if u < -0.1:
            return 0
        return 1 + sum(u >= g for g in self.params.gear_speeds)

    @property
    def rpm(self) -> float:
        """Engine rpm from speed: sweeps ``idle_rpm`` to ``max_rpm`` within each gear."""
        p = self.params
        u = abs(self.state.forward_speed)
        edges = (0.0, *p.gear_speeds, p.top_speed)
        g = max(1, self.gear) - 1
        lo, hi = edges[g], edges[g + 1]
        frac = min(max((u - lo) / (hi - lo), 0.0), 1.0)
        return p.idle_rpm + frac * (p.max_rpm - p.idle_rpm)
