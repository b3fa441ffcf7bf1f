"""The pretrained LIDAR actor drives, end to end: a stand-in ``SAC_4_LIDAR_pretrained.tmod`` in the
original's layout goes through ``--install --env tm20lidar`` (the import by the restricted loader),
then a rollout worker runs it on the TM20LIDAR interface against a fake TMRL_GrabData plugin (real
TCP, real 44-byte frames) and a window on Xvfb, and its actions reach the gamepad. The actions are
checked against the original network's forward pass computed here with NumPy from the stand-in's
tensors. Also: with ``save_replays`` on, a finished race asks TMRL_SaveGhost for its replay."""

from __future__ import annotations

import socket
import threading
import time
import warnings

import numpy as np
import pytest
from test_tm_interfaces import RecordingPad, lidar_image, paint_window
from tm_resources_support import ArchiveServer, archive, lidar_state
from xvfb_support import xvfb_display

from tmrl import cli
from tmrl.tm.control import GamepadControl
from tmrl.tm.openplanet import OpenPlanetClient, pack_frame
from tmrl.tm.resources import URL_ENV


class StreamingPlugin:
    """A fake TMRL_GrabData: sends a frame every few milliseconds, the car moving along x."""

    def __init__(self) -> None:
        self.srv = socket.create_server(("127.0.0.1", 0))
        self.port = self.srv.getsockname()[1]
        self.finished = 0.0
        self._stop = threading.Event()
        threading.Thread(target=self._run, daemon=True).start()

    def _run(self) -> None:
        try:
            conn, _ = self.srv.accept()
        except OSError:
            return
        x = 0.0
        with conn:
            while not self._stop.is_set():
                x += 0.05
                try:
                    conn.sendall(pack_frame((40.0, x, x, 0.0, 0.0, 0.0, 1.0, 0.0, self.finished, 3.0, 6000.0)))
                except OSError:
                    return
                time.sleep(0.005)

    def close(self) -> None:
        self._stop.set()
        self.srv.close()


def original_forward(state: dict, raw_obs: tuple) -> np.ndarray:
    """tmrl 0.7's SquashedGaussianMLPActor in test mode: the observation flattened and concatenated
    in order (its lidar preprocessor flattens the scans), two ReLU layers, ``tanh(mu)``."""
    w = {k: v.numpy().astype(np.float64) for k, v in state.items()}
    x = np.concatenate([np.ravel(np.asarray(o, dtype=np.float64)) for o in raw_obs])
    h = np.maximum(w["net.0.weight"] @ x + w["net.0.bias"], 0.0)
    h = np.maximum(w["net.2.weight"] @ h + w["net.2.bias"], 0.0)
    return np.tanh(w["mu_layer.weight"] @ h + w["mu_layer.bias"])


def test_the_pretrained_lidar_actor_drives_the_fake_game(monkeypatch, capsys, _isolated_data_folder):
    from tmrl.assembly import assemble
    from tmrl.config.loader import load_config
    from tmrl.distributed.worker import RolloutWorker
    from tmrl.tm.interfaces import realtime_config
    from tmrl.util import partial

    with ArchiveServer(archive()) as server:
        monkeypatch.setenv(URL_ENV, server.url)
        assert cli.main(["--install", "--env", "tm20lidar"]) == 0
    assert "SAC_4_LIDAR_pretrained.tmod: the pretrained tm20lidar actor, imported" in capsys.readouterr().out
    # The installed config as it is, with the window the Xvfb screen holds and no countdown wait.
    cfg = load_config(overrides={"ENV": {"WINDOW_WIDTH": 256, "WINDOW_HEIGHT": 128, "SLEEP_TIME_AT_RESET": 0.0}})
    assert cfg["ENV"]["RTGYM_INTERFACE"] == "TM20LIDAR" and cfg["RUN_NAME"] == "SAC_4_LIDAR_pretrained"
    parts = assemble(cfg)
    plugin = StreamingPlugin()
    pad = RecordingPad()
    with xvfb_display() as display:
        monkeypatch.setenv("DISPLAY", display)
        d, win = paint_window(display, lidar_image())
        client = OpenPlanetClient(port=plugin.port, retry_interval=0.05, timeout=10, first_timeout=10)
        rt = realtime_config(cfg, client=client, sleep=lambda s: None, gamepad=True,
                             control=GamepadControl(backend=pad, sleep=lambda s: None))
        env_cls = parts.ENV_CLS
        env_cls = partial(env_cls.func, *env_cls.args, **{**env_cls.keywords, "gym_kwargs": {"config": rt}})
        data = _isolated_data_folder
        worker = RolloutWorker(env_cls, parts.POLICY, obs_preprocessor=parts.OBS_PREPROCESSOR,
                               model_path=data / "weights" / "SAC_4_LIDAR_pretrained.tmod", standalone=True)
        seen: list[tuple[tuple, np.ndarray]] = []
        raw = {}
        env_step, env_reset, act = worker.env.step, worker.env.reset, worker.act

        def step(a):
            out = env_step(a)
            raw["obs"] = out[0]
            return out

        def reset(**kw):
            out = env_reset(**kw)
            raw["obs"] = out[0]
            return out

        def record(obs, test=False):
            a = act(obs, test=test)
            seen.append((tuple(raw["obs"]), np.asarray(a, dtype=np.float64)))
            return a

        worker.env.step, worker.env.reset, worker.act = step, reset, record
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")  # a loaded machine may miss a 50 ms deadline
                worker.run_episode(max_samples=6)
        finally:
            worker.close()
            worker.env.close()
            client.close()
            plugin.close()
            win.destroy()
            d.close()
    state = lidar_state()  # the stand-in's tensors, as the archive held them
    assert len(seen) == 6
    lidars = [obs[1] for obs, _ in seen]
    assert all(np.asarray(scan).shape == (4, 19) and np.asarray(scan).max() > 0 for scan in lidars)
    for obs, action in seen:
        np.testing.assert_allclose(action, original_forward(state, obs), atol=1e-4)
    assert len({tuple(np.round(a, 4)) for _, a in seen}) > 1  # the policy reacts to what it sees
    gas = [c[1] for c in pad.calls if c[0] == "right_trigger_float"]
    steer = [c[1] for c in pad.calls if c[0] == "left_joystick_float"]
    expected_gas = [max(float(a[0]), 0.0) for _, a in seen]
    assert len(gas) >= len(seen)
    for want in expected_gas:
        assert any(abs(g - want) < 1e-4 for g in gas), (want, gas)
    for _, a in seen:
        assert any(abs(s - float(a[2])) < 1e-4 for s in steer), (a, steer)


# ------------------------------------------------------------------------ replays
class FakeCapture:
    def screenshot(self) -> np.ndarray:
        img = lidar_image()[..., ::-1]
        return np.dstack([img, np.full(img.shape[:2], 255, np.uint8)])


class FakeSaveGhost:
    """The TMRL_SaveGhost plugin's side: counts the connections it accepts."""

    def __init__(self) -> None:
        self.srv = socket.create_server(("127.0.0.1", 0))
        self.port = self.srv.getsockname()[1]
        self.requests: list[bytes] = []
        self.event = threading.Event()
        threading.Thread(target=self._run, daemon=True).start()

    def _run(self) -> None:
        while True:
            try:
                conn, _ = self.srv.accept()
            except OSError:
                return
            with conn:
                conn.settimeout(1.0)
                try:
                    self.requests.append(conn.recv(64))
                except OSError:
                    self.requests.append(b"")
            self.event.set()


@pytest.mark.parametrize("finished", [True, False])
def test_a_finished_race_asks_saveghost_for_its_replay(finished):
    from tmrl.tm.interfaces import TM20LidarInterface

    ghost = FakeSaveGhost()
    plugin = StreamingPlugin()
    plugin.finished = 1.0 if finished else 0.0
    client = OpenPlanetClient(port=plugin.port, retry_interval=0.05, timeout=10, first_timeout=10)
    pad = RecordingPad()
    iface = TM20LidarInterface(save_replays=True, gamepad=True, window_size=(256, 128), sleep_time_at_reset=0.0,
                               reward_config={}, client=client, capture=FakeCapture(), trajectory=np.c_[
                                   np.arange(1001) * 0.1, np.zeros(1001), np.zeros(1001)],
                               control=GamepadControl(backend=pad, sleep=lambda s: None), sleep=lambda s: None,
                               saveghost_port=ghost.port)
    try:
        iface.reset()
        _, _, terminated, _ = iface.get_obs_rew_terminated_info()
        assert terminated is finished
        iface.wait()
        if finished:
            assert ghost.event.wait(5)
            assert ghost.requests == [b""]  # a bare connection: the plugin's whole protocol
        else:
            assert not ghost.event.wait(0.3) and ghost.requests == []
    finally:
        iface.close()
        plugin.close()
        ghost.srv.close()


def test_saveghost_missing_is_one_warning_and_the_episode_goes_on(caplog, port_factory):
    from tmrl.tm.openplanet import request_replay

    problem = request_replay(port=port_factory())
    assert problem is not None and "\n" not in problem and "--install --env tm20lidar" in problem
