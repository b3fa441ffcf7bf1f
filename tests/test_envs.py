"""tmrl.envs.GenericGymEnv: Gymnasium ids, real-time ids, scaling, float32 conversion."""

from __future__ import annotations

import threading

import gymnasium
import numpy as np
import pytest
from gymnasium import spaces

import tmrl.realtime as rt
from tmrl.envs import Float64ToFloat32, GenericGymEnv, ScaleObservation, to_float32
from tmrl.errors import UserError


class _Dummy(gymnasium.Env):
    """An environment whose observation is given at construction."""

    def __init__(self, observation_space, obs):
        self.observation_space = observation_space
        self.action_space = spaces.Box(-1.0, 1.0, (1,), np.float64)
        self._obs = obs

    def reset(self, *, seed=None, options=None):
        return self._obs, {}

    def step(self, action):
        return self._obs, 0.0, False, False, {}


def test_pendulum_default_and_no_default_action():
    env = GenericGymEnv()
    try:
        assert env.spec.id == "Pendulum-v1"
        obs, _ = env.reset(seed=0)
        assert obs.shape == (3,)
        assert getattr(env, "default_action", None) is None
        obs, *_ = env.step(np.zeros(1, np.float32))
        assert env.observation_space.contains(obs)
    finally:
        env.close()


def test_obs_scale_scales_observation_and_space():
    env = GenericGymEnv("Pendulum-v1", obs_scale=0.5)
    try:
        raw = gymnasium.make("Pendulum-v1")
        o_raw, _ = raw.reset(seed=1)
        o, _ = env.reset(seed=1)
        assert np.allclose(o, o_raw * 0.5)
        assert np.allclose(env.observation_space.high, raw.observation_space.high * 0.5)
        assert env.observation_space.contains(o)
    finally:
        env.close()


def test_negative_scale_keeps_bounds_ordered():
    inner = _Dummy(spaces.Box(0.0, 2.0, (2,), np.float32), np.ones(2, np.float32))
    env = ScaleObservation(inner, -1.0)
    assert np.all(env.observation_space.low == -2.0) and np.all(env.observation_space.high == 0.0)
    o, _ = env.reset()
    assert env.observation_space.contains(o)


def test_float64_to_float32_nested():
    space = spaces.Tuple(
        (spaces.Box(-1, 1, (2,), np.float64), spaces.Dict({"a": spaces.Box(-1, 1, (3,), np.float64)}))
    )
    obs = (np.zeros(2, np.float64), {"a": np.ones(3, np.float64)})
    env = Float64ToFloat32(_Dummy(space, obs))
    o, _ = env.reset()
    assert o[0].dtype == np.float32 and o[0].shape == (2,)
    assert o[1]["a"].dtype == np.float32 and o[1]["a"].shape == (3,)
    assert env.observation_space.contains(o)
    assert env.action_space.dtype == np.float32


def test_to_float32_leaves():
    out = to_float32([1.5, 2, np.float64(3.0), "text", None, np.arange(3), True, (np.float32(1.0),)])
    assert out[0].dtype == np.float32 and out[0].shape == (1,) and out[0][0] == 1.5
    assert out[1].dtype == np.float32 and out[1][0] == 2.0
    assert out[2].dtype == np.float32
    assert out[3] == "text" and out[4] is None
    assert out[5].dtype == np.arange(3).dtype  # integer arrays untouched
    assert out[6] is True
    assert out[7][0].dtype == np.float32


def test_real_time_id_without_config_is_a_user_error():
    with pytest.raises(UserError, match="interface"):
        GenericGymEnv("real-time-gym-v1")


def test_unknown_id_is_a_user_error():
    with pytest.raises(UserError, match="Pendulum-v1"):
        GenericGymEnv("NoSuchEnv-v7")


@pytest.mark.parametrize("env_id", ["real-time-gym-v1", "tmrl/real-time-gym-ts-v1"])
def test_real_time_env_through_wrapper(env_id):
    before = set(threading.enumerate())
    cfg = rt.drone_config(fast=True, ep_max_length=3)
    env = GenericGymEnv(env_id, gym_kwargs={"config": cfg}, to_float32=True)
    try:
        assert np.array_equal(env.default_action, np.zeros(2, np.float32))
        obs, _ = env.reset(seed=0)
        assert len(obs) == 4 + cfg["act_buf_len"]
        done = False
        steps = 0
        while not done:
            obs, _, terminated, truncated, _ = env.step(env.action_space.sample())
            done = terminated or truncated
            steps += 1
            assert env.observation_space.contains(obs)
        assert steps <= 3
    finally:
        env.close()
    assert set(threading.enumerate()) == before
