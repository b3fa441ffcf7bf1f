"""Tests of the built-in simulator: tracks, dynamics, rendering, interfaces, fast environments."""

from __future__ import annotations

import struct
import zlib

import gymnasium
import numpy as np
import pytest

import tmrl.sim
from tmrl.driving.compressors import (
    compress_full_sample,
    compress_lidar_progress_sample,
    compress_lidar_sample,
)
from tmrl.driving.preprocessors import (
    preprocess_full_obs,
    preprocess_lidar_obs,
    preprocess_lidar_progress_obs,
)
from tmrl.errors import UserError
from tmrl.sim.car import Car
from tmrl.sim.interfaces import (
    SimEnv,
    SimFullInterface,
    SimLidarInterface,
    SimLidarProgressInterface,
)
from tmrl.sim.race import Race, follow_centre_line
from tmrl.sim.render import BORDER, GROUND, ROAD, encode_png, track_map
from tmrl.sim.track import DEFAULT_TRACK, TRACK_NAMES, _problems, make_track, named_track, track_from_seed

# -- tracks ----------------------------------------------------------------------------------


def test_named_tracks_are_pinned_and_valid():
    lengths = {name: named_track(name).length for name in TRACK_NAMES}
    assert lengths == pytest.approx({"oval": 454.5, "classic": 617.3, "technical": 617.3}, abs=0.5)
    widths = [named_track(n).half_width for n in TRACK_NAMES]
    assert widths == sorted(widths, reverse=True)  # harder tracks are narrower
    for name in TRACK_NAMES:
        t = named_track(name)
        assert _problems(t) == []
        steps = np.linalg.norm(np.diff(t.centre, axis=0), axis=1)
        assert np.allclose(steps, 0.1, atol=1e-3)
    assert make_track(None).name == DEFAULT_TRACK


def test_seeded_tracks_are_deterministic_and_differ():
    a, b = track_from_seed(11), track_from_seed(11)
    assert np.array_equal(a.centre, b.centre)
    assert not np.array_equal(track_from_seed(12).centre[:100], a.centre[:100])
    assert make_track("11").name == "seed-11" and make_track(11) is a
    for seed in (5, 8):
        for difficulty in ("easy", "hard"):
            assert _problems(track_from_seed(seed, difficulty)) == []


def test_unknown_tracks_are_user_errors():
    with pytest.raises(UserError, match="unknown track"):
        make_track("monza")
    with pytest.raises(UserError, match="difficulty"):
        track_from_seed(1, "insane")


def test_reward_trajectory_runs_from_start_to_finish_line():
    t = named_track("oval")
    traj = t.reward_trajectory()
    assert np.array_equal(traj[0], traj[-1]) and len(traj) == t.n_points + 1


# -- dynamics --------------------------------------------------------------------------------


def drive(car: Car, action, seconds: float) -> int:
    hits = 0
    for _ in range(int(seconds / 0.0125)):
        hits += car.step(*action, 0.0125)
    return hits


def test_gas_brake_and_coasting():
    car = Car(named_track("oval"))
    drive(car, (1.0, 0.0, 0.0), 2.0)
    fast = car.state.forward_speed
    assert fast > 10.0
    drive(car, (0.0, 0.0, 0.0), 0.5)
    coasting = car.state.forward_speed
    assert 0 < fast - coasting < 2.0
    drive(car, (0.0, 1.0, 0.0), 0.5)
    assert car.state.forward_speed < coasting - 5.0
    # negative gas or brake does nothing (only the positive part of a trigger acts)
    car.reset()
    drive(car, (-1.0, -1.0, 0.0), 1.0)
    assert car.state.speed == 0.0


def test_steering_right_turns_clockwise_and_slides_at_speed():
    car = Car(named_track("oval"))
    h0 = car.state.heading
    drive(car, (0.5, 0.0, 1.0), 0.5)
    assert car.state.heading < h0
    # at speed, a full lock asks for more than the tyres give: the car slides sideways
    car.reset()
    car.state.vx, car.state.vy = 35.0 * np.cos(h0), 35.0 * np.sin(h0)
    car.step(0.0, 0.0, 1.0, 0.0125)
    car.step(0.0, 0.0, 1.0, 0.0125)
    c, s = np.cos(car.state.heading), np.sin(car.state.heading)
    lateral = -car.state.vx * s + car.state.vy * c
    assert abs(lateral) > 0.1


def test_steering_lock_shrinks_with_speed():
    slow, fast = Car(named_track("oval")), Car(named_track("oval"))
    h0 = slow.state.heading
    for car, v in ((slow, 5.0), (fast, 30.0)):
        car.state.vx, car.state.vy = v * np.cos(h0), v * np.sin(h0)
        car.step(0.0, 0.0, 1.0, 0.0125)
    # yaw per metre travelled is the path curvature: tighter at low speed
    assert (h0 - slow.state.heading) / 5.0 > 2 * (h0 - fast.state.heading) / 30.0


def test_walls_hold_the_car_and_cost_speed():
    car = Car(named_track("classic"))
    drive(car, (1.0, 0.0, 0.0), 2.0)
    limit = car.track.half_width - car.params.radius
    speed_before = car.state.speed
    hits = drive(car, (1.0, 0.0, 1.0), 1.5)
    assert hits > 0 and car.state.wall_hits == hits
    assert abs(car.state.lateral) <= limit + 1e-9
    assert car.state.speed < speed_before


def test_gear_and_rpm_follow_speed():
    car = Car(named_track("oval"))
    gears, rpms = [], []
    for _ in range(8):
        drive(car, (1.0, 0.0, 0.0), 0.6)
        gears.append(car.gear)
        rpms.append(car.rpm)
    assert gears == sorted(gears) and gears[0] >= 1 and gears[-1] >= 3
    assert all(2000.0 <= r <= 11000.0 for r in rpms)


# -- the race: a driver completes a lap, a random policy never does ---------------------------


@pytest.mark.parametrize("name", TRACK_NAMES)
def test_centre_line_driver_completes_a_lap(name):
    env = SimEnv("SIMLIDARPROGRESS", track=name, ep_max_length=2000)
    env.reset()
    total = 0.0
    for step in range(2000):
        obs, rew, terminated, truncated, info = env.step(follow_centre_line(env.race))
        total += rew
        if terminated or truncated:
            break
    assert terminated and info["lap_completed"] is True
    assert 10.0 < info["lap_time"] < 100.0
    assert info["lap_time"] == pytest.approx((step + 1) * 0.05, abs=0.05)
    track = env.race.track
    # progress reward of the whole lap (1 per 10 m) plus the finish bonus
    assert total == pytest.approx(track.length / 10.0 + 100.0, abs=1.0)
    assert obs[1][0] > 0.99


def test_random_policy_never_completes_a_lap():
    race = Race(make_track(None))
    rng = np.random.default_rng(0)
    best = 0.0
    for _ in range(200):
        race.reset()
        for _ in range(1000):
            race.advance(rng.uniform(-1.0, 1.0, 3), 0.05)
            _, terminated, info = race.score()
            assert not info["lap_completed"]
            if terminated:
                break
        best = max(best, race.progress)
    assert best < 0.1


def test_crossing_the_line_backwards_is_no_lap():
    race = Race(named_track("oval"))
    race.reset()
    race.car.state.heading += np.pi  # face backwards and drive over the line, then come back
    for _ in range(40):
        race.advance((0.6, 0.0, 0.0), 0.05)
    assert race.laps == -1
    race.car.state.heading -= np.pi
    for _ in range(60):
        race.advance((1.0, 0.0, 0.0), 0.05)
    assert race.laps == 0 and not race.finished


# -- rendering and observations --------------------------------------------------------------


def test_lidar_interface_reads_the_rendered_view():
    itf = SimLidarInterface(track="classic", img_hist_len=2)
    obs, info = itf.reset()
    view = itf.lidar_view()
    assert view.shape == (488, 958)
    assert np.array_equal(obs[1][-1], itf.lidar.measure(view))
    # at the start, the car is in the middle of a 12 m road: the side beams hit the borders about
    # 6 m - 2.4 m (the beams' first 20 px at 0.12 m/px) away, the forward beam goes much farther
    lateral = (obs[1][-1][0] + 20) * 0.12, (obs[1][-1][18] + 20) * 0.12
    assert lateral == pytest.approx((6.0, 6.0), abs=0.5)
    assert obs[1][-1][9] > 100


def test_full_view_has_black_borders_and_dark_ground():
    itf = SimFullInterface(track="classic")
    obs, _ = itf.reset()
    img = obs[3][-1]
    assert img.dtype == np.uint8 and img.shape == (64, 64)
    values = set(np.unique(img).tolist())
    assert {ROAD, BORDER, GROUND} <= values
    row = img[40]  # a row ahead of the car: ground, border, road, ..., road, border, ground
    assert row[0] == GROUND and row[32] in (ROAD, 220) and BORDER in row[:32] and BORDER in row[32:]
    tmap = track_map(itf.track)
    assert tmap.image.dtype == np.uint8


@pytest.mark.parametrize("env_id", sorted(tmrl.sim.ENV_IDS))
def test_gymnasium_ids_and_spaces(env_id):
    env = gymnasium.make(f"tmrl.sim:{env_id}", img_hist_len=3, act_buf_len=2)
    obs, info = env.reset(seed=1)
    assert env.observation_space.contains(obs)
    assert np.array_equal(obs[-1], np.zeros(3)) and np.array_equal(obs[-2], np.zeros(3))
    a1 = np.array([1.0, 0.0, 0.25], dtype=np.float32)
    a2 = np.array([0.5, 0.0, -0.5], dtype=np.float32)
    env.step(a1)
    obs, rew, terminated, truncated, info = env.step(a2)
    assert env.observation_space.contains(obs)
    assert np.array_equal(obs[-2], a1) and np.array_equal(obs[-1], a2)  # oldest first
    assert obs[0][0] > 0  # moving (km/h)
    assert not terminated and not truncated and info["lap_completed"] is False
    env.close()


def test_truncation_after_ep_max_length():
    env = SimEnv("SIMLIDAR", ep_max_length=5, img_hist_len=1)
    env.reset()
    flags = [env.step(np.array([1.0, 0.0, 0.0]))[3] for _ in range(5)]
    assert flags == [False] * 4 + [True]
    with pytest.raises(UserError, match="unknown simulator interface"):
        SimEnv("SIMSOMETHING")


def test_observation_spaces_match_trackmania():
    lidar = SimLidarInterface(img_hist_len=4).get_observation_space()
    assert [s.shape for s in lidar.spaces] == [(1,), (4, 19)]
    prog = SimLidarProgressInterface(img_hist_len=4).get_observation_space()
    assert [s.shape for s in prog.spaces] == [(1,), (1,), (4, 19)]
    assert prog.spaces[1].high[0] == 1.0
    full = SimFullInterface(img_hist_len=4).get_observation_space()
    assert [s.shape for s in full.spaces] == [(1,), (1,), (1,), (4, 64, 64)]
    assert full.spaces[3].dtype == np.uint8
    assert SimLidarInterface().get_action_space().shape == (3,)


def test_preprocessors_and_compressors_keep_only_the_newest_frame():
    env = SimEnv("SIMLIDARPROGRESS", img_hist_len=4)
    env.reset()
    obs, rew, te, tr, info = env.step(np.array([1.0, 0.0, 0.0]))
    pre = preprocess_lidar_progress_obs(obs)
    assert pre[2].shape == (76,)
    act, small, r, *_ = compress_lidar_progress_sample(np.ones(3), pre, rew, te, tr, info)
    assert len(small) == 3 and np.array_equal(small[2], obs[2][-1]) and isinstance(r, np.float32)
    lid = SimEnv("SIMLIDAR", img_hist_len=4)
    obs = lid.reset()[0]
    _, small, *_ = compress_lidar_sample(None, preprocess_lidar_obs(obs), 0.0, False, False, {})
    assert len(small) == 2 and np.array_equal(small[1], obs[1][-1])
    full = SimEnv("SIMFULL", img_hist_len=4)
    obs = full.reset()[0]
    pre = preprocess_full_obs(obs)
    assert pre[3].dtype == np.float32 and pre[3].max() < 1.0
    _, small, *_ = compress_full_sample(None, pre, 0.0, False, False, {})
    assert small[3].dtype == np.uint8 and np.array_equal(small[3], obs[3][-1])
    assert len(small) == 4


# -- real time --------------------------------------------------------------------------------


def test_real_time_environment_drives_the_sim():
    from tmrl.realtime import DEFAULT_CONFIG_DICT, RealTimeEnv, check_realtime_interface

    config = dict(DEFAULT_CONFIG_DICT, interface=SimLidarInterface, interface_kwargs={"img_hist_len": 2},
                  time_step_duration=0.02, start_obs_capture=0.02, act_buf_len=2, ep_max_length=30)
    env = RealTimeEnv(config)
    try:
        obs, _ = env.reset()
        assert env.observation_space.contains(obs)
        total = 0.0
        for _ in range(20):
            obs, rew, terminated, truncated, info = env.step(np.array([1.0, 0.0, 0.0], dtype=np.float32))
            total += rew
        race = env.unwrapped.interface.race if hasattr(env.unwrapped, "interface") else None
        assert obs[0][0] > 5.0  # km/h after ~0.4 s of full gas
        assert total > 0.0
        if race is not None:
            assert race.time == pytest.approx(0.4, abs=0.2)
    finally:
        env.close()
    problems = check_realtime_interface(dict(config, interface=SimFullInterface, interface_kwargs={}), n_steps=3)
    assert problems == []


def test_wait_freezes_the_car():
    now = [0.0]
    itf = SimLidarInterface(img_hist_len=1, clock=lambda: now[0])
    itf.reset()
    itf.send_control(np.array([1.0, 0.0, 0.0]))
    now[0] = 1.0
    itf.get_obs_rew_terminated_info()
    moved = itf.race.car.state.speed
    assert moved > 5.0 and itf.race.time == pytest.approx(1.0, abs=0.02)
    itf.wait()
    now[0] = 5.0
    itf.get_obs_rew_terminated_info()
    assert itf.race.time == pytest.approx(1.0, abs=0.02)


def test_png_encoder_writes_valid_files(tmp_path):
    from tmrl.sim.render import write_png

    img = (np.arange(12 * 7) % 256).astype(np.uint8).reshape(7, 12)
    data = encode_png(img)
    assert data[:8] == b"\x89PNG\r\n\x1a\n"
    w, h = struct.unpack(">II", data[16:24])
    assert (w, h) == (12, 7)
    idat_len = struct.unpack(">I", data[33:37])[0]
    raw = zlib.decompress(data[41:41 + idat_len])
    rows = np.frombuffer(raw, dtype=np.uint8).reshape(7, 13)
    assert np.array_equal(rows[:, 1:], img) and not rows[:, 0].any()
    write_png(tmp_path / "x.png", np.stack([img] * 3, axis=-1))
    assert (tmp_path / "x.png").read_bytes()[:4] == b"\x89PNG"


# -- building from a config ------------------------------------------------------------------


def sim_config(name: str) -> dict:
    return {"ENV": {"RTGYM_INTERFACE": name, "IMG_HIST_LEN": 2, "IMG_WIDTH": 48, "IMG_HEIGHT": 40,
                    "RTGYM_CONFIG": {"time_step_duration": 0.05, "act_buf_len": 3, "ep_max_length": 7,
                                     "interface_kwargs": {"track": "oval"}},
                    "REWARD_CONFIG": {"END_OF_TRACK": 50.0}}}


def test_fast_env_and_realtime_config_from_a_config():
    from tmrl.sim.interfaces import fast_env, pipeline_parts, realtime_config

    env = fast_env(sim_config("SIMFULL"))
    obs, _ = env.reset()
    assert obs[3].shape == (2, 40, 48) and len(obs) == 4 + 3
    assert env.race.track.name == "oval" and env.race.reward.end_of_track == 50.0
    truncated = [env.step(np.zeros(3))[3] for _ in range(7)]
    assert truncated[-1] and not any(truncated[:-1])
    rt = realtime_config(sim_config("SIMLIDAR"))
    assert rt["interface"] is SimLidarInterface and rt["act_buf_len"] == 3
    assert rt["interface_kwargs"]["track"] == "oval" and rt["interface_kwargs"]["img_hist_len"] == 2
    parts = pipeline_parts("SIMLIDARPROGRESS")
    assert parts["memory_cls"].__name__ == "LidarProgressMemory"
    for name in ("SIMLIDAR", "SIMFULL", "TM20LIDARPROGRESS"):
        parts = pipeline_parts(name)
        e = SimEnv(name if name.startswith("SIM") else "SIMLIDARPROGRESS", img_hist_len=2)
        assert type(parts["model_cls"](e.observation_space, e.action_space).actor) is parts["actor_cls"]
    with pytest.raises(UserError, match="RTGYM_INTERFACE"):
        fast_env(sim_config("TM20FULL"))


def test_trajectory_picture_and_learning_curve():
    from tmrl.sim.charts import lap_image, learning_curve_image
    from tmrl.sim.render import draw_trajectory

    env = SimEnv("SIMLIDAR", track="oval", img_hist_len=1)
    env.reset()
    path = [env.race.car.state.position]
    for _ in range(200):
        env.step(follow_centre_line(env.race))
        path.append(env.race.car.state.position)
    tmap = track_map(env.race.track)
    img = draw_trajectory(tmap, np.array(path), max_size=300)
    assert img.shape[2] == 3 and max(img.shape[:2]) <= 300
    red = (img[:, :, 0] == 230) & (img[:, :, 1] == 40)
    assert red.sum() > 50  # the path is drawn
    px = tmap.to_topdown_pixels(np.array(path[-1:]), 300)[0]
    assert red[max(px[0] - 2, 0):px[0] + 3, max(px[1] - 2, 0):px[1] + 3].any()  # where the car ended
    lap = lap_image(env.race.track, np.array(path), "BEST LAP", ["LAP TIME 12.34 S"])
    assert ((lap[:, :, 0] == 230) & (lap[:, :, 1] == 40)).sum() > 50
    header, footer = lap[:40], lap[-20:]
    assert (header.sum(axis=2) == 0).sum() > 100 and (footer.sum(axis=2) == 0).sum() > 50  # title, scale bar
    chart = learning_curve_image([0, 1, 3, 2, 5, 4, 8, 7, 9, 12.0] * 3, "TITLE", ["A KEY FIGURE"])
    assert chart.shape == (480, 800, 3)
    mean = (chart[:, :, 0] == 20) & (chart[:, :, 1] == 60) & (chart[:, :, 2] == 180)
    rows, cols = np.nonzero(mean[100:])  # below the legend's sample: the curve itself
    assert len(rows) > 100
    assert encode_png(chart)[:4] == b"\x89PNG"


def test_chart_text_is_drawn_with_a_glyph_per_character():
    from tmrl.sim.charts import _FONT, _render, draw_label, text_width

    assert all(m.shape == (7, 5) for m in _FONT.values()) and len({m.tobytes() for m in _FONT.values()}) == len(_FONT)
    assert _render("lap", 1).shape == (7, 18) and (_render("lap", 1) == _render("LAP", 1)).all()
    assert not _render("~", 1).any()  # unknown characters are spaces
    img = np.full((40, 200, 3), 255, dtype=np.uint8)
    draw_label(img, "RETURN", 2, 2, scale=2)
    ink = np.nonzero(img.sum(axis=2) == 0)
    assert ink[1].max() < 2 + text_width("RETURN") and ink[0].max() < 2 + 14
    tall = np.full((120, 40, 3), 255, dtype=np.uint8)
    draw_label(tall, "RETURN", 90, 2, vertical=True)  # a y-axis title: written upwards
    rows, cols = np.nonzero(tall.sum(axis=2) == 0)
    assert rows.max() - rows.min() > cols.max() - cols.min()


# -- the demo ---------------------------------------------------------------------------------


def _png_size(path) -> tuple[int, int]:
    data = path.read_bytes()
    assert data[:8] == b"\x89PNG\r\n\x1a\n" and data[12:16] == b"IHDR"
    w, h = struct.unpack(">II", data[16:24])
    idat_len = struct.unpack(">I", data[33:37])[0]
    zlib.decompress(data[41:41 + idat_len])  # the pixel data is a valid zlib stream
    return w, h


@pytest.mark.timeout(240)
def test_demo_runs_end_to_end_with_a_tiny_budget(tmp_path):
    import os
    import subprocess
    import sys

    out = tmp_path / "demo"
    proc = subprocess.run(
        [sys.executable, "-m", "tmrl", "--demo", "--minutes", "0.4", "--start-training", "100",
         "--track", "oval", "--out", str(out)],
        capture_output=True, text=True, timeout=220, env=dict(os.environ, OMP_NUM_THREADS="1"),
    )
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert "updates/s" in proc.stdout and "samples/s" in proc.stdout
    assert "tmrl demo finished" in proc.stdout
    import torch

    expected = "cuda" if torch.cuda.is_available() else "cpu"  # --device auto, the default
    assert f"trainer on {expected})" in proc.stdout.splitlines()[0], proc.stdout.splitlines()[0]
    w, h = _png_size(out / "learning_curve.png")
    assert (w, h) == (800, 480)
    w, h = _png_size(out / "best_lap.png")
    assert w > 100 and h > 100
    from safetensors.torch import load_file

    weights = load_file(str(out / "weights.safetensors"))
    assert any(k.startswith("net.") for k in weights)
    # the role logs say what each role did, not just a warning
    trainer_log = (out / "logs" / "trainer.log").read_text()
    assert "training starts" in trainer_log and "INFO" in trainer_log
    assert "train episode 0:" in (out / "logs" / "worker.log").read_text()
    # the demo keeps its files in its run folder: no TrackMania config.json in the data folder
    assert not (tmp_path / "TmrlData" / "config" / "config.json").exists()


def test_check_environment_writes_what_the_policy_sees(tmp_path):
    import io

    from tmrl.sim.tools import check_environment

    for name in ("SIMLIDAR", "SIMFULL"):
        cfg = sim_config(name)
        cfg["ENV"]["RTGYM_CONFIG"]["ep_max_length"] = 1000
        text = io.StringIO()
        assert check_environment(cfg, steps=25, out_dir=tmp_path / name, every=10, out=text) == 0
        files = sorted((tmp_path / name).glob("*.png"))
        assert [f.name for f in files] == ["step_000010.png", "step_000020.png", "step_000025.png"]
        w, h = _png_size(files[0])
        assert (w, h) == ((958, 488) if name == "SIMLIDAR" else (2 * 48 * 4, 40 * 4))
        assert "reward" in text.getvalue()


def test_interface_kwargs_are_checked():
    from tmrl.sim.interfaces import interface_kwargs

    cfg = sim_config("SIMLIDAR")
    cfg["ENV"]["RTGYM_CONFIG"]["interface_kwargs"] = {"save_replays": False, "lidar_scale": 0.1}
    assert interface_kwargs(cfg)["lidar_scale"] == 0.1 and interface_kwargs(cfg)["save_replays"] is False
    cfg["ENV"]["RTGYM_CONFIG"]["interface_kwargs"] = {"view_width": 20.0}
    with pytest.raises(UserError, match="view_width"):
        interface_kwargs(cfg)


def test_demo_reads_the_environment_from_a_config(tmp_path):
    import json

    from tmrl.sim import demo

    path = tmp_path / "config.json"
    path.write_text(json.dumps({"ENV": {"RTGYM_INTERFACE": "SIMLIDARPROGRESS", "IMG_HIST_LEN": 2,
                                        "RTGYM_CONFIG": {"act_buf_len": 3, "interface_kwargs": {"track": "oval"}}}}))
    env = demo._demo_config("SIMLIDARPROGRESS", "technical", str(path))["ENV"]
    assert env["IMG_HIST_LEN"] == 2 and env["RTGYM_CONFIG"]["act_buf_len"] == 3
    assert env["RTGYM_CONFIG"]["interface_kwargs"]["track"] == "technical"
    path.write_text(json.dumps({"ENV": {"RTGYM_INTERFACE": "TM20FULL"}}))
    with pytest.raises(UserError, match="SIMLIDAR"):
        demo.main(["--config", str(path), "--minutes", "0.1"])
    with pytest.raises(UserError, match="unknown track"):
        demo.main(["--track", "nowhere"])


@pytest.mark.parametrize("args, expected", [
    (["--minutes", "-1"], "argument --minutes: must be above 0, got -1"),
    (["--minutes", "0"], "argument --minutes: must be above 0, got 0"),
    (["--minutes", "soon"], "argument --minutes: 'soon' is not a number"),
    (["--steps", "-5"], "argument --steps: must be at least 0, got -5"),
    (["--start-training", "0"], "argument --start-training: must be at least 1, got 0"),
])
def test_demo_refuses_budgets_that_make_no_sense(tmp_path, monkeypatch, args, expected):
    from tmrl.sim import demo

    monkeypatch.chdir(tmp_path)
    with pytest.raises(UserError) as err:
        demo.main(args)
    assert str(err.value) == expected
    assert list(tmp_path.iterdir()) == []  # nothing was created


@pytest.mark.parametrize("realtime", [False, True])
@pytest.mark.parametrize("algorithm", ["SAC", "DROQ"])
def test_demo_trains_the_chosen_agent_and_spends_the_idle_real_time_trainer(tmp_path, algorithm, realtime):
    import json

    from tmrl.algorithms import agent_class
    from tmrl.driving.models import lidar_model_cls
    from tmrl.sim import demo

    saved = dict(demo.DEMO_SETTINGS)
    try:
        demo.DEMO_SETTINGS["algorithm"] = algorithm
        training = demo._training_cls("SIMLIDAR", "oval", tmp_path, realtime)
    finally:
        demo.DEMO_SETTINGS.clear()
        demo.DEMO_SETTINGS.update(saved)
    ratio = training.keywords["max_training_steps_per_env_step"]
    # real time: the clock sets the pace and the trainer does several updates per sample
    assert ratio == (saved["realtime_max_training_steps_per_env_step"] if realtime
                     else saved["max_training_steps_per_env_step"])
    assert saved["realtime_max_training_steps_per_env_step"] > saved["max_training_steps_per_env_step"]
    env = demo._make_env("SIMLIDAR", "oval")
    agent = training.keywords["training_agent_cls"](env.observation_space, env.action_space, "cpu")
    assert isinstance(agent, agent_class(algorithm)) and isinstance(agent.model, lidar_model_cls(algorithm))
    # real time: tmrl's fixed entropy coefficient (a learned one falls back at 4 updates per sample)
    mode = "realtime_" if realtime else ""
    assert (float(agent.alpha), agent.learn_entropy_coef) == (saved[mode + "alpha"], saved[mode + "learn_entropy_coef"])
    assert saved["realtime_learn_entropy_coef"] is False and saved["learn_entropy_coef"] is True
    memory = training.keywords["memory_cls"](device="cpu", nb_steps=1, batch_size=8)
    parts = demo._parts("SIMLIDAR")
    from tmrl.networking import RolloutWorker

    worker = RolloutWorker(env_cls=lambda: demo._make_env("SIMLIDAR", "oval"), actor_module_cls=parts["actor_cls"],
                           sample_compressor=parts["sample_compressor"], obs_preprocessor=parts["obs_preprocessor"],
                           standalone=True, max_samples_per_episode=300, model_path=str(tmp_path / "w.tmod"))
    worker.collect_train_episode(300)
    memory.append(worker.buffer)
    agent.train(memory.sample())
    assert json.loads((tmp_path / "trainer.json").read_text())["updates"] >= 1


def test_demo_refuses_an_agent_without_an_image_model(tmp_path, monkeypatch):
    from tmrl.sim import demo

    monkeypatch.chdir(tmp_path)
    with pytest.raises(UserError, match="--algorithm DROQ trains on lidar observations only"):
        demo.main(["--interface", "SIMFULL", "--algorithm", "droq"])
    assert list(tmp_path.iterdir()) == []


@pytest.mark.posix
def test_demo_roles_stop_on_sigint_even_when_started_with_sigint_ignored(tmp_path):
    # `nohup python -m tmrl --demo &` starts the demo with SIGINT ignored, which its roles inherit;
    # the parent stops them with SIGINT, so they must listen to it anyway.
    import os
    import signal
    import socket
    import subprocess
    import sys

    from tmrl.sim import demo

    port = demo._free_port()
    proc = subprocess.Popen(
        [sys.executable, "-m", "tmrl.sim.demo", "--role", "server", "--interface", "SIMLIDAR", "--track", "oval",
         "--workdir", str(tmp_path), "--port", str(port)],
        env=dict(os.environ, TMRL_DEMO_PASSWORD="x" * 16, TMRL_DATA=str(tmp_path / "data")),
        preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_IGN),
    )
    try:
        demo._wait_listening(port, 60.0, proc)
        proc.send_signal(signal.SIGINT)
        assert proc.wait(timeout=30) == 0
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    with socket.socket() as s:  # the port is free again
        s.bind(("127.0.0.1", port))


def test_demo_in_real_time_on_a_gpu_trains_the_benchmark_s_recommendation(tmp_path, monkeypatch):
    from bench.track_learning import DEMO_OVERRIDES, VARIANTS
    from tmrl.algorithms import REDQSACAgent
    from tmrl.sim import demo

    gpu = demo.GPU_REALTIME_SETTINGS
    # what the demo measured its setting from: the benchmark's REDQSAC-UTD8-CAP-R250
    assert VARIANTS["REDQSAC-UTD8-CAP-R250"] == (gpu["algorithm"], "demo", gpu["realtime_max_training_steps_per_env_step"])
    assert DEMO_OVERRIDES["REDQSAC-UTD8-CAP-R250"] == {"start_steps": gpu["start_training"], "policy_every": 1,
                                                      "alpha_max": gpu["alpha_max"]}
    # when it applies: real time, lidar, a CUDA trainer, no agent chosen; what the user gives wins
    assert demo.demo_setting("SIMLIDAR", True, "cuda", None, None) == ("REDQSAC", 250, "gpu")
    assert demo.demo_setting("SIMLIDARPROGRESS", True, "cuda:1", None, 400) == ("REDQSAC", 400, "gpu")
    assert demo.demo_setting("SIMLIDAR", True, "cuda", "SAC", None) == ("SAC", 1000, None)
    assert demo.demo_setting("SIMLIDAR", True, "mps", None, None) == ("SAC", 1000, None)
    assert demo.demo_setting("SIMLIDAR", True, "cpu", None, None) == ("SAC", 250, "sac-w128")
    assert demo.demo_setting("SIMLIDAR", False, "cuda", None, None) == ("SAC", 1000, None)
    assert demo.demo_setting("SIMFULL", True, "cuda", None, None) == ("SAC", 1000, None)
    # the parent hands it to its roles, and a role applies it before it builds the trainer
    args = demo._parse(["--realtime"])
    args.interface, args.track, args.algorithm, args.start_training = "SIMLIDAR", "oval", "REDQSAC", 250
    cmd = demo._role_command("trainer", args, tmp_path, 1234, "cuda", "gpu")
    assert cmd[-2:] == ["--setting", "gpu"] and "--setting" not in demo._role_command("trainer", args, tmp_path, 1,
                                                                                        "cpu", None)
    seen = {}
    monkeypatch.setattr(demo, "_run_role", lambda *a: seen.update(settings=dict(demo.DEMO_SETTINGS), args=a))
    saved = dict(demo.DEMO_SETTINGS)
    try:
        assert demo._role_main(demo._parse(cmd[3:] + ["--port", "1234"])) == 0
        training = demo._training_cls("SIMLIDAR", "oval", tmp_path, realtime=True)
    finally:
        demo.DEMO_SETTINGS.clear()
        demo.DEMO_SETTINGS.update(saved)
    assert seen["settings"]["algorithm"] == "REDQSAC" and seen["settings"]["start_training"] == 250
    assert seen["args"][-1] == "cuda" and seen["args"][-2] is True  # device, realtime
    assert training.keywords["max_training_steps_per_env_step"] == 8.0
    assert training.keywords["start_training"] == 250
    env = demo._make_env("SIMLIDAR", "oval")
    agent = training.keywords["training_agent_cls"](env.observation_space, env.action_space, "cpu")
    assert isinstance(agent, REDQSACAgent) and agent.q_updates_per_policy_update == 1
    assert agent.learn_entropy_coef and float(agent.alpha) == pytest.approx(0.2) and agent.alpha_max == 0.01
    # and the demo's own setting is left as it was
    assert "alpha_max" not in demo.DEMO_SETTINGS and demo.DEMO_SETTINGS["algorithm"] == "SAC"


def test_demo_in_real_time_on_a_cpu_trains_sac_w128_and_bro_s_setting_matches_the_benchmark(tmp_path, monkeypatch):
    """On a CPU the narrow SAC lapped first in real time, so it is the default there (the fast
    mode, images and ``--algorithm`` keep the demo's SAC); BRO's setting, kept for ``--setting
    bro-cpu``, is the benchmark's BRO-W128-UTD8-CAP-R250."""
    from bench.track_learning import DEMO_OVERRIDES, VARIANTS
    from tmrl.algorithms import agent_class
    from tmrl.sim import demo

    assert demo.demo_setting("SIMLIDAR", True, "cpu", None, None) == ("SAC", 250, "sac-w128")
    assert demo.demo_setting("SIMLIDARPROGRESS", True, "cpu", None, None)[2] == "sac-w128"
    assert demo.demo_setting("SIMLIDAR", True, "cpu", "SAC", None) == ("SAC", 1000, None)
    assert demo.demo_setting("SIMLIDAR", False, "cpu", None, None) == ("SAC", 1000, None)
    assert demo.demo_setting("SIMFULL", True, "cpu", None, None) == ("SAC", 1000, None)
    bro = demo.CPU_REALTIME_SETTINGS
    label = bro["label"]
    assert VARIANTS[label] == (bro["algorithm"], "demo", bro["realtime_max_training_steps_per_env_step"])
    assert DEMO_OVERRIDES[label].get("start_steps") == bro["start_training"]
    assert DEMO_OVERRIDES[label].get("alpha_max") == bro["alpha_max"]
    assert DEMO_OVERRIDES[label].get("agent", {}) == bro.get("agent_kwargs", {})
    args = demo._parse(["--realtime"])
    args.interface, args.track, args.algorithm, args.start_training = "SIMLIDAR", "oval", bro["algorithm"], 250
    cmd = demo._role_command("trainer", args, tmp_path, 1234, "cpu", "bro-cpu")
    seen = {}
    monkeypatch.setattr(demo, "_run_role", lambda *a: seen.update(settings=dict(demo.DEMO_SETTINGS)))
    saved = dict(demo.DEMO_SETTINGS)
    try:
        assert demo._role_main(demo._parse(cmd[3:] + ["--port", "1234"])) == 0
        training = demo._training_cls("SIMLIDAR", "oval", tmp_path, realtime=True)
    finally:
        demo.DEMO_SETTINGS.clear()
        demo.DEMO_SETTINGS.update(saved)
    assert seen["settings"]["algorithm"] == bro["algorithm"] and seen["settings"]["start_training"] == 250
    assert training.keywords["max_training_steps_per_env_step"] == bro["realtime_max_training_steps_per_env_step"]
    env = demo._make_env("SIMLIDAR", "oval")
    agent = training.keywords["training_agent_cls"](env.observation_space, env.action_space, "cpu")
    assert isinstance(agent, agent_class(bro["algorithm"])) and agent.alpha_max == bro["alpha_max"]
    assert agent.learn_entropy_coef and float(agent.alpha) == pytest.approx(bro["realtime_alpha"])
    for key, value in bro.get("agent_kwargs", {}).items():
        assert getattr(agent, key) == value


def test_an_explicit_setting_is_trained_whatever_the_device_and_refused_where_it_cannot_apply():
    from tmrl.sim import demo

    assert demo.demo_setting("SIMLIDAR", True, "cpu", None, None, "sac-w128") == ("SAC", 250, "sac-w128")
    assert demo.demo_setting("SIMLIDAR", True, "cuda", None, 400, "bro-cpu") == ("BRO", 400, "bro-cpu")
    for bad in [("SIMLIDAR", False, "cpu", None, None, "sac-w128"),  # fast mode
                ("SIMLIDAR", True, "cpu", "SAC", None, "sac-w128"),  # an agent of its own
                ("SIMFULL", True, "cpu", None, None, "sac-w128")]:  # images
        with pytest.raises(UserError, match="--setting sac-w128"):
            demo.demo_setting(*bad)


def test_a_setting_s_narrower_network_is_the_trainer_s_and_the_worker_s(tmp_path):
    """``sac-w128``: the trainer's actor and critics are 128 wide, and the worker builds the same
    actor, so it loads the trainer's weights (a worker of the default width would refuse them)."""
    import torch

    from bench.track_learning import DEMO_OVERRIDES, VARIANTS
    from tmrl.sim import demo

    setting = demo.REALTIME_SETTINGS["sac-w128"]
    # what it was measured as in fast mode: the benchmark's variant of that label
    assert VARIANTS[setting["label"]] == ("SAC", "demo", setting["realtime_max_training_steps_per_env_step"])
    assert DEMO_OVERRIDES[setting["label"]] == {"start_steps": setting["start_training"], "alpha_max": setting["alpha_max"],
                                                "hidden_sizes": setting["hidden_sizes"]}
    saved = dict(demo.DEMO_SETTINGS)
    try:
        demo.DEMO_SETTINGS.update(setting)
        training = demo._training_cls("SIMLIDAR", "oval", tmp_path, realtime=True)
        actor_cls = demo._worker_actor_cls("SIMLIDAR")
    finally:
        demo.DEMO_SETTINGS.clear()
        demo.DEMO_SETTINGS.update(saved)
    env = demo._make_env("SIMLIDAR", "oval")
    spaces = (env.observation_space, env.action_space)
    agent = training.keywords["training_agent_cls"](*spaces, "cpu")
    assert training.keywords["max_training_steps_per_env_step"] == 8.0
    widths = {m.out_features for m in agent.model.modules() if isinstance(m, torch.nn.Linear) and m.out_features > 3}
    assert widths == {128}
    worker_actor = actor_cls(*spaces)
    worker_actor.load_state_dict(agent.get_actor().state_dict())  # same shapes
    with pytest.raises(RuntimeError, match="size mismatch"):
        demo._parts("SIMLIDAR")["actor_cls"](*spaces).load_state_dict(agent.get_actor().state_dict())
