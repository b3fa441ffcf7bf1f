"""TM20FULL, TM20LIDAR and TM20LIDARPROGRESS run end to end through tmrl.realtime against a fake
OpenPlanet plugin (real TCP, real 44-byte frames), a window on Xvfb captured by the real capture
code, and a gamepad backend that records calls."""

from __future__ import annotations

import socket
import threading
import warnings

import numpy as np
import pytest
from xvfb_support import xvfb_display

from tmrl.errors import UserError
from tmrl.tm.capture import preprocess
from tmrl.tm.control import BUTTON_A, BUTTON_B, GamepadControl
from tmrl.tm.interfaces import (
    TM20FullInterface,
    TM20LidarInterface,
    TM20LidarProgressInterface,
    interface_class,
    realtime_config,
)
from tmrl.tm.openplanet import OpenPlanetClient, pack_frame

W, H = 256, 128
TRAJ = np.c_[np.arange(1001) * 0.1, np.zeros(1001), np.zeros(1001)]  # 100 m straight along x


# ------------------------------------------------------------------------ fakes
class FakePlugin:
    def __init__(self):
        self.srv = socket.create_server(("127.0.0.1", 0))
        self.port = self.srv.getsockname()[1]
        self.accepted = threading.Event()
        self.conn = None
        threading.Thread(target=self._accept, daemon=True).start()

    def _accept(self):
        try:
            self.conn, _ = self.srv.accept()
        except OSError:
            return
        self.accepted.set()

    def send(self, x, finished=0.0, speed=50.0):
        self.conn.sendall(pack_frame((speed, x, x, 0.0, 0.0, 0.0, 1.0, 0.0, finished, 3.0, 7000.0)))

    def close(self):
        if self.conn is not None:
            self.conn.close()
        self.srv.close()


class RecordingPad:
    def __init__(self):
        self.calls = []

    def __getattr__(self, name):
        return lambda *a, **k: self.calls.append((name, *a, *k.values()))


@pytest.fixture
def plugin():
    p = FakePlugin()
    yield p
    p.close()


@pytest.fixture
def client(plugin):
    c = OpenPlanetClient(port=plugin.port, retry_interval=0.05, timeout=10, first_timeout=10)
    assert plugin.accepted.wait(10)
    yield c
    c.close()


@pytest.fixture(scope="module")
def xvfb():
    with xvfb_display() as name:
        yield name


def paint_window(display_name, image, title="Trackmania"):
    """A mapped window whose background pixmap is ``image`` (RGB); returns (display, window)."""
    from Xlib import X, display

    d = display.Display(display_name)
    screen = d.screen()
    h, w = image.shape[:2]
    pixmap = screen.root.create_pixmap(w, h, screen.root_depth)
    gc = pixmap.create_gc()
    for row in range(h):
        col = 0
        while col < w:
            end = col
            while end < w and (image[row, end] == image[row, col]).all():
                end += 1
            r, g, b = (int(v) for v in image[row, col])
            gc.change(foreground=(r << 16) | (g << 8) | b)
            pixmap.fill_rectangle(gc, col, row, end - col, 1)
            col = end
    win = screen.root.create_window(
        40,
        30,
        120,
        60,
        0,
        screen.root_depth,
        X.InputOutput,
        X.CopyFromParent,
        background_pixmap=pixmap,
        event_mask=X.StructureNotifyMask,
    )
    win.set_wm_name(title)
    win.map()
    while True:
        ev = d.next_event()
        if ev.type == X.MapNotify and ev.window.id == win.id:
            break
    d.sync()
    return d, win


def full_image():
    img = np.zeros((H, W, 3), dtype=np.uint8)
    img[:, : W // 2] = (200, 120, 40)
    img[: H // 2, W // 2 :] = (30, 60, 250)
    img[H // 2 :, W // 2 :] = (255, 255, 255)
    return img


def lidar_image():
    img = np.full((H, W, 3), 100, dtype=np.uint8)  # grey road
    img[:, :40] = 0  # dark border on the left
    img[:, 216:] = 0  # and on the right
    img[:20] = 0  # and far ahead
    return img


def make_env(xvfb, monkeypatch, client, interface, image, **extra):
    from tmrl.config.loader import load_config
    from tmrl.realtime import RealTimeEnv

    monkeypatch.setenv("DISPLAY", xvfb)
    d, win = paint_window(xvfb, image)
    cfg = load_config(
        overrides={
            "ENV": {
                "RTGYM_INTERFACE": interface,
                "IMG_HIST_LEN": 4,
                "WINDOW_WIDTH": W,
                "WINDOW_HEIGHT": H,
                "SLEEP_TIME_AT_RESET": 0.0,
            }
        }
    )
    pad = RecordingPad()
    rt = realtime_config(
        cfg,
        client=client,
        trajectory=TRAJ,
        sleep=lambda s: None,
        gamepad=True,
        control=GamepadControl(backend=pad, sleep=lambda s: None),
        **extra,
    )
    env = RealTimeEnv(rt)
    return env, pad, (d, win)


def drive(env, plugin, xs, action):
    out = []
    for x in xs:
        plugin.send(x)
        out.append(env.step(action))
    return out


# ------------------------------------------------------------------------ tests
@pytest.mark.linux  # a display on Xvfb
def test_tm20full_end_to_end(xvfb, monkeypatch, plugin, client):
    env, pad, (d, win) = make_env(xvfb, monkeypatch, client, "TM20FULL", full_image())
    try:
        assert env.observation_space[3].shape == (4, 64, 64)
        plugin.send(0.0)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # a slow machine may miss a 50 ms deadline
            obs, info = env.reset()
            expected = preprocess(
                np.dstack([full_image()[..., ::-1], np.full((H, W), 255, np.uint8)]), 64, 64
            )
            assert len(obs) == 4 + 2  # speed, gear, rpm, images, then the action buffer of 2
            assert obs[0][0] == 50.0 and obs[1][0] == 3.0 and obs[2][0] == 7000.0
            assert obs[3].shape == (4, 64, 64) and obs[3].dtype == np.uint8
            np.testing.assert_array_equal(obs[3][-1], expected)
            assert env.observation_space.contains(obs)
            assert ("press_button", BUTTON_B) in pad.calls  # respawned at reset
            # the shared driving pipeline accepts these observations: only the newest uint8 image travels
            from tmrl.driving.compressors import compress_full_sample
            from tmrl.driving.preprocessors import preprocess_full_obs

            pre = preprocess_full_obs(obs)
            sample = compress_full_sample(None, pre, 0.0, False, False, {})
            np.testing.assert_array_equal(sample[1][3], expected)
            action = np.array([0.8, 0.0, -0.25], dtype=np.float32)
            steps = drive(env, plugin, [1.0, 2.0, 3.0], action)
            for _obs, rew, term, trunc, _ in steps:
                assert rew == pytest.approx(0.1, abs=1e-6) and not term and not trunc
            assert ("right_trigger_float", pytest.approx(0.8)) in pad.calls
            assert ("left_joystick_float", pytest.approx(-0.25), 0.0) in pad.calls
            pad.calls.clear()
            plugin.send(4.0, finished=1.0)
            o, rew, term, trunc, _ = env.step(action)
        assert term and rew == pytest.approx(100.1, abs=1e-4)
        # wait_on_done: default action, respawn, then A closes the finish pop-up
        assert ("press_button", BUTTON_A) in pad.calls and ("press_button", BUTTON_B) in pad.calls
    finally:
        env.close()
        win.destroy()
        d.close()


@pytest.mark.linux  # a display on Xvfb
@pytest.mark.parametrize("name", ["TM20LIDAR", "TM20LIDARPROGRESS"])
def test_tm20lidar_end_to_end(xvfb, monkeypatch, plugin, client, name):
    from tmrl.driving.lidar import Lidar

    env, pad, (d, win) = make_env(xvfb, monkeypatch, client, name, lidar_image())
    img = lidar_image()
    expected = Lidar.for_image(img).measure(img)
    assert expected[0] == 68 and expected[-1] == 69  # right and left borders, by hand
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            plugin.send(0.0)
            obs, _ = env.reset()
            lidars = obs[-3]
            assert lidars.shape == (4, 19)
            np.testing.assert_array_equal(lidars[-1], expected)
            steps = drive(env, plugin, [2.0, 5.0], np.array([1.0, 0.0, 0.0], dtype=np.float32))
        assert [round(float(s[1]), 4) for s in steps] == [0.2, 0.3]
        if name == "TM20LIDARPROGRESS":
            assert obs[1][0] == 0.0
            assert steps[-1][0][1][0] == pytest.approx(50 / 1001)
        assert env.observation_space.contains(steps[-1][0])
        plugin.send(6.0)  # the time step still running gets its frame, so close() need not wait
    finally:
        env.close()
        win.destroy()
        d.close()


def test_spaces_without_a_game():
    full = TM20FullInterface(window_size=(W, H), sleep_time_at_reset=0, reward_config={}, grayscale=False)
    assert full.get_observation_space()[3].shape == (4, 64, 64, 3)
    lidar = TM20LidarProgressInterface(
        img_hist_len=3, window_size=(W, H), sleep_time_at_reset=0, reward_config={}
    )
    assert [s.shape for s in lidar.get_observation_space()] == [(1,), (1,), (3, 19)]
    assert full.get_action_space().shape == (3,)


def test_missing_reward_file_says_how_to_record(monkeypatch):
    itf = TM20LidarInterface(
        window_size=(W, H),
        sleep_time_at_reset=0,
        reward_config={},
        control=GamepadControl(backend=RecordingPad()),
        capture=object(),
        client=object(),
    )
    with pytest.raises(UserError, match="--record-reward"):
        itf.reset()


def test_interface_selection_by_name():
    assert interface_class("tm20lidar") is TM20LidarInterface
    assert interface_class("TM20FULL") is TM20FullInterface
    with pytest.raises(UserError, match="not a TrackMania interface"):
        interface_class("SIMFULL")


def test_realtime_config_follows_the_tmrl_config():
    from tmrl.config.loader import load_config

    cfg = load_config(
        overrides={
            "ENV": {
                "RTGYM_INTERFACE": "TM20FULL",
                "IMG_WIDTH": 32,
                "IMG_HEIGHT": 48,
                "IMG_GRAYSCALE": False,
                "RTGYM_CONFIG": {"interface_kwargs": {"save_replays": True}},
            }
        }
    )
    rt = realtime_config(cfg)
    assert rt["interface"] is TM20FullInterface
    kw = rt["interface_kwargs"]
    assert kw["resize_to"] == (32, 48) and kw["grayscale"] is False and kw["save_replays"] is True
    assert kw["window_size"] == (cfg["ENV"]["WINDOW_WIDTH"], cfg["ENV"]["WINDOW_HEIGHT"])
    assert rt["time_step_duration"] == cfg["ENV"]["RTGYM_CONFIG"]["time_step_duration"]
    assert rt["act_buf_len"] == cfg["ENV"]["RTGYM_CONFIG"]["act_buf_len"]


# ------------------------------------------------------------------------ tools on the same fakes
class StreamingPlugin:
    """Streams the same telemetry frame every few milliseconds to one client."""

    def __init__(self, x=0.0):
        self.srv = socket.create_server(("127.0.0.1", 0))
        self.port = self.srv.getsockname()[1]
        self.x = x
        self.stop = threading.Event()
        self.thread = threading.Thread(target=self._serve, daemon=True)
        self.thread.start()

    def _serve(self):
        self.srv.settimeout(0.2)
        while not self.stop.is_set():
            try:
                conn, _ = self.srv.accept()
            except OSError:
                continue
            with conn:
                while not self.stop.is_set():
                    try:
                        conn.sendall(pack_frame((10.0, self.x, self.x, 0.0, 0.0, 0, 0, 0, 0.0, 1.0, 1000.0)))
                    except OSError:
                        break
                    self.stop.wait(0.004)

    def close(self):
        self.stop.set()
        self.thread.join(timeout=5)
        self.srv.close()


def read_png(path):
    """Minimal PNG reader for the files write_png makes (8-bit, filter 0)."""
    import struct
    import zlib

    data = path.read_bytes()
    assert data[:8] == b"\x89PNG\r\n\x1a\n"
    pos, idat, ihdr = 8, b"", None
    while pos < len(data):
        n = struct.unpack(">I", data[pos : pos + 4])[0]
        kind, body = data[pos + 4 : pos + 8], data[pos + 8 : pos + 8 + n]
        if kind == b"IHDR":
            ihdr = struct.unpack(">IIBBBBB", body)
        elif kind == b"IDAT":
            idat += body
        pos += 12 + n
    w, h, _, color, *_ = ihdr
    ch = 3 if color == 2 else 1
    raw = np.frombuffer(zlib.decompress(idat), dtype=np.uint8).reshape(h, 1 + w * ch)
    assert (raw[:, 0] == 0).all()
    return raw[:, 1:].reshape(h, w, ch) if ch == 3 else raw[:, 1:].reshape(h, w)


def test_write_png_round_trip(tmp_path):
    from tmrl.tm.tools import write_png

    rgb = (np.random.default_rng(0).random((7, 5, 3)) * 255).astype(np.uint8)
    np.testing.assert_array_equal(read_png(write_png(tmp_path / "a.png", rgb)), rgb)
    gray = rgb[..., 0]
    np.testing.assert_array_equal(read_png(write_png(tmp_path / "b.png", gray)), gray)


@pytest.mark.linux  # a display on Xvfb
def test_check_environment_saves_what_the_policy_sees(xvfb, monkeypatch, tmp_path):
    import io

    from tmrl.config.loader import load_config
    from tmrl.tm.tools import check_environment

    monkeypatch.setenv("DISPLAY", xvfb)
    d, win = paint_window(xvfb, lidar_image())
    stream = StreamingPlugin()
    try:
        cfg = load_config(
            overrides={
                "ENV": {
                    "RTGYM_INTERFACE": "TM20LIDAR",
                    "WINDOW_WIDTH": W,
                    "WINDOW_HEIGHT": H,
                    "SLEEP_TIME_AT_RESET": 0.0,
                }
            }
        )
        out = io.StringIO()
        # the keyboard respawn goes through the real XTest backend on the Xvfb display
        code = check_environment(
            cfg, steps=3, out_dir=tmp_path, every=1, out=out, trajectory=TRAJ, openplanet_port=stream.port
        )
    finally:
        stream.close()
        win.destroy()
        d.close()
    assert code == 0
    files = sorted(p.name for p in tmp_path.iterdir())
    assert files == ["step_000001.png", "step_000002.png", "step_000003.png"]
    img = read_png(tmp_path / files[-1])
    assert img.shape == (H, W, 3)
    assert ((img == (255, 0, 0)).all(axis=-1)).sum() > 100  # the rays are drawn
    assert "reward" in out.getvalue()


@pytest.mark.linux  # a display on Xvfb
def test_benchmark_prints_the_real_time_report(xvfb, monkeypatch):
    import io

    from tmrl.config.loader import load_config
    from tmrl.tm.tools import benchmark

    monkeypatch.setenv("DISPLAY", xvfb)
    d, win = paint_window(xvfb, lidar_image())
    stream = StreamingPlugin(x=1.0)
    out = io.StringIO()
    try:
        cfg = load_config(
            overrides={
                "ENV": {
                    "RTGYM_INTERFACE": "TM20LIDAR",
                    "WINDOW_WIDTH": W,
                    "WINDOW_HEIGHT": H,
                    "SLEEP_TIME_AT_RESET": 0.0,
                }
            }
        )
        pad = RecordingPad()
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            code = benchmark(
                cfg,
                steps=5,
                out=out,
                trajectory=TRAJ,
                openplanet_port=stream.port,
                control=GamepadControl(backend=pad, sleep=lambda s: None),
            )
    finally:
        stream.close()
        win.destroy()
        d.close()
    assert code == 0
    text = out.getvalue()
    assert "time_step_duration" in text and "get_obs_duration" in text
    assert ("left_joystick_float", 0.0, 0.0) in pad.calls  # the default action was applied
