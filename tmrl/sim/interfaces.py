"""The simulator behind TrackMania's observation and action spaces.

Three real-time interfaces (:class:`tmrl.realtime.RealTimeGymInterface`), one per TrackMania
interface, with the same observation Tuples:

| interface                   | observation (before the action buffer)               | TrackMania twin     |
|-----------------------------|------------------------------------------------------|---------------------|
| SimLidarInterface           | speed (1,), lidar history (hist, 19)                 | TM20LIDAR           |
| SimLidarProgressInterface   | speed (1,), progress (1,), lidar history (hist, 19)  | TM20LIDARPROGRESS   |
| SimFullInterface            | speed, gear, rpm (1,) each, images (hist, h, w) u8   | TM20FULL            |

Speed is in km/h, lidar values in pixels along each beam of a 958 x 488 view (the TrackMania
window's default size, so the numbers have the same range), progress in [0, 1], images 64 x 64
grayscale by default. Actions are ``[gas, brake, steer]`` in [-1, 1]. The reward is the shared
trajectory reward (:mod:`tmrl.driving.reward`) on the track's centre line; an episode terminates
when the finish line is crossed (``info["lap_completed"]``, ``info["lap_time"]``) or when the
reward gives up on the car.

Run through :class:`tmrl.realtime.RealTimeEnv`, the physics follows the wall clock: whatever time
passes between two calls is simulated with the control in force. The plain Gymnasium
environments (:class:`SimLidarEnv`, :class:`SimLidarProgressEnv`, :class:`SimFullEnv`) instead
advance exactly ``time_step_duration`` of simulated time per step, as fast as the CPU allows, and
append the same action buffer as the real-time environment.
"""

from __future__ import annotations

import time
from collections import deque
from pathlib import Path
from collections.abc import Callable, Mapping
from typing import Any

import gymnasium
import numpy as np
from gymnasium import spaces

from tmrl.driving.lidar import DEFAULT_BLACK_THRESHOLD, LIDAR_BEAMS, Lidar
from tmrl.errors import UserError
from tmrl.realtime import RealTimeGymInterface
from tmrl.sim.car import CarParams
from tmrl.sim.race import Race
from tmrl.sim.render import Camera, track_map
from tmrl.sim.track import Track, make_track

__all__ = [
    "DEFAULT_SIM_RTGYM_CONFIG",
    "SIM_INTERFACES",
    "SimEnv",
    "SimFullEnv",
    "SimFullInterface",
    "SimLidarEnv",
    "SimLidarInterface",
    "SimLidarProgressEnv",
    "SimLidarProgressInterface",
    "fast_env",
    "interface_class",
    "interface_kwargs",
    "pipeline_parts",
    "realtime_config",
]

DEFAULT_SIM_RTGYM_CONFIG: dict[str, Any] = {
    "time_step_duration": 0.05,
    "start_obs_capture": 0.04,
    "time_step_timeout_factor": 1.0,
    "act_buf_len": 2,
    "benchmark": False,
    "wait_on_done": True,
    "ep_max_length": 1000,
}
"""rtgym settings the simulator configs ship with (TrackMania's, 20 steps per second)."""

_DEFAULT_ACTION = np.zeros(3, dtype=np.float32)


class ReplayRecorder:
    """Records the car's path during an episode and saves it when a lap is completed (the
    simulator's ``save_replays``).

    Args:
        track: the track driven.
        folder: ``True`` for ``replays/`` in the data folder (resolved at the first save), or a
            folder path.
    """

    def __init__(self, track: Track, folder: bool | str) -> None:
        self.track = track
        self.folder = None if folder is True else Path(folder)
        self.path: list[tuple[float, float]] = []
        self.saved: list[Path] = []

    def start(self, race: Race) -> None:
        """A new episode: forget the path, start it at the car's position."""
        self.path = [tuple(race.car.state.position)]

    def observe(self, race: Race, info: Mapping[str, Any]) -> Path | None:
        """Record the car's position; when ``info`` says the lap was just completed, save the
        replay and return the JSON file's path."""
        self.path.append(tuple(race.car.state.position))
        if not info.get("lap_completed") or "lap_time" not in info or not self.path:
            return None
        path, self.path = self.path, []  # a finished race stays finished: save it once
        return self._save(path, float(info["lap_time"]))

    def _save(self, path: list[tuple[float, float]], lap_time: float) -> Path:
        import datetime
        import json

        from tmrl.sim.charts import lap_image
        from tmrl.sim.render import write_png
        from tmrl.util import atomic_write_text

        folder = self.folder
        if folder is None:
            from tmrl.config.loader import data_folder

            folder = data_folder() / "replays"
        folder.mkdir(parents=True, exist_ok=True)
        stamp = datetime.datetime.now().strftime("%Y%m%d-%H%M%S-%f")
        stem = f"sim-{self.track.name}-{stamp}-{lap_time:.2f}s"
        record = {
            "format": "tmrl-sim-replay",
            "version": 1,
            "track": self.track.name,
            "lap_time": lap_time,
            "xy": [[round(float(x), 4), round(float(y), 4)] for x, y in path],
        }
        json_path = folder / f"{stem}.json"
        atomic_write_text(json_path, json.dumps(record))
        write_png(folder / f"{stem}.png", lap_image(self.track, np.asarray(path), f"REPLAY ON TRACK {self.track.name}",
                                                   [f"LAP TIME {lap_time:.2f} S (SIMULATED)"]))
        self.saved.append(json_path)
        return json_path


class _SimInterface(RealTimeGymInterface):
    """What the three interfaces share: the race, the clock and the observation history.

    Args:
        track: a track name, a seed, or a :class:`Track` (default: the default track).
        img_hist_len: length of the lidar or image history in each observation.
        reward_config: ``REWARD_CONFIG`` dict (see :data:`tmrl.driving.reward.DEFAULT_REWARD_CONFIG`).
        car_params: physical constants of the car.
        clock: a function returning seconds (``time.perf_counter`` by default); tests pass a fake.
        save_replays: save a replay of every completed lap (TrackMania's ``save_replays``): a
            JSON file with the track, the lap time and the car's path, and a top-down PNG of the
            lap, in ``replays/`` of the data folder (``True``) or in the folder given as a string.
            Files are named after the time and the lap time, e.g.
            ``sim-classic-20261123-141503-31.85s.json``.
    """

    def __init__(self, track: str | int | Track | None = None, img_hist_len: int = 4,
                 reward_config: Mapping[str, Any] | None = None, car_params: CarParams | None = None,
                 clock: Callable[[], float] | None = None, save_replays: bool | str = False) -> None:
        if int(img_hist_len) < 1:
            raise UserError(f"ENV.IMG_HIST_LEN must be >= 1, got {img_hist_len}")
        self.track = track if isinstance(track, Track) else make_track(track)
        self.race = Race(self.track, reward_config=reward_config, car_params=car_params)
        self.img_hist_len = int(img_hist_len)
        self.clock = clock or time.perf_counter
        self.history: deque[np.ndarray] = deque(maxlen=self.img_hist_len)
        self._control = _DEFAULT_ACTION.copy()
        self._last_time: float | None = None
        self._paused = True
        self.replays = ReplayRecorder(self.track, save_replays) if save_replays else None

    # -- the clock --------------------------------------------------------------------------

    def _catch_up(self) -> None:
        """Simulate the time elapsed since the last call with the control in force."""
        now = self.clock()
        if not self._paused and self._last_time is not None:
            self.race.advance(self._control, max(0.0, now - self._last_time))
        self._last_time = now

    # -- RealTimeGymInterface ------------------------------------------------------------------

    def send_control(self, control: Any) -> None:
        """Apply ``[gas, brake, steer]`` from now on (``None`` keeps the current control)."""
        self._catch_up()
        if control is not None:
            self._control = np.clip(np.asarray(control, dtype=np.float32).reshape(3), -1.0, 1.0)

    def reset(self, seed: int | None = None, options: dict[str, Any] | None = None) -> tuple[list[Any], dict]:
        """Car at rest on the start line; the history is filled with the first frame."""
        self.race.reset()
        if self.replays is not None:
            self.replays.start(self.race)
        self._control = _DEFAULT_ACTION.copy()
        self._paused = False
        self._last_time = self.clock()
        frame = self._frame()
        self.history.clear()
        for _ in range(self.img_hist_len):
            self.history.append(frame)
        return self._obs(), {}

    def wait(self) -> None:
        """Freeze the car until the next reset."""
        self._catch_up()
        self._paused = True

    def get_obs_rew_terminated_info(self) -> tuple[list[Any], float, bool, dict]:
        """Simulate up to now, then observe and score."""
        self._catch_up()
        return self._observe_and_score()

    def get_action_space(self) -> spaces.Box:
        """``[gas, brake, steer]`` in [-1, 1]."""
        return spaces.Box(low=-1.0, high=1.0, shape=(3,), dtype=np.float32)

    def get_default_action(self) -> np.ndarray:
        """No gas, no brake, wheels straight."""
        return _DEFAULT_ACTION.copy()

    # -- fast mode -------------------------------------------------------------------------------

    def step_for(self, control: Any, duration: float) -> tuple[list[Any], float, bool, dict]:
        """Apply ``control`` for exactly ``duration`` simulated seconds, then observe and score
        (the fast environments' step; ignores the wall clock)."""
        self._control = np.clip(np.asarray(control, dtype=np.float32).reshape(3), -1.0, 1.0)
        self.race.advance(self._control, duration)
        return self._observe_and_score()

    # -- observations ----------------------------------------------------------------------------

    def _observe_and_score(self) -> tuple[list[Any], float, bool, dict]:
        rew, terminated, info = self.race.score()
        self.history.append(self._frame())
        if self.replays is not None:
            saved = self.replays.observe(self.race, info)
            if saved is not None:
                info["replay"] = str(saved)
        return self._obs(), rew, terminated, info

    def _speed(self) -> np.ndarray:
        return np.array([self.race.car.state.speed * 3.6], dtype=np.float32)

    def _frame(self) -> np.ndarray:  # pragma: no cover - abstract
        raise NotImplementedError

    def _obs(self) -> list[Any]:  # pragma: no cover - abstract
        raise NotImplementedError


class SimLidarInterface(_SimInterface):
    """Speed and a history of 19-beam lidars, like ``TM20LIDAR``.

    Args:
        track: a track name, a seed, or a :class:`~tmrl.sim.track.Track` (default: the default
            track, see :func:`~tmrl.sim.track.make_track`).
        img_hist_len: length of the lidar history in each observation.
        **kwargs: passed to the shared base: ``reward_config`` (a ``REWARD_CONFIG`` dict, see
            :data:`tmrl.driving.reward.DEFAULT_REWARD_CONFIG`), ``car_params`` (a
            :class:`~tmrl.sim.car.CarParams`), ``clock`` (a function returning seconds,
            ``time.perf_counter`` by default; tests pass a fake one) and ``save_replays`` (save a
            JSON replay and a top-down PNG of every completed lap, in ``replays/`` of the data
            folder for ``True`` or in the folder given as a string).
        lidar_size: ``(width, height)`` of the view the lidar reads, in pixels (TrackMania's
            default window, 958 x 488, so that values have the same range).
        lidar_scale: metres per pixel of that view.
        black_threshold: the lidar's dark-pixel threshold, an RGB triple
            (``LIDAR_BLACK_THRESHOLD``).

    Raises:
        UserError: ``img_hist_len`` < 1, or an unknown track.
    """

    def __init__(self, track: str | int | Track | None = None, img_hist_len: int = 4,
                 lidar_size: tuple[int, int] = (958, 488), lidar_scale: float = 0.12,
                 black_threshold: Any = DEFAULT_BLACK_THRESHOLD, **kwargs: Any) -> None:
        super().__init__(track=track, img_hist_len=img_hist_len, **kwargs)
        width, height = lidar_size
        self.lidar = Lidar(height, width, black_threshold)
        # Only the pixels the beams read are rendered: the same values as rendering the whole
        # view and measuring it, for a fraction of the cost.
        self.lidar_camera = Camera(height, width, lidar_scale, anchor=self.lidar.road_point,
                                   rows=self.lidar.rows, cols=self.lidar.cols)
        self.map = track_map(self.track)

    def lidar_view(self) -> np.ndarray:
        """The whole grayscale view the lidar reads (for ``--check-environment`` and tests)."""
        cam = Camera(self.lidar.height, self.lidar.width, self.lidar_camera.scale, anchor=self.lidar.road_point)
        s = self.race.car.state
        return cam.render(self.map, s.x, s.y, s.heading)

    def _frame(self) -> np.ndarray:
        s = self.race.car.state
        values = self.lidar_camera.render(self.map, s.x, s.y, s.heading)
        return self.lidar.distances_from_dark(self.lidar.dark(values))

    def _obs(self) -> list[Any]:
        return [self._speed(), np.array(self.history, dtype=np.float32)]

    def get_observation_space(self) -> spaces.Tuple:
        """``(speed (1,), lidars (img_hist_len, 19))``."""
        return spaces.Tuple((
            spaces.Box(low=0.0, high=1000.0, shape=(1,), dtype=np.float32),
            spaces.Box(low=0.0, high=np.inf, shape=(self.img_hist_len, LIDAR_BEAMS), dtype=np.float32),
        ))


class SimLidarProgressInterface(SimLidarInterface):
    """Speed, progress along the track in [0, 1] and lidars, like ``TM20LIDARPROGRESS``. Takes
    the arguments of :class:`SimLidarInterface`."""

    def _obs(self) -> list[Any]:
        progress = np.array([self.race.progress], dtype=np.float32)
        return [self._speed(), progress, np.array(self.history, dtype=np.float32)]

    def get_observation_space(self) -> spaces.Tuple:
        """``(speed (1,), progress (1,), lidars (img_hist_len, 19))``."""
        return spaces.Tuple((
            spaces.Box(low=0.0, high=1000.0, shape=(1,), dtype=np.float32),
            spaces.Box(low=0.0, high=1.0, shape=(1,), dtype=np.float32),
            spaces.Box(low=0.0, high=np.inf, shape=(self.img_hist_len, LIDAR_BEAMS), dtype=np.float32),
        ))


class SimFullInterface(_SimInterface):
    """Speed, gear, rpm and a history of grayscale images from behind the car, like ``TM20FULL``.

    Args:
        track: a track name, a seed, or a :class:`~tmrl.sim.track.Track` (default: the default
            track, see :func:`~tmrl.sim.track.make_track`).
        img_hist_len: length of the image history in each observation.
        **kwargs: passed to the shared base: ``reward_config`` (a ``REWARD_CONFIG`` dict, see
            :data:`tmrl.driving.reward.DEFAULT_REWARD_CONFIG`), ``car_params`` (a
            :class:`~tmrl.sim.car.CarParams`), ``clock`` (a function returning seconds,
            ``time.perf_counter`` by default; tests pass a fake one) and ``save_replays`` (save a
            JSON replay and a top-down PNG of every completed lap, in ``replays/`` of the data
            folder for ``True`` or in the folder given as a string).
        img_size: ``(width, height)`` of the images (``IMG_WIDTH``, ``IMG_HEIGHT``).
        view_width: metres of track across the image.

    Raises:
        UserError: ``img_hist_len`` < 1, or an unknown track.
    """

    def __init__(self, track: str | int | Track | None = None, img_hist_len: int = 4,
                 img_size: tuple[int, int] = (64, 64), view_width: float = 32.0, **kwargs: Any) -> None:
        super().__init__(track=track, img_hist_len=img_hist_len, **kwargs)
        width, height = int(img_size[0]), int(img_size[1])
        self.camera = Camera(height, width, view_width / width, draw_car=True)
        self.map = track_map(self.track)

    def _frame(self) -> np.ndarray:
        s = self.race.car.state
        return self.camera.render(self.map, s.x, s.y, s.heading)

    def _obs(self) -> list[Any]:
        car = self.race.car
        return [
            self._speed(),
            np.array([car.gear], dtype=np.float32),
            np.array([car.rpm], dtype=np.float32),
            np.array(self.history, dtype=np.uint8),
        ]

    def get_observation_space(self) -> spaces.Tuple:
        """``(speed, gear, rpm, images (img_hist_len, height, width) uint8)``."""
        return spaces.Tuple((
            spaces.Box(low=0.0, high=1000.0, shape=(1,), dtype=np.float32),
            spaces.Box(low=0.0, high=6.0, shape=(1,), dtype=np.float32),
            spaces.Box(low=0.0, high=np.inf, shape=(1,), dtype=np.float32),
            spaces.Box(low=0, high=255, shape=(self.img_hist_len, self.camera.height, self.camera.width),
                       dtype=np.uint8),
        ))


SIM_INTERFACES: dict[str, type[_SimInterface]] = {
    "SIMLIDAR": SimLidarInterface,
    "SIMLIDARPROGRESS": SimLidarProgressInterface,
    "SIMFULL": SimFullInterface,
}
"""``ENV.RTGYM_INTERFACE`` values of the simulator and their interfaces."""


class SimEnv(gymnasium.Env):
    """A simulator interface as a plain Gymnasium environment that steps as fast as it can.

    Observations are the interface's elements followed by the last ``act_buf_len`` actions
    (oldest first, the newest being the action of this step), exactly as the real-time
    environment builds them; the buffer is filled with the default action at reset. Episodes are
    truncated after ``ep_max_length`` steps.

    Args:
        interface: the interface class, or its ``RTGYM_INTERFACE`` name (``"SIMLIDAR"``...).
        time_step_duration: simulated seconds per step.
        ep_max_length: steps before truncation.
        act_buf_len: actions appended to each observation.
        act_in_obs: append the action buffer at all.
        **interface_kwargs: passed to the interface (``track``, ``img_hist_len``...).

    Raises:
        UserError: an unknown interface name.
    """

    metadata = {"render_modes": []}

    def __init__(self, interface: str | type[_SimInterface] = "SIMLIDAR", time_step_duration: float = 0.05,
                 ep_max_length: int = 1000, act_buf_len: int = 2, act_in_obs: bool = True,
                 **interface_kwargs: Any) -> None:
        if isinstance(interface, str):
            if interface.upper() not in SIM_INTERFACES:
                raise UserError(f"unknown simulator interface {interface!r}: use one of {sorted(SIM_INTERFACES)}")
            interface = SIM_INTERFACES[interface.upper()]
        self.interface = interface(**interface_kwargs)
        self.time_step_duration = float(time_step_duration)
        self.ep_max_length = int(ep_max_length)
        self.act_buf_len = int(act_buf_len) if act_in_obs else 0
        self.action_space = self.interface.get_action_space()
        elements = list(self.interface.get_observation_space().spaces)
        elements += [self.action_space] * self.act_buf_len
        self.observation_space = spaces.Tuple(elements)
        self.act_buf: deque[np.ndarray] = deque(maxlen=max(1, self.act_buf_len))
        self.steps = 0

    @property
    def race(self) -> Race:
        """The underlying race (car, track, reward)."""
        return self.interface.race

    def _with_actions(self, obs: list[Any]) -> tuple:
        return tuple(obs) + tuple(a.copy() for a in self.act_buf) if self.act_buf_len else tuple(obs)

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None) -> tuple[tuple, dict]:
        """New episode: the car at rest on the start line, the action buffer filled with the
        default action.

        Args:
            seed: accepted for Gymnasium's API (the simulator is deterministic).
            options: passed to the interface's ``reset`` (which ignores it).

        Returns:
            ``(observation, info)``.
        """
        super().reset(seed=seed)
        obs, info = self.interface.reset(seed=seed, options=options)
        default = self.interface.get_default_action()
        self.act_buf.clear()
        for _ in range(self.act_buf_len):
            self.act_buf.append(default.copy())
        self.steps = 0
        return self._with_actions(obs), info

    def wait(self) -> None:
        """rtgym's pause between episodes: nothing to do here, the simulated clock only moves
        when the environment steps (kept so that code written for real-time environments runs)."""

    def step(self, action: Any) -> tuple[tuple, float, bool, bool, dict]:
        """Apply an action for one time step of simulated time.

        Args:
            action: ``[gas, brake, steer]``, clipped to [-1, 1].

        Returns:
            Gymnasium's ``(observation, reward, terminated, truncated, info)``.
        """
        act = np.clip(np.asarray(action, dtype=np.float32).reshape(3), -1.0, 1.0)
        obs, rew, terminated, info = self.interface.step_for(act, self.time_step_duration)
        if self.act_buf_len:
            self.act_buf.append(act)
        self.steps += 1
        truncated = (not terminated) and self.steps >= self.ep_max_length
        return self._with_actions(obs), float(rew), bool(terminated), bool(truncated), info


class SimLidarEnv(SimEnv):
    """Fast :class:`SimLidarInterface` environment (Gymnasium id ``tmrl/SimLidar-v0``).

    Args:
        **kwargs: the arguments of :class:`SimEnv` other than ``interface``.
    """

    def __init__(self, **kwargs: Any) -> None:
        super().__init__(SimLidarInterface, **kwargs)


class SimLidarProgressEnv(SimEnv):
    """Fast :class:`SimLidarProgressInterface` environment (``tmrl/SimLidarProgress-v0``).

    Args:
        **kwargs: the arguments of :class:`SimEnv` other than ``interface``.
    """

    def __init__(self, **kwargs: Any) -> None:
        super().__init__(SimLidarProgressInterface, **kwargs)


class SimFullEnv(SimEnv):
    """Fast :class:`SimFullInterface` environment (``tmrl/SimFull-v0``).

    Args:
        **kwargs: the arguments of :class:`SimEnv` other than ``interface``.
    """

    def __init__(self, **kwargs: Any) -> None:
        super().__init__(SimFullInterface, **kwargs)


# ---------------------------------------------------------------------------------------------
# building from a config


def interface_class(name: str) -> type[_SimInterface]:
    """The simulator interface for an ``ENV.RTGYM_INTERFACE`` value.

    Args:
        name: ``"SIMLIDAR"``, ``"SIMLIDARPROGRESS"`` or ``"SIMFULL"`` (any case).

    Raises:
        UserError: not a simulator interface name.
    """
    try:
        return SIM_INTERFACES[name.upper()]
    except KeyError:
        raise UserError(
            f"ENV.RTGYM_INTERFACE {name!r} is not a simulator interface: use one of {', '.join(SIM_INTERFACES)}"
        ) from None


def interface_kwargs(cfg: Mapping[str, Any]) -> dict[str, Any]:
    """Keyword arguments of the interface selected by a config: ``IMG_HIST_LEN``,
    ``REWARD_CONFIG``, ``IMG_WIDTH``/``IMG_HEIGHT`` (full), then ``RTGYM_CONFIG.interface_kwargs``
    on top (``track``, ``lidar_size``, ``lidar_scale``, ``view_width``...).

    Args:
        cfg: a validated tmrl config whose ``ENV.RTGYM_INTERFACE`` is a simulator's.

    Raises:
        UserError: not a simulator interface, or a key of ``interface_kwargs`` the interface
            does not take.
    """
    env = cfg["ENV"]
    name = str(env["RTGYM_INTERFACE"]).upper()
    interface_class(name)
    kwargs: dict[str, Any] = {
        "img_hist_len": int(env.get("IMG_HIST_LEN", 4)),
        "reward_config": dict(env.get("REWARD_CONFIG", {})),
    }
    if name == "SIMFULL":
        kwargs["img_size"] = (int(env.get("IMG_WIDTH", 64)), int(env.get("IMG_HEIGHT", 64)))
    extra = dict(env.get("RTGYM_CONFIG", {}).get("interface_kwargs") or {})
    allowed = _SIM_KWARGS | (_FULL_KWARGS if name == "SIMFULL" else _LIDAR_KWARGS)
    unknown = sorted(set(extra) - allowed)
    if unknown:
        raise UserError(
            f"ENV.RTGYM_CONFIG.interface_kwargs has {unknown}, unknown to {name}: the simulator takes "
            f"{sorted(allowed)}"
        )
    if "lidar_size" in extra:
        extra["lidar_size"] = tuple(extra["lidar_size"])
    if "img_size" in extra:
        extra["img_size"] = tuple(extra["img_size"])
    kwargs.update(extra)
    return kwargs


_SIM_KWARGS = frozenset({"track", "img_hist_len", "reward_config", "save_replays"})
_LIDAR_KWARGS = frozenset({"lidar_size", "lidar_scale", "black_threshold"})
_FULL_KWARGS = frozenset({"img_size", "view_width"})


def realtime_config(cfg: Mapping[str, Any], **extra_kwargs: Any) -> dict[str, Any]:
    """The :mod:`tmrl.realtime` configuration of a simulator run: the defaults,
    ``ENV.RTGYM_CONFIG`` on top, and the interface with :func:`interface_kwargs`.

    Args:
        cfg: a validated tmrl config whose ``ENV.RTGYM_INTERFACE`` is a simulator's.
        **extra_kwargs: more interface arguments, over the config's (e.g. ``clock``).

    Returns:
        A dict for ``gymnasium.make("real-time-gym-ts-v1", config=...)``.
    """
    from tmrl.realtime import DEFAULT_CONFIG_DICT

    env = cfg["ENV"]
    rt = dict(DEFAULT_CONFIG_DICT)
    overrides = dict(env.get("RTGYM_CONFIG", {}))
    overrides.pop("interface_kwargs", None)
    overrides.pop("interface_args", None)
    rt.update(overrides)
    rt["interface"] = interface_class(str(env["RTGYM_INTERFACE"]))
    rt["interface_args"] = ()
    rt["interface_kwargs"] = {**interface_kwargs(cfg), **extra_kwargs}
    return rt


def fast_env(cfg: Mapping[str, Any], **extra_kwargs: Any) -> SimEnv:
    """The plain Gymnasium environment of a simulator run (fast mode): same observations and
    action buffer as :func:`realtime_config`'s environment, ``time_step_duration`` of simulated
    time per step, ``ep_max_length`` steps per episode at most.

    Args:
        cfg: a validated tmrl config whose ``ENV.RTGYM_INTERFACE`` is a simulator's.
        **extra_kwargs: more interface arguments, over the config's (e.g. ``track``).
    """
    env = cfg["ENV"]
    rt = dict(DEFAULT_SIM_RTGYM_CONFIG)
    rt.update(env.get("RTGYM_CONFIG", {}))
    max_len = rt.get("ep_max_length") or 10**9
    return SimEnv(
        interface_class(str(env["RTGYM_INTERFACE"])),
        time_step_duration=float(rt["time_step_duration"]),
        ep_max_length=int(min(max_len, 10**9)),
        act_buf_len=int(rt["act_buf_len"]),
        act_in_obs=bool(rt.get("act_in_obs", True)),
        **{**interface_kwargs(cfg), **extra_kwargs},
    )


def pipeline_parts(name: str) -> dict[str, Any]:
    """What a worker and a trainer need besides the environment, for an ``RTGYM_INTERFACE``
    value of the simulator or of TrackMania (the observations are the same):
    ``obs_preprocessor``, ``sample_compressor``, ``memory_cls`` (call it with ``hist_len``,
    ``act_buf_len`` and the memory arguments) and ``model_cls`` (actor-critic class taking ``n``
    critics: :class:`~tmrl.driving.models.LidarActorCritic` for lidar,
    :class:`~tmrl.driving.models.CNNActorCritic` for images) and ``actor_cls`` (the worker's
    policy class, the same as ``model_cls(...).actor``).

    Args:
        name: a ``SIM*`` or ``TM20*`` value of ``ENV.RTGYM_INTERFACE`` (any case).

    Raises:
        UserError: any other value.
    """
    from tmrl.driving import compressors, memories, preprocessors
    from tmrl.driving.models import CNNActorCritic, LidarActor, LidarActorCritic, SquashedGaussianCNNActor

    key = name.upper()
    if key in ("SIMLIDAR", "TM20LIDAR"):
        return dict(obs_preprocessor=preprocessors.preprocess_lidar_obs,
                    sample_compressor=compressors.compress_lidar_sample,
                    memory_cls=memories.LidarMemory, model_cls=LidarActorCritic, actor_cls=LidarActor)
    if key in ("SIMLIDARPROGRESS", "TM20LIDARPROGRESS"):
        return dict(obs_preprocessor=preprocessors.preprocess_lidar_progress_obs,
                    sample_compressor=compressors.compress_lidar_progress_sample,
                    memory_cls=memories.LidarProgressMemory, model_cls=LidarActorCritic,
                    actor_cls=LidarActor)
    if key in ("SIMFULL", "TM20FULL"):
        return dict(obs_preprocessor=preprocessors.preprocess_full_obs,
                    sample_compressor=compressors.compress_full_sample,
                    memory_cls=memories.ImageMemory, model_cls=CNNActorCritic,
                    actor_cls=SquashedGaussianCNNActor)
    raise UserError(f"no driving pipeline for ENV.RTGYM_INTERFACE {name!r}: use a SIM* or TM20* interface")
