"""A simulated remote-controlled drone, so the real-time tutorial runs without hardware.

:class:`DummyRCDrone` is a point in a square world that moves at the velocity last commanded.
Commands and observations travel with a random delay (``communication_delay_min`` to
``communication_delay_max`` seconds each way), and a message older than the last one delivered is
dropped, as on a real radio link. One background thread runs the physics and delivers messages;
``close()`` stops it.

:class:`DroneInterface` is the tutorial's interface over it (observation: drone position and
target; action: velocity; reward: minus the distance to the target; terminated within 1 cm), and
:func:`drone_config` a ready real-time config for it.
"""

from __future__ import annotations

import heapq
import math
import random
import threading
import time
from typing import Any

import numpy as np
from gymnasium import spaces

from tmrl.errors import UserError
from tmrl.realtime.interface import CONFIG_KEYS, DEFAULT_CONFIG_DICT, RealTimeGymInterface

__all__ = ["DroneInterface", "DummyRCDrone", "drone_config"]


class DummyRCDrone:
    """A 2-D drone with velocity control over a delayed, lossy-ordering link.

    Args:
        mass: kept for compatibility with rtgym's signature (the drone is velocity-controlled).
        friction: kept for compatibility with rtgym's signature.
        communication_delay_min: shortest delay of a command or an observation, in seconds.
        communication_delay_max: longest delay, in seconds.
        max_vel: commanded velocities are scaled down to this norm (world units per second).
        world_size: the position is clipped to ``[-world_size, world_size]`` on each axis.
        control_sleep: physics period in seconds (the drone sends its position every period).
        seed: seed of the delay generator (``None``: unpredictable).

    Raises:
        UserError: a negative delay, ``communication_delay_max < communication_delay_min`` or a
            non-positive ``control_sleep``.
    """

    def __init__(
        self,
        mass: float = 1.0,
        friction: float = 1.0,
        communication_delay_min: float = 0.02,
        communication_delay_max: float = 0.05,
        max_vel: float = 2.0,
        world_size: float = 1.0,
        control_sleep: float = 0.01,
        seed: int | None = None,
    ) -> None:
        if communication_delay_min < 0 or communication_delay_max < communication_delay_min:
            raise UserError(
                f"DummyRCDrone delays ({communication_delay_min}, {communication_delay_max}): "
                "use 0 <= communication_delay_min <= communication_delay_max"
            )
        if control_sleep <= 0:
            raise UserError(
                f"DummyRCDrone control_sleep is {control_sleep}: use a positive period in seconds"
            )
        self.mass = mass
        self.friction = friction
        self.communication_delay_min = float(communication_delay_min)
        self.communication_delay_max = float(communication_delay_max)
        self.max_vel = float(max_vel)
        self.world_size = float(world_size)
        self.control_sleep = float(control_sleep)
        self._rng = random.Random(seed)
        self._cond = threading.Condition()
        # (deliver_at, sequence, kind, sent_at, payload); kind is "act" or "obs".
        self._inbox: list[tuple[float, int, str, float, tuple[float, float]]] = []
        self._seq = 0
        now = time.perf_counter()
        self._last_sent = {"act": now, "obs": now}  # messages sent before these times are dropped
        self._vel = (0.0, 0.0)
        self._obs = (0.0, 0.0)
        self._pos = (0.0, 0.0)
        self._stopped = False
        self._thread = threading.Thread(target=self._run, name="tmrl-DummyRCDrone", daemon=True)
        self._thread.start()

    def send_control(self, vel_x: float, vel_y: float) -> None:
        """Command a velocity; it reaches the drone after a random delay (never blocks).

        Args:
            vel_x: velocity along x, in units per second (the norm is clipped to ``max_vel``).
            vel_y: velocity along y, in units per second.
        """
        vel_x, vel_y = float(vel_x), float(vel_y)
        norm = math.hypot(vel_x, vel_y)
        if norm > self.max_vel:
            vel_x, vel_y = vel_x * self.max_vel / norm, vel_y * self.max_vel / norm
        self._post("act", (vel_x, vel_y))

    def get_observation(self) -> tuple[float, float]:
        """The last position received from the drone (it is ``communication_delay`` old)."""
        with self._cond:
            return self._obs

    @property
    def velocity(self) -> tuple[float, float]:
        """The velocity the drone applies now (the last command that reached it)."""
        with self._cond:
            return self._vel

    @property
    def position(self) -> tuple[float, float]:
        """The drone's true position now (for tests; a real drone would not tell)."""
        with self._cond:
            return self._pos

    def close(self) -> None:
        """Stop the drone's thread (idempotent)."""
        with self._cond:
            self._stopped = True
            self._cond.notify()
        while self._thread is not threading.current_thread() and self._thread.is_alive():
            self._thread.join(0.2)  # in slices: on Windows, Ctrl-C comes in between two

    def __enter__(self) -> DummyRCDrone:  # noqa: PYI034
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _post(self, kind: str, payload: tuple[float, float]) -> None:
        with self._cond:
            sent_at = time.perf_counter()
            delay = self._rng.uniform(self.communication_delay_min, self.communication_delay_max)
            self._seq += 1
            heapq.heappush(self._inbox, (sent_at + delay, self._seq, kind, sent_at, payload))
            self._cond.notify()

    def _deliver_due(self, now: float) -> None:
        while self._inbox and self._inbox[0][0] <= now:
            _, _, kind, sent_at, payload = heapq.heappop(self._inbox)
            if sent_at <= self._last_sent[kind]:
                continue  # an older message overtaken by a newer one: dropped
            self._last_sent[kind] = sent_at
            if kind == "act":
                self._vel = payload
            else:
                self._obs = payload

    def _run(self) -> None:
        period, size = self.control_sleep, self.world_size
        next_tick = time.perf_counter()
        with self._cond:
            while not self._stopped:
                now = time.perf_counter()
                self._deliver_due(now)
                if now >= next_tick:
                    # Send the position, then move for one period at the current velocity.
                    self._seq += 1
                    delay = self._rng.uniform(self.communication_delay_min, self.communication_delay_max)
                    heapq.heappush(self._inbox, (now + delay, self._seq, "obs", now, self._pos))
                    x = min(max(self._pos[0] + self._vel[0] * period, -size), size)
                    y = min(max(self._pos[1] + self._vel[1] * period, -size), size)
                    self._pos = (x, y)
                    next_tick += period
                    if next_tick < now:  # fell behind (a loaded machine): do not try to catch up
                        next_tick = now + period
                wake = min(next_tick, self._inbox[0][0]) if self._inbox else next_tick
                self._cond.wait(max(0.0, wake - time.perf_counter()))


class DroneInterface(RealTimeGymInterface):
    """The rtgym tutorial's interface: fly a :class:`DummyRCDrone` to a random target.

    Observation: ``[pos_x, pos_y, target_x, target_y]``, each a float32 array of shape (1,).
    Action: a velocity ``[vel_x, vel_y]`` in ``[-2, 2]``. Reward: minus the distance from the
    observed position to the target; terminated when it is under ``success_distance``.

    Args:
        success_distance: distance to the target that ends the episode.
        speed_factor: the commanded velocity is multiplied by this before it is sent (and the
            drone's ``max_vel`` by default too): with time steps ``k`` times shorter, a factor
            ``k`` keeps the motion per time step the same.
        **drone_kwargs: passed to :class:`DummyRCDrone` (delays, ``control_sleep``, ``seed``...),
            which is built at the first ``reset()`` on the thread that calls it.
    """

    def __init__(
        self, success_distance: float = 0.01, speed_factor: float = 1.0, **drone_kwargs: Any
    ) -> None:
        self.success_distance = float(success_distance)
        self.speed_factor = float(speed_factor)
        drone_kwargs.setdefault("max_vel", 2.0 * self.speed_factor)
        self.drone_kwargs = drone_kwargs
        self.world_size = float(drone_kwargs.get("world_size", 1.0))
        self.rc_drone: DummyRCDrone | None = None
        self.target = np.zeros(2, dtype=np.float32)
        self._rng = np.random.default_rng()

    def get_observation_space(self) -> spaces.Tuple:
        w = self.world_size
        pos = spaces.Box(low=-w, high=w, shape=(1,), dtype=np.float32)
        tar = spaces.Box(low=-0.5, high=0.5, shape=(1,), dtype=np.float32)
        return spaces.Tuple((pos, pos, tar, tar))

    def get_action_space(self) -> spaces.Box:
        return spaces.Box(low=-2.0, high=2.0, shape=(2,), dtype=np.float32)

    def get_default_action(self) -> np.ndarray:
        return np.zeros(2, dtype=np.float32)

    def send_control(self, control: Any) -> None:
        if control is not None and self.rc_drone is not None:
            k = self.speed_factor
            self.rc_drone.send_control(k * float(control[0]), k * float(control[1]))

    def _obs(self) -> list[np.ndarray]:
        assert self.rc_drone is not None
        x, y = self.rc_drone.get_observation()
        return [np.array([v], dtype=np.float32) for v in (x, y, self.target[0], self.target[1])]

    def reset(self, seed: int | None = None, options: dict[str, Any] | None = None) -> tuple[list[Any], dict]:
        if self.rc_drone is None:
            self.rc_drone = DummyRCDrone(**self.drone_kwargs)
        if seed is not None:
            self._rng = np.random.default_rng(seed)
        self.target[:] = self._rng.uniform(-0.5, 0.5, size=2)
        return self._obs(), {}

    def get_obs_rew_terminated_info(self) -> tuple[list[Any], float, bool, dict]:
        obs = self._obs()
        rew = -float(np.hypot(obs[0][0] - self.target[0], obs[1][0] - self.target[1]))
        return obs, rew, rew > -self.success_distance, {}

    def render(self) -> np.ndarray:
        """A 200x200 RGB image: the drone in blue, the target in red (no window is opened)."""
        img = np.full((200, 200, 3), 255, dtype=np.uint8)
        yy, xx = np.mgrid[0:200, 0:200]
        scale = 100.0 / max(self.world_size, 1e-9)
        x, y = self.rc_drone.get_observation() if self.rc_drone is not None else (0.0, 0.0)
        for (cx, cy), radius, color in (((x, y), 6, (0, 0, 255)), (tuple(self.target), 3, (255, 0, 0))):
            mask = (xx - (100 + cx * scale)) ** 2 + (yy - (100 + cy * scale)) ** 2 <= radius**2
            img[mask] = color
        return img

    def close(self) -> None:
        if self.rc_drone is not None:
            self.rc_drone.close()
            self.rc_drone = None


def drone_config(fast: bool = False, **overrides: Any) -> dict[str, Any]:
    """A fresh real-time config for :class:`DroneInterface`.

    Defaults: 20 Hz (``time_step_duration`` and ``start_obs_capture`` 0.05 s), episodes of 100
    steps, an action buffer of 4 (the delays span up to two time steps each way), buffer reset at
    each episode.

    Args:
        fast: scale every duration down by 10 (5 ms time steps, 2 to 5 ms delays, 1 ms physics
            period) and the drone's speed up by 10, so that an episode looks the same in time
            steps, for tests.
        **overrides: config keys to change. When ``time_step_duration`` is given without
            ``start_obs_capture``, the capture follows it (end of the time step).
            ``interface_kwargs`` are merged into the drone's.

    Raises:
        UserError: an override is not a real-time config key.
    """
    unknown = sorted(set(overrides) - CONFIG_KEYS)
    if unknown:
        raise UserError(f"drone_config(): unknown config keys {unknown}; valid keys: {sorted(CONFIG_KEYS)}")
    scale = 0.1 if fast else 1.0
    cfg = dict(DEFAULT_CONFIG_DICT)
    cfg.update(
        interface=DroneInterface,
        interface_args=(),
        interface_kwargs={
            "speed_factor": 1.0 / scale,
            "communication_delay_min": 0.02 * scale,
            "communication_delay_max": 0.05 * scale,
            "control_sleep": 0.01 * scale,
        },
        time_step_duration=0.05 * scale,
        start_obs_capture=0.05 * scale,
        time_step_timeout_factor=1.0,
        ep_max_length=100,
        act_in_obs=True,
        act_buf_len=4,
        reset_act_buf=True,
        benchmark=False,
        benchmark_polyak=0.2,
    )
    kwargs = {**cfg["interface_kwargs"], **dict(overrides.pop("interface_kwargs", {}))}
    if "time_step_duration" in overrides and "start_obs_capture" not in overrides:
        cfg["start_obs_capture"] = overrides["time_step_duration"]
    cfg.update(overrides)
    cfg["interface_kwargs"] = kwargs
    return cfg
