"""Real-time interfaces of TrackMania 2020: ``TM20FULL``, ``TM20LIDAR``, ``TM20LIDARPROGRESS``.

Observation and action spaces are the original tmrl's:

- **TM20FULL** (:class:`TM20FullInterface`): ``(speed (1,), gear (1,), rpm (1,), images)`` with
  ``images`` the last ``img_hist_len`` captures resized to ``resize_to`` (``(hist, h, w)``
  grayscale or ``(hist, h, w, 3)`` RGB, uint8).
- **TM20LIDAR** (:class:`TM20LidarInterface`): ``(speed (1,), lidars (hist, 19))``.
- **TM20LIDARPROGRESS** (:class:`TM20LidarProgressInterface`): ``(speed, progress (1,) in
  [0, 1], lidars)``.

Actions are ``[gas, brake, steer]`` in ``[-1, 1]``. The reward is the shared trajectory reward
(:class:`tmrl.driving.reward.TrajectoryReward`) on the recorded trajectory, plus ``END_OF_TRACK``
when the plugin reports the finish and ``CONSTANT_PENALTY`` at every step.

``reset`` applies the default action, respawns, waits ``SLEEP_TIME_AT_RESET`` for the countdown and
captures; ``wait`` applies the default action, asks the TMRL_SaveGhost plugin for a replay when
``save_replays`` is on and the race was finished (:func:`tmrl.tm.openplanet.request_replay`, as the
original does), respawns and closes the finish pop-up. The game is first touched at the first ``reset``: building the environment (to read
its spaces) needs no game.

Every game-facing part can be injected (``client``, ``capture``, ``control``, ``trajectory``),
which is how the tests run the whole environment against a fake plugin, an Xvfb window and a
recording gamepad. :func:`realtime_config` builds the ``tmrl.realtime`` configuration from a
tmrl config, as ``ENV.RTGYM_INTERFACE`` selects it.
"""

from __future__ import annotations

import logging
import time
from collections import deque
from typing import Any, Callable, Mapping

import numpy as np
from gymnasium import spaces

from tmrl.errors import UserError
from tmrl.realtime.interface import DEFAULT_CONFIG_DICT, RealTimeGymInterface

__all__ = [
    "INTERFACES",
    "TM20FullInterface",
    "TM20LidarInterface",
    "TM20LidarProgressInterface",
    "interface_class",
    "realtime_config",
]

logger = logging.getLogger(__name__)


def _env_config() -> Mapping[str, Any]:
    from tmrl.config.loader import load_config

    return load_config()


class TM20FullInterface(RealTimeGymInterface):
    """TrackMania 2020 seen through screenshots (the original ``TM2020Interface``).

    Args:
        img_hist_len: number of images in each observation (``ENV.IMG_HIST_LEN``).
        gamepad: drive with the virtual gamepad (analog) instead of the keyboard (``VIRTUAL_GAMEPAD``).
        save_replays: after each episode that crossed the finish line, ask the TMRL_SaveGhost
            plugin to save its replay (keyboard or gamepad).
        grayscale: grayscale images instead of RGB (``ENV.IMG_GRAYSCALE``).
        resize_to: ``(width, height)`` of the images (``ENV.IMG_WIDTH``, ``ENV.IMG_HEIGHT``).
        window_size: ``(width, height)`` the game window is resized to; None: ``ENV.WINDOW_WIDTH``
            and ``ENV.WINDOW_HEIGHT`` of the config.
        sleep_time_at_reset: seconds waited after a respawn; None: ``ENV.SLEEP_TIME_AT_RESET``.
        reward_config: ``REWARD_CONFIG`` dict; None: ``ENV.REWARD_CONFIG``.
        reward_path: the reward trajectory file; None: ``reward/reward.npy`` of the data folder
            (or a legacy ``reward.pkl`` there).
        window_title: title of the game window.
        openplanet_host: host of the TMRL_GrabData plugin (127.0.0.1).
        openplanet_port: port of the TMRL_GrabData plugin (9000).
        telemetry_timeout: seconds without a new telemetry frame before a step fails (10).
        client: telemetry source (an :class:`~tmrl.tm.openplanet.OpenPlanetClient`); default: one
            connected at the first reset.
        capture: screen source with ``screenshot() -> BGRA`` (a :class:`~tmrl.tm.capture.WindowCapture`);
            default: the game window, moved and resized at the first reset.
        control: controller with ``send(action)``, ``respawn()`` and ``close_finish_pop_up()``
            (:mod:`tmrl.tm.control`); default from ``gamepad``.
        trajectory: ``(N, 3)`` reward trajectory; default: read from ``reward_path``.
        sleep: the wait function (tests pass a no-op).
        saveghost_port: port of the TMRL_SaveGhost plugin (10000).

    Raises (at the first reset):
        tmrl.tm.record.RewardFileError: no reward file (the message says how to record one).
        tmrl.errors.UserError: window, capture, driver or telemetry problems, one line each.
    """

    def __init__(
        self,
        img_hist_len: int = 4,
        gamepad: bool = True,
        save_replays: bool = False,
        grayscale: bool = True,
        resize_to: tuple[int, int] | None = (64, 64),
        *,
        window_size: tuple[int, int] | None = None,
        sleep_time_at_reset: float | None = None,
        reward_config: Mapping[str, Any] | None = None,
        reward_path: str | None = None,
        window_title: str = "Trackmania",
        openplanet_host: str | None = None,
        openplanet_port: int | None = None,
        telemetry_timeout: float | None = None,
        client: Any = None,
        capture: Any = None,
        control: Any = None,
        trajectory: np.ndarray | None = None,
        sleep: Callable[[float], None] = time.sleep,
        saveghost_port: int | None = None,
    ) -> None:
        self.img_hist_len = int(img_hist_len)
        self.gamepad = bool(gamepad)
        self.save_replays = bool(save_replays)
        self.grayscale = bool(grayscale)
        self.resize_to = None if resize_to is None else (int(resize_to[0]), int(resize_to[1]))
        needs_config = window_size is None or sleep_time_at_reset is None or reward_config is None
        env = dict(_env_config().get("ENV", {})) if needs_config else {}
        self.window_size: tuple[int, int] = (
            (int(window_size[0]), int(window_size[1]))
            if window_size is not None
            else (int(env.get("WINDOW_WIDTH", 256)), int(env.get("WINDOW_HEIGHT", 128)))
        )
        self.sleep_time_at_reset = float(
            sleep_time_at_reset if sleep_time_at_reset is not None else env.get("SLEEP_TIME_AT_RESET", 1.5)
        )
        self.reward_config = dict(
            reward_config if reward_config is not None else env.get("REWARD_CONFIG", {})
        )
        self.reward_path = reward_path
        self.window_title = window_title
        self.openplanet_host = openplanet_host
        self.openplanet_port = openplanet_port
        self.telemetry_timeout = telemetry_timeout
        self.client = client
        self.capture = capture
        self.control = control
        self.trajectory = trajectory
        self._sleep = sleep
        self.saveghost_port = saveghost_port
        self.finished = False  # the plugin reported the finish line in this episode
        self._replay_warned = False
        self.reward_function: Any = None
        self.hist: deque[np.ndarray] = deque(maxlen=self.img_hist_len)
        self.img: np.ndarray | None = None
        self.last_data: Any = None
        self.initialized = False

    # ------------------------------------------------------------------ game-facing parts
    def initialize(self) -> None:
        """Connect the telemetry, prepare the window and the controller, load the reward."""
        from tmrl.driving.reward import TrajectoryReward
        from tmrl.tm.record import load_reward

        traj = load_reward(self.reward_path) if self.trajectory is None else np.asarray(self.trajectory)
        self.reward_function = TrajectoryReward.from_config(traj, self.reward_config)
        if self.control is None:
            from tmrl.tm.control import GamepadControl, KeyboardControl

            self.control = GamepadControl() if self.gamepad else KeyboardControl()
        if self.capture is None:
            from tmrl.tm.capture import WindowCapture

            self.capture = WindowCapture(self.window_title, self.window_size[0], self.window_size[1])
            self.capture.move_and_resize(0, 0)
        if self.client is None:
            from tmrl.tm.openplanet import OpenPlanetClient

            self.client = OpenPlanetClient(
                self.openplanet_host, self.openplanet_port, timeout=self.telemetry_timeout
            )
        self.initialized = True

    def close(self) -> None:
        for part in (self.client, self.capture):
            closer = getattr(part, "close", None)
            if closer is not None:
                closer()

    def _grab_image(self) -> np.ndarray:
        from tmrl.tm.capture import preprocess

        bgra = self.capture.screenshot()
        w, h = self.resize_to if self.resize_to is not None else (None, None)
        return preprocess(bgra, w, h, grayscale=self.grayscale)

    def _grab(self) -> tuple[np.ndarray, Any]:
        item = self._grab_image()  # the picture first, then the newest telemetry, as the original
        data = self.client.retrieve_data(timeout=self.telemetry_timeout)
        self.img = item
        self.last_data = data
        return item, data

    def _observation(self, item: np.ndarray, data: Any) -> list[Any]:
        return [
            np.array([data[0]], dtype=np.float32),
            np.array([data[9]], dtype=np.float32),
            np.array([data[10]], dtype=np.float32),
            np.array(self.hist, dtype=np.uint8),
        ]

    # ------------------------------------------------------------------ RealTimeGymInterface
    def send_control(self, control: Any) -> None:
        if control is not None and self.control is not None:
            self.control.send(control)

    def _reset_race(self) -> None:
        self.control.respawn()

    def reset(self, seed: int | None = None, options: dict[str, Any] | None = None) -> tuple[list[Any], dict]:
        if not self.initialized:
            self.initialize()
        self.send_control(self.get_default_action())
        self._reset_race()
        # The respawn itself takes ~0.1 s with the gamepad (the button is held): wait the rest.
        self._sleep(max(0.0, self.sleep_time_at_reset - 0.1) if self.gamepad else self.sleep_time_at_reset)
        item, data = self._grab()
        self.hist.clear()
        for _ in range(self.img_hist_len):
            self.hist.append(item)
        self.reward_function.reset()
        self.finished = False
        return self._observation(item, data), {}

    def _save_replay(self) -> None:
        from tmrl.tm.openplanet import SAVEGHOST_PORT, request_replay

        host = self.openplanet_host or "127.0.0.1"
        problem = request_replay(host, self.saveghost_port or SAVEGHOST_PORT)
        if problem is not None and not self._replay_warned:
            self._replay_warned = True  # once per run: the episodes go on without replays
            logger.warning("%s", problem)
        self._sleep(1.0)  # the plugin saves while the car still stands at the finish

    def wait(self) -> None:
        self.send_control(self.get_default_action())
        if self.save_replays and self.finished:
            self._save_replay()
        self._reset_race()
        self._sleep(0.5)
        self.control.close_finish_pop_up()

    def get_obs_rew_terminated_info(self) -> tuple[list[Any], float, bool, dict]:
        item, data = self._grab()
        rew, terminated = self.reward_function.compute_reward(
            np.array([data[2], data[3], data[4]], dtype=np.float64)
        )
        self.hist.append(item)
        obs = self._observation(item, data)
        if bool(data[8]):  # the plugin's "race finished" flag
            terminated = True
            self.finished = True
            rew += self.reward_function.end_of_track
        rew += self.reward_function.constant_penalty
        return obs, float(np.float32(rew)), bool(terminated), {}  # float32 precision, as the original

    def get_observation_space(self) -> spaces.Tuple:
        speed = spaces.Box(low=0.0, high=1000.0, shape=(1,), dtype=np.float32)
        gear = spaces.Box(low=0.0, high=6.0, shape=(1,), dtype=np.float32)
        rpm = spaces.Box(low=0.0, high=np.inf, shape=(1,), dtype=np.float32)
        w, h = self.resize_to if self.resize_to is not None else self.window_size
        shape = (self.img_hist_len, h, w) if self.grayscale else (self.img_hist_len, h, w, 3)
        return spaces.Tuple((speed, gear, rpm, spaces.Box(low=0, high=255, shape=shape, dtype=np.uint8)))

    def get_action_space(self) -> spaces.Box:
        return spaces.Box(low=-1.0, high=1.0, shape=(3,), dtype=np.float32)

    def get_default_action(self) -> np.ndarray:
        return np.array([0.0, 0.0, 0.0], dtype=np.float32)

    def render(self) -> Any:
        """The last image (or lidar) captured."""
        return self.img


class TM20LidarInterface(TM20FullInterface):
    """TrackMania 2020 seen through a 19-beam lidar of the screenshot (the original
    ``TM2020InterfaceLidar``). Takes the arguments of :class:`TM20FullInterface`; the image ones
    are unused. ``img_hist_len`` is the number of lidar scans per observation (default 1)."""

    def __init__(
        self, img_hist_len: int = 1, gamepad: bool = False, save_replays: bool = False, **kwargs: Any
    ) -> None:
        kwargs.pop("grayscale", None)
        kwargs.pop("resize_to", None)
        super().__init__(img_hist_len, gamepad, save_replays, grayscale=False, resize_to=None, **kwargs)
        self.lidar: Any = None
        self.black_threshold: Any = None  # None: the original LIDAR_BLACK_THRESHOLD (55, 55, 55)
        self.screenshot: np.ndarray | None = None

    def _grab_image(self) -> np.ndarray:
        from tmrl.driving.lidar import DEFAULT_BLACK_THRESHOLD, Lidar

        img = self.capture.screenshot()[..., :3]
        if self.lidar is None:
            self.lidar = Lidar.for_image(
                img, DEFAULT_BLACK_THRESHOLD if self.black_threshold is None else self.black_threshold
            )
        self.screenshot = img  # for --check-environment, which draws the rays on it
        return self.lidar.measure(img)

    def _observation(self, item: np.ndarray, data: Any) -> list[Any]:
        return [np.array([data[0]], dtype=np.float32), np.array(self.hist, dtype=np.float32)]

    def get_observation_space(self) -> spaces.Tuple:
        speed = spaces.Box(low=0.0, high=1000.0, shape=(1,), dtype=np.float32)
        lidars = spaces.Box(low=0.0, high=np.inf, shape=(self.img_hist_len, 19), dtype=np.float32)
        return spaces.Tuple((speed, lidars))


class TM20LidarProgressInterface(TM20LidarInterface):
    """:class:`TM20LidarInterface` plus the track progress in [0, 1] (the original
    ``TM2020InterfaceLidarProgress``): the fraction of the reward trajectory passed."""

    def _observation(self, item: np.ndarray, data: Any) -> list[Any]:
        progress = self.reward_function.progress if self.reward_function is not None else 0.0
        return [
            np.array([data[0]], dtype=np.float32),
            np.array([min(max(progress, 0.0), 1.0)], dtype=np.float32),
            np.array(self.hist, dtype=np.float32),
        ]

    def reset(self, seed: int | None = None, options: dict[str, Any] | None = None) -> tuple[list[Any], dict]:
        obs, info = super().reset(seed=seed, options=options)
        obs[1] = np.zeros(1, dtype=np.float32)  # the reward was reset after the observation was built
        return obs, info

    def get_observation_space(self) -> spaces.Tuple:
        speed = spaces.Box(low=0.0, high=1000.0, shape=(1,), dtype=np.float32)
        progress = spaces.Box(low=0.0, high=1.0, shape=(1,), dtype=np.float32)
        lidars = spaces.Box(low=0.0, high=np.inf, shape=(self.img_hist_len, 19), dtype=np.float32)
        return spaces.Tuple((speed, progress, lidars))


INTERFACES: dict[str, type[TM20FullInterface]] = {
    "TM20FULL": TM20FullInterface,
    "TM20LIDAR": TM20LidarInterface,
    "TM20LIDARPROGRESS": TM20LidarProgressInterface,
}


def interface_class(name: str) -> type[TM20FullInterface]:
    """The interface class for an ``ENV.RTGYM_INTERFACE`` value.

    Raises:
        UserError: not a TrackMania interface name.
    """
    try:
        return INTERFACES[name.upper()]
    except KeyError:
        raise UserError(
            f"ENV.RTGYM_INTERFACE {name!r} is not a TrackMania interface: use one of {', '.join(INTERFACES)}"
        ) from None


def realtime_config(cfg: Mapping[str, Any], **interface_kwargs: Any) -> dict[str, Any]:
    """The ``tmrl.realtime`` configuration of a TrackMania run, as the original config_objects
    builds it: the defaults, ``ENV.RTGYM_CONFIG`` on top, and the interface selected by
    ``ENV.RTGYM_INTERFACE`` with its arguments from the config.

    Args:
        cfg: a validated tmrl config.
        interface_kwargs: extra keyword arguments of the interface (e.g. injected parts).
    """
    env = cfg["ENV"]
    name = str(env["RTGYM_INTERFACE"]).upper()
    cls = interface_class(name)
    kwargs: dict[str, Any] = {
        "img_hist_len": int(env["IMG_HIST_LEN"]),
        "gamepad": bool(cfg.get("VIRTUAL_GAMEPAD", True)),
        "window_size": (int(env["WINDOW_WIDTH"]), int(env["WINDOW_HEIGHT"])),
        "sleep_time_at_reset": float(env["SLEEP_TIME_AT_RESET"]),
        "reward_config": dict(env.get("REWARD_CONFIG", {})),
    }
    if name == "TM20FULL":
        kwargs["grayscale"] = bool(env["IMG_GRAYSCALE"])
        kwargs["resize_to"] = (int(env["IMG_WIDTH"]), int(env["IMG_HEIGHT"]))
    rt = dict(DEFAULT_CONFIG_DICT)
    rt_overrides = dict(env.get("RTGYM_CONFIG", {}))
    kwargs.update(rt_overrides.pop("interface_kwargs", None) or {})
    rt_overrides.pop("interface_args", None)
    rt.update(rt_overrides)
    kwargs.update(interface_kwargs)
    rt["interface"] = cls
    rt["interface_args"] = ()
    rt["interface_kwargs"] = kwargs
    return rt
