"""One race on a track: the car, the clock, the lap and the trajectory reward.

:class:`Race` is the simulator without observations. The interfaces add what the policy sees; the
tests and the random-policy check drive it directly, which is cheap. :func:`follow_centre_line`
is a hand-written driver (pure pursuit on the centre line with a speed limit from the bends
ahead) that completes laps: it proves a track is drivable and gives a baseline lap time.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any

import numpy as np

from tmrl.driving.reward import TrajectoryReward
from tmrl.sim.car import Car, CarParams
from tmrl.sim.track import Track

__all__ = ["PHYSICS_DT", "Race", "follow_centre_line"]

PHYSICS_DT = 0.0125
"""Physics substep in seconds; every call to :meth:`Race.advance` is split into such steps."""


class Race:
    """The car on a track from the start line to the finish, with the shared reward.

    Args:
        track: the track.
        reward_config: a ``REWARD_CONFIG`` dict (keys of
            :data:`tmrl.driving.reward.DEFAULT_REWARD_CONFIG`; missing keys take those defaults).
        car_params: physical constants of the car.
        physics_dt: physics substep in seconds.

    Attributes:
        time: simulated seconds since the start.
        lap_time: time at which the finish line was crossed, or None.
        laps: signed number of times the start/finish line was crossed forward.
    """

    def __init__(self, track: Track, reward_config: Mapping[str, Any] | None = None,
                 car_params: CarParams | None = None, physics_dt: float = PHYSICS_DT) -> None:
        self.track = track
        self.car = Car(track, car_params)
        self.reward = TrajectoryReward.from_config(track.reward_trajectory(), reward_config, spacing=track.spacing)
        self.physics_dt = float(physics_dt)
        self.time = 0.0
        self.laps = 0
        self.lap_time: float | None = None
        self._carry = 0.0
        self._new_hits = 0

    def reset(self) -> None:
        """Car at rest on the start line, clock and reward at zero."""
        self.car.reset()
        self.reward.reset()
        self.time = 0.0
        self.laps = 0
        self.lap_time = None
        self._carry = 0.0
        self._new_hits = 0

    @property
    def finished(self) -> bool:
        """Whether the finish line has been crossed (the lap is complete)."""
        return self.lap_time is not None

    def advance(self, action: np.ndarray | tuple[float, float, float], duration: float) -> None:
        """Drive for ``duration`` seconds with ``action`` = ``[gas, brake, steer]``.

        Time that does not fill a whole physics substep is carried over to the next call, so
        that a real-time caller with irregular intervals keeps the simulated clock exact. Nothing
        moves once the lap is complete.
        """
        gas, brake, steer = (float(a) for a in action)
        self._carry += duration
        n = int(self._carry / self.physics_dt + 1e-9)
        self._carry -= n * self.physics_dt
        half = self.track.n_points // 2
        for _ in range(n):
            if self.finished:
                break
            before = self.car.state.index
            if self.car.step(gas, brake, steer, self.physics_dt):
                self._new_hits += 1
            self.time += self.physics_dt
            after = self.car.state.index
            if before - after > half:  # wrapped forward past the start/finish line
                self.laps += 1
                if self.laps >= 1 and self.lap_time is None:
                    self.lap_time = self.time
            elif after - before > half:  # backward over the line
                self.laps -= 1

    def score(self) -> tuple[float, bool, dict[str, Any]]:
        """The reward for the current position: ``(reward, terminated, info)``.

        The reward is the trajectory reward, plus ``END_OF_TRACK`` when the lap is complete, plus
        ``CONSTANT_PENALTY``; ``terminated`` is set when the lap is complete or the reward gives
        up on the car. ``info`` holds ``lap_completed`` (bool), ``lap_time`` (seconds, only when
        completed) and ``wall_hits`` (wall contacts since the last call).
        """
        rew, terminated = self.reward.compute_reward(self.car.state.position)
        info: dict[str, Any] = {"lap_completed": self.finished, "wall_hits": self._new_hits}
        self._new_hits = 0
        if self.finished:
            terminated = True
            rew += self.reward.end_of_track
            info["lap_time"] = float(self.lap_time)  # type: ignore[arg-type]
        rew += self.reward.constant_penalty
        return float(rew), bool(terminated), info

    @property
    def progress(self) -> float:
        """Progress along the reward trajectory in [0, 1]."""
        return self.reward.progress


def follow_centre_line(race: Race, look_ahead: float = 8.0, caution: float = 0.75) -> np.ndarray:
    """A hand-written driver: ``[gas, brake, steer]`` towards a point on the centre line ahead,
    at a speed the bends ahead allow.

    Args:
        race: the race (the driver reads the car's state and the track).
        look_ahead: base distance to the aimed point in metres (grows with speed).
        caution: share of the tyres' grip the driver is willing to use in bends.

    Returns:
        The action as a float32 array.
    """
    track, state, params = race.track, race.car.state, race.car.params
    n = track.n_points
    u = max(state.forward_speed, 0.0)
    ahead = int((look_ahead + 0.4 * u) / track.spacing)
    target = track.centre[(state.index + ahead) % n]
    dx, dy = target[0] - state.x, target[1] - state.y
    angle = math.atan2(dy, dx) - state.heading
    angle = (angle + math.pi) % (2 * math.pi) - math.pi
    steer = float(np.clip(-2.5 * angle, -1.0, 1.0))
    # Fastest speed that the bends within braking distance allow.
    horizon = int((u * u / (2 * 0.6 * params.brake) + 15.0) / track.spacing)
    idx = (state.index + np.arange(0, max(horizon, 1), 5)) % n
    kappa = float(np.max(np.abs(track.curvature[idx])))
    v_max = math.sqrt(caution * params.grip / max(kappa, 1e-4))
    gas = 1.0 if u < v_max else 0.0
    brake = 1.0 if u > v_max + 1.5 else 0.0
    return np.array([gas, brake, steer], dtype=np.float32)
