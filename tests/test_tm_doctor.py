"""``--doctor`` checks: on a machine without the game every failure is listed with its fix and the
exit code is non-zero; against a fake OpenPlanet plugin and a window on Xvfb, the telemetry,
window and capture checks pass."""

from __future__ import annotations

import io
import os
import socket
import subprocess
import sys
import threading

import numpy as np
import pytest
from xvfb_support import xvfb_display

from tmrl.tm import doctor
from tmrl.tm.doctor import CheckResult, format_report, run_checks, run_doctor
from tmrl.tm.openplanet import pack_frame
from tmrl.tm.record import save_reward


def base_cfg(**top):
    env = {
        "RTGYM_INTERFACE": "TM20FULL",
        "WINDOW_WIDTH": 256,
        "WINDOW_HEIGHT": 128,
        "IMG_WIDTH": 64,
        "IMG_HEIGHT": 64,
        "IMG_GRAYSCALE": True,
        "RTGYM_CONFIG": {"time_step_duration": 0.05, "start_obs_capture": 0.04},
        "REWARD_CONFIG": {"CONSTANT_PENALTY": 0.0},
    }
    cfg = {
        "ENV": env,
        "VIRTUAL_GAMEPAD": True,
        "LOCALHOST_WORKER": True,
        "LOCALHOST_TRAINER": True,
        "PUBLIC_IP_SERVER": "0.0.0.0",
        "PORT": 55555,
        "TLS": False,
        "ALLOW_PLAIN_TCP": False,
        "CUDA_TRAINING": False,
        "CUDA_INFERENCE": False,
        "PASSWORD": "x",
        "RUN_NAME": "run",
        "TLS_CREDENTIALS_DIRECTORY": "",
    }
    cfg.update(top)
    return cfg


def test_without_the_game_every_failure_has_a_fix(port_factory, monkeypatch):
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    out = io.StringIO()
    code = run_doctor(
        base_cfg(PORT=port_factory()), out=out, openplanet_port=port_factory(), openplanet_wait=0.3
    )
    text = out.getvalue()
    assert code == doctor.CHECKS_FAILED == 3  # 1 stays reserved for bugs in tmrl
    assert "Traceback" not in text
    lines = text.splitlines()
    fails = [i for i, line in enumerate(lines) if line.startswith("[FAIL]")]
    names = {lines[i].split("]")[1].split("  ")[0].strip() for i in fails}
    assert {"OpenPlanet telemetry", "game window", "reward file", "server reachable"} <= names
    for i in fails:
        assert lines[i + 1].lstrip().startswith("fix: ") and len(lines[i + 1]) > 20
    assert "nothing answers at 127.0.0.1" in text and "--record-reward" in text
    assert "[SKIP] capture time" in text


def test_doctor_in_a_subprocess_prints_no_traceback(tmp_path, port_factory):
    code = (
        "import sys\n"
        "from tmrl.tm.doctor import run_doctor\n"
        f"sys.exit(run_doctor(openplanet_port={port_factory()}, openplanet_wait=0.2, server_timeout=0.5))\n"
    )
    env = {k: v for k, v in os.environ.items() if k not in ("DISPLAY", "WAYLAND_DISPLAY")}
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=60)
    assert proc.returncode == 3
    assert "Traceback" not in proc.stdout + proc.stderr
    assert "[FAIL] OpenPlanet telemetry" in proc.stdout and "fix:" in proc.stdout


def test_other_interfaces_skip_the_game_checks_and_see_packages_and_data_folder(tmp_path, monkeypatch):
    cfg = base_cfg()
    cfg["ENV"]["RTGYM_INTERFACE"] = "SIMLIDAR"
    monkeypatch.setenv("TMRL_DATA", str(tmp_path / "missing"))
    results = {r.name: r for r in run_checks(cfg, only=("packages", "data", "config", "openplanet", "window",
                                                        "gamepad", "capture", "reward"))}
    assert results["packages"].status == "pass" and "torch" in results["packages"].detail
    assert results["data folder"].status == "skip" and "--install" in results["data folder"].detail
    assert results["config"].status == "pass" and "SIMLIDAR" in results["config"].detail
    for name in ("OpenPlanet telemetry", "game window", "gamepad driver", "capture time", "reward file"):
        assert results[name].status == "skip" and "not needed for SIMLIDAR" in results[name].detail
    assert not (tmp_path / "missing").exists()  # the doctor creates nothing
    (tmp_path / "missing" / "config").mkdir(parents=True)
    (res,) = run_checks(cfg, only=("data",))
    assert res.status == "fail" and "--install" in res.fix  # a folder without config.json
    (tmp_path / "missing" / "config" / "config.json").write_text("{}")
    (res,) = run_checks(cfg, only=("data",))
    assert res.status == "pass"


def test_missing_trackmania_extras_fail_the_packages_check(monkeypatch):
    import importlib.util

    real = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec", lambda name, *a: None if name == "mss" else real(name, *a))
    assert doctor.check_packages("SIMLIDAR").status == "pass"
    res = doctor.check_packages("TM20LIDAR")
    assert res.status == "fail" and "mss" in res.detail and 'pip install ".[trackmania]"' in res.fix


def test_a_crashing_check_becomes_a_failure(monkeypatch):
    def boom(*a, **k):
        raise RuntimeError("kaput")

    monkeypatch.setattr(doctor, "check_reward_file", boom)
    (res,) = run_checks(base_cfg(), only=("reward",))
    assert res.status == "fail" and "RuntimeError: kaput" in res.detail and "report" in res.fix


def test_reward_check_passes_with_a_recorded_file(tmp_path):
    save_reward(np.c_[np.arange(1001) * 0.1, np.zeros(1001), np.zeros(1001)], tmp_path / "r.npy")
    res = doctor.check_reward_file(tmp_path / "r.npy")
    assert res.status == "pass" and "1001 points (100 m" in res.detail


def test_config_problems_are_reported_with_their_keys():
    cfg = base_cfg(LOCALHOST_WORKER=False, PASSWORD="YourRandomPasswordHere")
    cfg["ENV"]["RTGYM_CONFIG"]["start_obs_capture"] = 0.2
    res = doctor.check_config(cfg)
    assert res.status == "fail"
    assert "start_obs_capture" in res.fix and "--install" in res.fix
    assert doctor.check_config(base_cfg()).status == "pass"


def test_tls_remote_without_tls_fails_and_missing_certificate_fails(tmp_path):
    assert doctor.check_tls(base_cfg(LOCALHOST_WORKER=False)).status == "fail"
    assert doctor.check_tls(base_cfg(LOCALHOST_WORKER=False, ALLOW_PLAIN_TCP=True)).status == "pass"
    res = doctor.check_tls(base_cfg(TLS=True), credentials_dir=tmp_path)
    assert res.status == "fail" and "certificate.pem" in res.detail
    (tmp_path / "certificate.pem").write_text("x")
    assert doctor.check_tls(base_cfg(TLS=True), credentials_dir=tmp_path).status == "pass"


def test_gpu_asked_but_missing_fails(monkeypatch):
    torch = pytest.importorskip("torch")
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    assert doctor.check_gpu(cuda_training=True).status == "fail"
    assert doctor.check_gpu().status == "pass"


def test_server_check_against_a_listening_socket(port_factory):
    with socket.create_server(("127.0.0.1", 0)) as srv:
        assert doctor.check_server("127.0.0.1", srv.getsockname()[1]).status == "pass"
    assert doctor.check_server("127.0.0.1", port_factory(), timeout=0.5).status == "fail"


def test_report_format():
    text = format_report([CheckResult("a", "pass", "fine"), CheckResult("bb", "fail", "broken", "do x")])
    assert text.splitlines() == [
        "[PASS] a   fine",
        "[FAIL] bb  broken",
        "           fix: do x",
        "1 of 2 checks passed or skipped, 1 failed",
    ]


# ------------------------------------------------------------------------ against the fakes
class StreamingPlugin:
    """Fake TMRL_GrabData that streams frames continuously to each client until stopped."""

    def __init__(self):
        self.srv = socket.create_server(("127.0.0.1", 0))
        self.port = self.srv.getsockname()[1]
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
                i = 0
                while not self.stop.is_set():
                    try:
                        conn.sendall(pack_frame((12.0, i, 500.0, 10.0, 300.0, 0, 1, 0, 0, 2, 6000)))
                    except OSError:
                        break
                    i += 1
                    self.stop.wait(0.005)  # pacing like a game running at ~200 fps

    def close(self):
        self.stop.set()
        self.thread.join(timeout=5)
        self.srv.close()


@pytest.fixture
def plugin():
    p = StreamingPlugin()
    yield p
    p.close()


def test_openplanet_check_passes_against_the_fake_plugin(plugin):
    res = doctor.check_openplanet("127.0.0.1", plugin.port, wait=5.0, measure=0.5, min_rate=1.0)
    assert res.status == "pass", res
    assert "position (500.0, 10.0, 300.0)" in res.detail


@pytest.fixture
def xvfb_window(monkeypatch):
    with xvfb_display() as name:
        from Xlib import X, display

        monkeypatch.setenv("DISPLAY", name)
        d = display.Display(name)
        screen = d.screen()
        win = screen.root.create_window(
            30,
            40,
            256,
            128,
            0,
            screen.root_depth,
            X.InputOutput,
            X.CopyFromParent,
            background_pixel=0x336699,
            event_mask=X.StructureNotifyMask,
        )
        win.set_wm_name("Trackmania")
        win.map()
        while not (lambda ev: ev.type == X.MapNotify)(d.next_event()):
            pass
        d.sync()
        yield name
        d.close()


@pytest.mark.linux  # a display on Xvfb
def test_window_and_capture_checks_pass_on_xvfb(xvfb_window, plugin, port_factory):
    results = run_checks(
        base_cfg(PORT=port_factory()),
        openplanet_port=plugin.port,
        openplanet_wait=5.0,
        min_frame_rate=1.0,
        only=("openplanet", "window", "capture"),
    )
    by_name = {r.name: r for r in results}
    assert by_name["OpenPlanet telemetry"].status == "pass", by_name["OpenPlanet telemetry"]
    assert by_name["game window"].status == "pass", by_name["game window"]
    assert "picture 256x128" in by_name["game window"].detail
    assert by_name["capture time"].status == "pass", by_name["capture time"]
    assert "ms per frame" in by_name["capture time"].detail


@pytest.mark.linux  # a display on Xvfb
def test_wrong_window_size_fails_with_the_fix(xvfb_window):
    res = doctor.check_window("Trackmania", 300, 200, resize=False)
    assert res.status == "fail" and "256x128, expected 300x200" in res.detail and "windowed" in res.fix


# ------------------------------------------------------------------------ the game side
def test_no_plugin_is_one_line_with_the_fix(tmp_path, monkeypatch):
    from tm_resources_support import plugin_bytes

    home = tmp_path / "home"
    monkeypatch.setenv("HOME", str(home))
    (res,) = run_checks(base_cfg(), only=("plugins",))
    assert res.status == "fail" and "no OpenplanetNext folder" in res.detail and "\n" not in res.detail
    assert "--install --env tm20lidar" in res.fix and "OPENPLANET_FOLDER" in res.fix
    plugins = home / "OpenplanetNext" / "Plugins"
    plugins.mkdir(parents=True)
    (res,) = run_checks(base_cfg(), only=("plugins",))
    assert res.status == "fail" and "TMRL_GrabData.op not in" in res.detail and "--install" in res.fix
    (plugins / "TMRL_GrabData.op").write_bytes(plugin_bytes("TMRL Grab Data", "0.3"))
    (res,) = run_checks(base_cfg(), only=("plugins",))
    assert res.status == "pass" and "TMRL_GrabData.op v0.3" in res.detail
    replays = base_cfg()
    replays["ENV"]["RTGYM_CONFIG"]["interface_kwargs"] = {"save_replays": True}
    (res,) = run_checks(replays, only=("plugins",))
    assert res.status == "fail" and "TMRL_SaveGhost.op not in" in res.detail
    (res,) = run_checks(base_cfg(OPENPLANET_FOLDER=str(tmp_path / "nowhere")), only=("plugins",))
    assert res.status == "fail" and "OPENPLANET_FOLDER" in res.detail


def test_doctor_command_without_plugin_says_so_and_never_blocks(tmp_path, port_factory):
    env = {k: v for k, v in os.environ.items() if k not in ("DISPLAY", "WAYLAND_DISPLAY")}
    env["TMRL_CONFIG_OVERRIDE"] = '{"PORT": %d}' % port_factory()
    proc = subprocess.run([sys.executable, "-m", "tmrl", "--doctor"], capture_output=True, text=True, env=env,
                          timeout=120)
    assert proc.returncode == 3, proc.stdout + proc.stderr
    lines = proc.stdout.splitlines()
    (i,) = [n for n, line in enumerate(lines) if line.startswith("[FAIL] OpenPlanet plugins")]
    assert "OpenplanetNext" in lines[i] and lines[i + 1].lstrip().startswith("fix: ")
    assert "--install --env tm20lidar" in lines[i + 1]
    assert "docs/" not in proc.stdout


class _NoVgamepadImport:
    """A meta-path finder that records any attempt to import vgamepad (and refuses it)."""

    def __init__(self):
        self.attempts = []

    def find_spec(self, name, path=None, target=None):
        if name == "vgamepad" or name.startswith("vgamepad."):
            self.attempts.append(name)
            raise AssertionError("vgamepad imported: its installer would start")
        return None


def test_windows_without_vigembus_never_imports_vgamepad(monkeypatch):
    from tmrl.tm import control

    finder = _NoVgamepadImport()
    monkeypatch.setattr(sys, "meta_path", [finder, *sys.meta_path])
    monkeypatch.delitem(sys.modules, "vgamepad", raising=False)
    monkeypatch.setattr(control.platform, "system", lambda: "Windows")
    monkeypatch.setattr(control, "vigembus_installed", lambda: False)
    res = doctor.check_gamepad(True)
    assert res.status == "fail" and "ViGEmBus" in res.detail and control.VIGEMBUS_URL in res.detail + res.fix
    with pytest.raises(control.ControlUnavailable, match="ViGEmBus"):
        control.make_vgamepad()
    assert finder.attempts == []


def test_windows_with_vigembus_imports_vgamepad_with_its_installer_off(monkeypatch):
    from tmrl.tm import control

    class Vgamepad:
        class VX360Gamepad:
            def __init__(self):
                self.skip = os.environ.get("VGAMEPAD_SKIP_VIGEMBUS_INSTALL")

    monkeypatch.setattr(control.platform, "system", lambda: "Windows")
    monkeypatch.setattr(control, "vigembus_installed", lambda: True)
    monkeypatch.setitem(sys.modules, "vgamepad", Vgamepad)
    monkeypatch.delenv("VGAMEPAD_SKIP_VIGEMBUS_INSTALL", raising=False)
    assert control.make_vgamepad().skip == "true"


def test_the_original_tmrl_in_the_same_environment_is_reported(tmp_path):
    site = tmp_path / "site"
    original = site / "tmrl-0.7.1.dist-info"
    original.mkdir(parents=True)
    (original / "METADATA").write_text("Metadata-Version: 2.1\nName: tmrl\nVersion: 0.7.1\n"
                                       "Home-page: https://github.com/trackmania-rl/tmrl\n")
    res = doctor.check_original_tmrl([str(site)])
    assert res.status == "fail" and "0.7.1" in res.detail and "pip uninstall tmrl" in res.fix
    ours = tmp_path / "ours"
    (ours / "tmrl-0.1.0.dist-info").mkdir(parents=True)  # this project under its former name
    (ours / "tmrl-0.1.0.dist-info" / "METADATA").write_text(  # its README names the original in the body
        "Metadata-Version: 2.1\nName: tmrl\nVersion: 0.1.0\n\nThe original: github.com/trackmania-rl/tmrl\n")
    assert doctor.check_original_tmrl([str(ours)]).status == "pass"


def test_reward_file_of_another_map_fails_when_the_car_is_far_from_it(tmp_path):
    traj = np.c_[np.arange(100) * 0.1, np.zeros(100), np.zeros(100)]
    save_reward(traj, tmp_path / "r.npy")
    assert doctor.check_reward_file(tmp_path / "r.npy", position=(5.0, 1.0, 0.0)).status == "pass"
    res = doctor.check_reward_file(tmp_path / "r.npy", position=(500.0, 10.0, 300.0))
    assert res.status == "fail" and "another map" in res.detail and "--record-reward" in res.fix
