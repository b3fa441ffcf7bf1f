"""Tests of tmrl.driving.memories: histories and action buffers rebuilt by index, against
hand-built episodes across resets and against what the simulator's environments really returned."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from tmrl.driving.compressors import (
    compress_full_sample,
    compress_lidar_progress_sample,
    compress_lidar_sample,
)
from tmrl.driving.memories import ImageMemory, LidarMemory, LidarProgressMemory
from tmrl.driving.preprocessors import (
    preprocess_full_obs,
    preprocess_lidar_obs,
    preprocess_lidar_progress_obs,
)
from tmrl.errors import UserError

DEFAULT = np.zeros(3, dtype=np.float32)


def buffer(samples, sources=None):
    return SimpleNamespace(memory=list(samples), sources=sources)


def image_episode(ep: int, n: int):
    """Samples of one episode: image pixels = 10 * ep + step, action = [ep, step, 0]."""
    out = []
    for step in range(n):
        act = DEFAULT if step == 0 else np.array([ep, step, 0], dtype=np.float32)
        img = np.full((8, 8), 10 * ep + step, dtype=np.uint8)
        obs = (np.float32([step]), np.float32([1]), np.float32([2]), img)
        out.append((act, obs, float(step), False, step == n - 1, {}))
    return out


def test_image_histories_and_action_buffers_across_resets():
    mem = ImageMemory(hist_len=3, act_buf_len=2, memory_size=100, batch_size=4)
    mem.append_buffer(buffer(image_episode(1, 4) + image_episode(2, 3)))
    # slots 0..3 episode 1, 4..6 episode 2; transitions: 1,2,3 and 5,6
    assert list(mem.valid_slots()) == [1, 2, 3, 5, 6]
    prev_obs, act, rew, new_obs, terminated, truncated, _ = mem.get_transition(5)
    # first transition of episode 2: its previous observation is the reset frame repeated,
    # nothing of episode 1 leaks in
    assert np.allclose(prev_obs[3] * 256, [[[20]], [[20]], [[20]]])
    assert np.allclose(new_obs[3][:, 0, 0] * 256, [20, 20, 21])
    assert new_obs[3].dtype == np.float32 and new_obs[3].shape == (3, 8, 8)
    assert np.array_equal(act, [2, 1, 0]) and rew == 1.0
    # action buffers: reset's default action repeated before the episode starts
    assert np.array_equal(prev_obs[4], DEFAULT) and np.array_equal(prev_obs[5], DEFAULT)
    assert np.array_equal(new_obs[4], DEFAULT) and np.array_equal(new_obs[5], [2, 1, 0])
    # last transition of episode 1: full histories
    prev_obs, act, rew, new_obs, terminated, truncated, _ = mem.get_transition(3)
    assert np.allclose(prev_obs[3][:, 0, 0] * 256, [10, 11, 12])
    assert np.allclose(new_obs[3][:, 0, 0] * 256, [11, 12, 13])
    assert np.array_equal(new_obs[4], [1, 2, 0]) and np.array_equal(new_obs[5], [1, 3, 0])
    assert truncated and not terminated
    assert float(new_obs[0][0]) == 3.0


def test_batches_are_tensors_in_the_policy_layout():
    mem = ImageMemory(hist_len=4, act_buf_len=2, memory_size=50, batch_size=6)
    mem.append_buffer(buffer(image_episode(1, 10)))
    o, a, r, o2, d, t = mem.sample()
    assert o[3].shape == (6, 4, 8, 8) and str(o[3].dtype) == "torch.float32"
    assert a.shape == (6, 3) and r.shape == (6,) and len(o) == 6
    # one stored byte per pixel, whatever the history length
    assert mem.obs_leaf(3).dtype == np.uint8 and mem.obs_leaf(3).shape == (50, 8, 8)


def test_interleaved_workers_do_not_mix():
    a = image_episode(1, 4)
    b = image_episode(2, 4)
    samples = [s for pair in zip(a, b) for s in pair]
    mem = ImageMemory(hist_len=3, act_buf_len=1, memory_size=100)
    mem.append_buffer(buffer(samples, sources=[0, 1] * 4))
    for slot in mem.valid_slots():
        prev_obs, _, _, new_obs, *_ = mem.get_transition(int(slot))
        episodes = {int(v) // 10 for v in np.round(np.concatenate([prev_obs[3][:, 0, 0], new_obs[3][:, 0, 0]]) * 256)}
        assert len(episodes) == 1


def test_overwritten_history_is_never_sampled():
    mem = ImageMemory(hist_len=3, act_buf_len=1, memory_size=5, batch_size=32)
    mem.append_buffer(buffer(image_episode(1, 8)))  # slots hold samples 3..7
    slots = mem.sample_indices()
    for slot in np.unique(slots):
        _, _, _, new_obs, *_ = mem.get_transition(int(slot))
        # the history of the new observation only uses samples still in memory (>= 3)
        assert np.all(np.round(new_obs[3][:, 0, 0] * 256) >= 13)


def lidar_episode(n: int, progress: bool):
    out = []
    for step in range(n):
        act = DEFAULT if step == 0 else np.full(3, step / 10, dtype=np.float32)
        lidar = np.full(19, float(step), dtype=np.float32)
        obs = (np.float32([step]), np.float32([step / n]), lidar) if progress else (np.float32([step]), lidar)
        out.append((act, obs, 0.5, step == n - 1, False, {}))
    return out


@pytest.mark.parametrize("progress", [False, True])
def test_lidar_histories_are_flattened(progress):
    cls = LidarProgressMemory if progress else LidarMemory
    mem = cls(hist_len=4, act_buf_len=2, memory_size=100)
    mem.append_buffer(buffer(lidar_episode(6, progress) + lidar_episode(3, progress)))
    k = 2 if progress else 1
    _, _, _, new_obs, terminated, _, _ = mem.get_transition(5)
    assert new_obs[k].shape == (76,)
    assert np.array_equal(new_obs[k].reshape(4, 19)[:, 0], [2, 3, 4, 5])
    assert terminated
    prev_obs, _, _, new_obs, *_ = mem.get_transition(7)  # second episode, first transition
    assert np.array_equal(prev_obs[k].reshape(4, 19)[:, 0], [0, 0, 0, 0])
    assert np.array_equal(new_obs[k].reshape(4, 19)[:, 0], [0, 0, 0, 1])


def test_mismatched_compressor_is_a_user_error():
    mem = ImageMemory(hist_len=2, act_buf_len=1, memory_size=10)
    mem.append_buffer(buffer(lidar_episode(3, False)))  # two stored elements, no frame at index 3
    with pytest.raises(UserError, match="compressor"):
        mem.get_transition(1)
    with pytest.raises(UserError, match="IMG_HIST_LEN"):
        LidarMemory(hist_len=0)


@pytest.mark.parametrize(
    "name,pre,comp,cls",
    [
        ("SIMLIDAR", preprocess_lidar_obs, compress_lidar_sample, LidarMemory),
        ("SIMLIDARPROGRESS", preprocess_lidar_progress_obs, compress_lidar_progress_sample, LidarProgressMemory),
        ("SIMFULL", preprocess_full_obs, compress_full_sample, ImageMemory),
    ],
)
def test_rebuilds_what_the_simulator_returned(name, pre, comp, cls):
    """Record episodes of the fast environment as a worker does, then check that every rebuilt
    transition equals the preprocessed observations the policy saw."""
    from tmrl.sim.interfaces import SimEnv
    from tmrl.sim.race import follow_centre_line

    env = SimEnv(name, img_hist_len=3, act_buf_len=2, ep_max_length=12)
    rng = np.random.default_rng(0)
    samples, seen = [], []
    for _ in range(3):
        obs, info = env.reset()
        samples.append(comp(env.interface.get_default_action(), pre(obs), 0.0, False, False, info))
        seen.append(pre(obs))
        while True:
            act = follow_centre_line(env.race) * 0.5 + rng.uniform(-0.5, 0.5, 3).astype(np.float32)
            act = np.clip(act, -1, 1).astype(np.float32)
            obs, rew, terminated, truncated, info = env.step(act)
            samples.append(comp(act, pre(obs), rew, terminated, truncated, info))
            seen.append(pre(obs))
            if terminated or truncated:
                break
    mem = cls(hist_len=3, act_buf_len=2, memory_size=1000)
    mem.append_buffer(buffer(samples))
    assert len(mem) == len(samples) - 3
    for slot in mem.valid_slots():
        prev_obs, act, rew, new_obs, *_ = mem.get_transition(int(slot))
        for rebuilt, truth in ((prev_obs, seen[int(slot) - 1]), (new_obs, seen[int(slot)])):
            assert len(rebuilt) == len(truth)
            for x, y in zip(rebuilt, truth):
                assert np.allclose(np.asarray(x, dtype=np.float32), np.asarray(y, dtype=np.float32), atol=1e-6)
        assert np.array_equal(act, samples[int(slot)][0])
