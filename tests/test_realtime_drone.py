"""The simulated drone, its interface and config, and a real-clock smoke test of the environment."""

from __future__ import annotations

import subprocess
import sys
import threading
import time
from pathlib import Path

import gymnasium
import numpy as np
import pytest

import tmrl.realtime as rt
from tmrl.errors import UserError
from tmrl.realtime import DroneInterface, DummyRCDrone, drone_config

ROOT = Path(__file__).resolve().parents[1]


def _wait_for(predicate, timeout=10.0):
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if predicate():
            return True
        time.sleep(0.002)
    return False


def test_drone_moves_with_delay_and_stops_its_thread():
    before = set(threading.enumerate())
    with DummyRCDrone(
        communication_delay_min=0.002, communication_delay_max=0.004, control_sleep=0.001, seed=0
    ) as d:
        assert d.get_observation() == (0.0, 0.0)
        d.send_control(1.0, -0.5)
        assert _wait_for(lambda: d.get_observation()[0] > 0.01)
        x, y = d.get_observation()
        assert y < 0 and x > 0
        assert x <= d.position[0]  # observations lag the true position
    assert set(threading.enumerate()) == before


def test_older_commands_are_dropped():
    with DummyRCDrone(
        communication_delay_min=0.0, communication_delay_max=0.02, control_sleep=0.001, seed=1
    ) as d:
        for i in range(40):
            d.send_control(0.01 * i, 0.0)
        # once every message has arrived, the last command sent is the one applied
        assert _wait_for(lambda: d.velocity == (0.39, 0.0))
        time.sleep(0.03)
        assert d.velocity == (0.39, 0.0)


def test_velocity_norm_and_world_are_clipped():
    with DummyRCDrone(
        communication_delay_min=0.0,
        communication_delay_max=0.0,
        control_sleep=0.001,
        world_size=0.05,
        max_vel=2.0,
    ) as d:
        d.send_control(30.0, 40.0)
        assert _wait_for(lambda: d.velocity != (0.0, 0.0))
        vx, vy = d.velocity
        assert np.hypot(vx, vy) == pytest.approx(2.0) and vy / vx == pytest.approx(4 / 3)
        assert _wait_for(lambda: d.position == (0.05, 0.05))


@pytest.mark.parametrize(
    "kwargs",
    [
        {"communication_delay_min": -1},
        {"communication_delay_min": 0.05, "communication_delay_max": 0.01},
        {"control_sleep": 0},
    ],
)
def test_drone_argument_mistakes(kwargs):
    with pytest.raises(UserError):
        DummyRCDrone(**kwargs)


def test_drone_interface_spaces_reset_and_render():
    itf = DroneInterface(communication_delay_min=0.001, communication_delay_max=0.002, control_sleep=0.001)
    try:
        obs_space, act_space = itf.get_observation_space(), itf.get_action_space()
        assert act_space.contains(itf.get_default_action())
        obs, info = itf.reset(seed=5)
        assert obs_space.contains(tuple(obs)) and info == {}
        target = itf.target.copy()
        itf.reset(seed=5)
        assert np.array_equal(itf.target, target)  # seeded targets
        itf.send_control(np.array([0.5, 0.5], np.float32))
        obs, rew, terminated, info = itf.get_obs_rew_terminated_info()
        assert obs_space.contains(tuple(obs)) and rew <= 0 and isinstance(terminated, bool)
        img = itf.render()
        assert img.shape == (200, 200, 3) and img.dtype == np.uint8 and (img != 255).any()
    finally:
        itf.close()
    assert itf.rc_drone is None


def test_speed_factor_scales_commands():
    itf = DroneInterface(
        speed_factor=10.0, communication_delay_min=0.0, communication_delay_max=0.0, control_sleep=0.001
    )
    try:
        itf.reset(seed=0)
        itf.send_control(np.array([1.5, 0.0], np.float32))
        assert _wait_for(lambda: itf.rc_drone.velocity == (15.0, 0.0))  # max_vel scaled too
    finally:
        itf.close()


def test_drone_config():
    cfg = drone_config()
    assert cfg["interface"] is DroneInterface and cfg["time_step_duration"] == 0.05
    assert cfg["ep_max_length"] == 100 and cfg["reset_act_buf"] is True
    cfg = drone_config(time_step_duration=0.02, interface_kwargs={"seed": 3})
    assert cfg["start_obs_capture"] == 0.02
    assert cfg["interface_kwargs"]["seed"] == 3 and "control_sleep" in cfg["interface_kwargs"]
    fast = drone_config(fast=True)
    assert fast["time_step_duration"] == pytest.approx(0.005)
    assert fast["interface_kwargs"]["communication_delay_max"] == pytest.approx(0.005)
    assert fast["interface_kwargs"]["speed_factor"] == pytest.approx(10.0)
    with pytest.raises(UserError, match="time_step"):
        drone_config(time_step=0.1)
    # virtual time for the checker's timing, so that a loaded machine cannot fail it
    assert rt.check_realtime_interface(drone_config(fast=True), n_steps=3, clock=rt.FakeClock()) == []


@pytest.mark.parametrize("env_id", ["real-time-gym-v1", "real-time-gym-ts-v1"])
def test_real_clock_smoke(env_id):
    """The drone flown by the tutorial's controller in real time; only sanity is asserted."""
    before = set(threading.enumerate())
    env = gymnasium.make(env_id, config=drone_config(fast=True, ep_max_length=40, benchmark=True))
    try:
        obs, _ = env.reset(seed=0)
        steps, done = 0, False
        while not done:
            act = np.clip(np.concatenate((obs[2] - obs[0], obs[3] - obs[1])) * 5.0, -2.0, 2.0)
            obs, _, terminated, truncated, _ = env.step(act.astype(np.float32))
            done = terminated or truncated
            steps += 1
            assert env.observation_space.contains(obs)
        assert 1 <= steps <= 40
        bench = env.unwrapped.benchmarks()
        assert bench["time_step_duration"][0] > 0 and bench["get_obs_duration"][0] >= 0
    finally:
        env.close()
    assert set(threading.enumerate()) == before


def test_example_runs():
    out = subprocess.run(
        [sys.executable, str(ROOT / "examples" / "realtime_drone.py"), "--fast", "--episodes", "1"],
        capture_output=True,
        text=True,
        timeout=120,
        check=False,
    )
    assert out.returncode == 0, out.stderr
    assert "episode 1" in out.stdout and "time_step_duration" in out.stdout
