"""Tests of tmrl.memory: hand-built episodes whose rebuilt transitions are checked exactly."""

from __future__ import annotations

import subprocess
import sys
from collections import deque
from pathlib import Path

import numpy as np
import pytest
import torch

import tmrl.memory
from tmrl.batch import Batch
from tmrl.errors import UserError
from tmrl.memory import (
    ColumnBuffer,
    CRCMismatchError,
    EpisodeLinks,
    GenericTorchMemory,
    RealTimeTorchMemory,
    RingStorage,
    SlotSampler,
    TorchMemory,
    check_transition,
    collate_torch,
)

ROOT = Path(__file__).resolve().parents[1]


class Buf:
    """The part of tmrl.networking.Buffer that memories use."""

    def __init__(self, samples=(), sources=None, ret=0.0):
        self.memory = list(samples)
        self.sources = sources
        self.stat_train_return = ret
        self.stat_test_return = ret + 1
        self.stat_train_steps = 7
        self.stat_test_steps = 8

    def __len__(self):
        return len(self.memory)


def obs_of(src: int, ep: int, t: int) -> tuple:
    """An observation that names where it comes from."""
    return (np.array([src, ep, t], dtype=np.float32), {"img": np.full((2, 3), t, dtype=np.uint8)})


def act_of(src: int, ep: int, t: int) -> np.ndarray:
    return np.array([100 * src + 10 * ep + t, -t], dtype=np.float32)


def episode(src: int, ep: int, n: int, first_act=None, truncated_end=False) -> list[tuple]:
    """n samples: a reset sample (action first_act) then n-1 steps; the last one ends the episode."""
    out = []
    for t in range(n):
        act = first_act if t == 0 else act_of(src, ep, t)
        last = t == n - 1
        out.append((act, obs_of(src, ep, t), float(t) / 2, last and not truncated_end, last and truncated_end, {}))
    return out


def assert_tree_equal(a, b):
    if isinstance(a, dict):
        assert set(a) == set(b)
        for k in a:
            assert_tree_equal(a[k], b[k])
    elif isinstance(a, (tuple, list)):
        assert len(a) == len(b)
        for x, y in zip(a, b):
            assert_tree_equal(x, y)
    else:
        x = a.cpu().numpy() if isinstance(a, torch.Tensor) else np.asarray(a)
        y = b.cpu().numpy() if isinstance(b, torch.Tensor) else np.asarray(b)
        assert x.shape == y.shape and np.array_equal(x, y), (x, y)


# ---- GenericTorchMemory -------------------------------------------------------------------------


def test_generic_transitions_boundary_mask_and_none_actions():
    mem = GenericTorchMemory(memory_size=100, batch_size=3)
    # episode 0: 3 samples (terminated), episode 1: 2 samples (truncated); None reset actions
    mem.append(Buf(episode(0, 0, 3) + episode(0, 1, 2, truncated_end=True), ret=5.0))
    assert mem.stat_train_return == 5.0 and mem.stat_test_steps == 8
    # slots 0 and 3 are episode starts: no transition ends there, and none spans the reset
    assert list(mem.valid_slots()) == [1, 2, 4]
    assert len(mem) == 3
    prev_obs, act, rew, new_obs, terminated, truncated, info = mem.get_transition(2)
    assert_tree_equal(prev_obs, obs_of(0, 0, 1))
    assert_tree_equal(new_obs, obs_of(0, 0, 2))
    assert_tree_equal(act, act_of(0, 0, 2))
    assert rew == np.float32(1.0) and terminated is True and truncated is False and info == {}
    prev_obs, act, _, new_obs, terminated, truncated, _ = mem.get_transition(4)
    assert_tree_equal(prev_obs, obs_of(0, 1, 0))
    assert_tree_equal(act, act_of(0, 1, 1))
    assert (terminated, truncated) == (False, True)
    with pytest.raises(IndexError, match="holds no transition"):
        mem.get_transition(3)
    with pytest.raises(IndexError, match="out of range"):
        mem.get_transition(5)


def test_generic_batch_matches_transitions_and_dtypes():
    mem = GenericTorchMemory(memory_size=100, batch_size=4)
    mem.append(Buf(episode(0, 0, 6)))
    batch = mem.sample(indices=[5, 1, 3])
    prev_obs, act, rew, new_obs, terminated, truncated = batch
    assert isinstance(prev_obs, tuple) and prev_obs[0].shape == (3, 3) and prev_obs[1]["img"].dtype == torch.uint8
    assert act.dtype == torch.float32 and act.shape == (3, 2)
    for t in (rew, terminated, truncated):
        assert t.dtype == torch.float32 and t.shape == (3,)
    assert terminated.tolist() == [1.0, 0.0, 0.0]
    for row, slot in enumerate([5, 1, 3]):
        tr = mem.get_transition(slot)
        assert_tree_equal(prev_obs[0][row], tr[0][0])
        assert_tree_equal(new_obs[1]["img"][row], tr[3][1]["img"])
        assert_tree_equal(act[row], tr[1])
        assert float(rew[row]) == float(tr[2])
    drawn = mem.sample()[1]
    assert drawn.shape == (4, 2)
    assert set(drawn[:, 0].tolist()) <= {1.0, 2.0, 3.0, 4.0, 5.0}


def test_interleaved_sources_are_separate_streams():
    a = episode(1, 0, 4)
    b = episode(2, 0, 4)
    # Two workers interleaved in one buffer, then their streams continue in a second buffer.
    first = [a[0], b[0], b[1], a[1], a[2]]
    mem = GenericTorchMemory(memory_size=100, batch_size=2)
    mem.append(Buf(first, sources=[1, 2, 2, 1, 1]))
    mem.append(Buf([b[2], a[3], b[3]], sources=[2, 1, 2]))
    expected = {}  # slot -> (src, t) of the arriving sample
    order = [(1, 0), (2, 0), (2, 1), (1, 1), (1, 2), (2, 2), (1, 3), (2, 3)]
    for slot, (src, t) in enumerate(order):
        expected[slot] = (src, t)
    valid = list(mem.valid_slots())
    assert valid == [slot for slot, (_, t) in expected.items() if t > 0]
    for slot in valid:
        src, t = expected[slot]
        prev_obs, act, _, new_obs, *_ = mem.get_transition(slot)
        assert_tree_equal(prev_obs, obs_of(src, 0, t - 1))
        assert_tree_equal(new_obs, obs_of(src, 0, t))
        assert_tree_equal(act, act_of(src, 0, t))


def test_ring_buffer_wraps_around_and_drops_broken_transitions():
    mem = GenericTorchMemory(memory_size=5, batch_size=8)
    samples = episode(0, 0, 8)
    mem.append(Buf(samples[:3]))
    mem.append(Buf(samples[3:6]))
    mem.append(Buf(samples[6:]))
    # counters 3..7 are held in slots 3,4,0,1,2; the transition into counter 3 lost its prev
    assert mem.total == 8 and mem.size == 5
    assert sorted(mem.valid_slots()) == [0, 1, 2, 4]
    for counter in range(4, 8):
        prev_obs, act, _, new_obs, *_ = mem.get_transition(counter % 5)
        assert_tree_equal(prev_obs, obs_of(0, 0, counter - 1))
        assert_tree_equal(new_obs, obs_of(0, 0, counter))
        assert_tree_equal(act, act_of(0, 0, counter))
    with pytest.raises(IndexError):
        mem.get_transition(3)
    # a buffer larger than the memory keeps its newest samples and its stream continuity
    big = GenericTorchMemory(memory_size=3, batch_size=2)
    big.append(Buf(samples))
    assert big.total == 8 and sorted(big.valid_slots()) == [0, 1]  # counters 6, 7
    assert_tree_equal(big.get_transition(7 % 3)[0], obs_of(0, 0, 6))


def test_structure_and_shape_changes_are_user_errors():
    mem = GenericTorchMemory(memory_size=10)
    mem.append(Buf(episode(0, 0, 2)))
    bad_shape = [(act_of(0, 0, 1), (np.zeros(4, np.float32), {"img": np.zeros((2, 3), np.uint8)}), 0.0, False, False, {})]
    with pytest.raises(UserError, match=r"obs\[0\] has shape"):
        mem.append(Buf(bad_shape))
    bad_struct = [(act_of(0, 0, 1), (np.zeros(3, np.float32),), 0.0, False, False, {})]
    with pytest.raises(UserError, match="changed structure"):
        mem.append(Buf(bad_struct))
    with pytest.raises(UserError, match="six values"):
        mem.append(Buf([(None, 1.0, 0.0)]))


def test_sampling_is_reproducible_from_numpy_seed():
    def draw():
        np.random.seed(3)
        mem = GenericTorchMemory(memory_size=100, batch_size=16)
        mem.append(Buf(episode(0, 0, 50)))
        return mem.sample_indices()

    assert np.array_equal(draw(), draw())


def counted_episodes(lengths: list[int]) -> list[tuple]:
    """Samples whose reward is their absolute sample number (episodes of the given lengths)."""
    out, k = [], 0
    for n in lengths:
        for t in range(n):
            obs = (np.array([k, t], np.float32),)
            act = None if t == 0 else np.array([k], np.float32)
            out.append((act, obs, float(k), t == n - 1, False, {}))
            k += 1
    return out


def test_sampling_is_uniform_over_valid_transitions_newest_included():
    np.random.seed(7)
    lengths = [37, 50, 23, 41, 30]  # 181 samples into a memory of 100: the ring has wrapped
    size = 100
    mem = GenericTorchMemory(memory_size=size, batch_size=64)
    samples = counted_episodes(lengths)
    for start in range(0, len(samples), 25):
        mem.append(Buf(samples[start : start + 25]))
    total = len(samples)
    # Transition k (arriving sample k) is valid when k is not an episode's first sample and its
    # predecessor k - 1 is still held (the last `size` samples).
    firsts = set(np.cumsum([0] + lengths[:-1]).tolist())
    valid = [k for k in range(total - size + 1, total) if k not in firsts]
    assert total - 1 in valid and len(mem) == len(valid)
    counts = dict.fromkeys(valid, 0)
    draws = 0
    for _ in range(400):
        rewards = mem.sample()[2]
        for k in rewards.to(torch.int64).tolist():
            assert k in counts, f"drew transition {k}, which is not valid"
            counts[k] += 1
        draws += len(rewards)
    expected = draws / len(valid)
    assert counts[total - 1] > expected / 2  # the newest transition is drawn like the others
    chi2 = sum((c - expected) ** 2 / expected for c in counts.values())
    dof = len(valid) - 1
    # Far above chance (about 6 standard deviations of the chi-square law) means not uniform.
    assert chi2 < dof + 6 * (2 * dof) ** 0.5, (chi2, dof)


# ---- RealTimeTorchMemory ------------------------------------------------------------------------


def rtgym_run(src: int, episodes: list[int], L: int, default: np.ndarray) -> list[tuple]:
    """Samples of a real-time environment with an action buffer of length L reset at each episode
    (rtgym's reset_act_buf=True), as the worker records them with crc_debug: the compressor drops
    the action buffer and info["crc_sample"] keeps the full transition."""
    out = []
    for ep, n in enumerate(episodes):
        buf = deque([default] * L, maxlen=L)
        prev_full = None
        for t in range(n):
            act = default if t == 0 else act_of(src, ep, t)
            if t > 0:
                buf.append(act)
            base = obs_of(src, ep, t)
            full = (*base, *buf)
            last = t == n - 1
            rew = float(t)
            info = {"crc_sample": (prev_full, act, full, rew, last, False)}
            out.append((act, full[:-L], rew, last, False, info))
            prev_full = full
    return out


@pytest.mark.parametrize("L", [1, 3])
def test_realtime_rebuilds_action_buffer_across_resets(L):
    default = np.array([0.5, 0.5], dtype=np.float32)
    samples = rtgym_run(0, [2, 5, 3], L, default)
    mem = RealTimeTorchMemory(act_buf_len=L, memory_size=100, batch_size=4, crc_debug=True)
    mem.append(Buf(samples))
    valid = list(mem.valid_slots())
    assert valid == [1, 3, 4, 5, 6, 8, 9]
    for slot in valid:
        prev_obs, act, rew, new_obs, terminated, truncated, info = mem.get_transition(slot)
        want_prev, want_act, want_new, want_rew, want_term, _ = info["crc_sample"]
        assert len(new_obs) == 2 + L
        assert_tree_equal(prev_obs, want_prev)
        assert_tree_equal(new_obs, want_new)
        assert_tree_equal(act, want_act)
        assert float(rew) == want_rew and terminated == want_term
    # first step after a reset: the previous episode's last action is not in the buffer
    prev_obs, _, _, new_obs, *_ = mem.get_transition(3)
    for a in prev_obs[2:]:
        assert_tree_equal(a, default)
    assert_tree_equal(new_obs[-1], act_of(0, 1, 1))
    # the batched fast path gives the same values as the per-item path (crc_debug off)
    mem.crc_debug = False
    fast = mem.sample(indices=valid)
    mem.crc_debug = True
    slow = mem.sample(indices=valid)  # per item, with the CRC check of each transition
    assert_tree_equal(fast, slow)


def test_realtime_skips_transitions_whose_history_was_overwritten():
    default = np.zeros(2, dtype=np.float32)
    mem = RealTimeTorchMemory(act_buf_len=3, memory_size=4, batch_size=64)
    mem.append(Buf(rtgym_run(0, [10], 3, default)))
    # live counters 6..9; 7 and 8 need actions of counter 5 (gone); only 9 is complete
    assert sorted(mem.valid_slots()) == sorted([7 % 4, 8 % 4, 9 % 4])
    assert set(mem.sample_indices().tolist()) == {9 % 4}
    mem2 = RealTimeTorchMemory(act_buf_len=3, memory_size=2, batch_size=4)
    mem2.append(Buf(rtgym_run(0, [10], 3, default)))
    with pytest.raises(UserError, match="too small"):
        mem2.sample_indices()


def test_history_slots_clamp_at_episode_start():
    mem = GenericTorchMemory(memory_size=100)
    mem.append(Buf(episode(0, 0, 3) + episode(0, 1, 4)))
    hist = mem.history_slots(np.array([0, 2, 4, 6]), 4)
    assert hist.tolist() == [[0, 0, 0, 0], [0, 0, 1, 2], [3, 3, 3, 4], [3, 4, 5, 6]]


# ---- the parts of the array-shaped memories -------------------------------------------------------


def vec_obs(counters) -> list:
    """One observation per counter: a dict of a float vector naming it."""
    return [{"v": np.array([c, -c], np.float32)} for c in counters]


def test_storage_ring_wraps_around_on_its_own():
    store = RingStorage(capacity=4)
    assert store.size == 0 and store.oldest == 0 and store.act is None
    first = list(range(3))
    store.write(0, store.obs_rows(vec_obs(first)), store.act_rows([None, np.ones(1), np.ones(1)]),
                np.arange(3, dtype=np.float32), np.zeros(3, bool), np.zeros(3, bool))
    store.total = 3
    # counters 3..6 wrap: slots 3, 0, 1, 2
    more = list(range(3, 7))
    store.write(3, store.obs_rows(vec_obs(more)), None, np.arange(3, 7, dtype=np.float32),
                np.array([False, False, False, True]), np.zeros(4, bool))
    store.total = 7
    assert store.size == 4 and store.oldest == 3
    assert store.count.tolist() == [4, 5, 6, 3]
    assert store.rew.tolist() == [4.0, 5.0, 6.0, 3.0]
    assert store.terminated.tolist() == [False, False, True, False]
    assert store.observations(np.array([3, 0]))["v"].tolist() == [[3, -3], [4, -4]]
    assert store.act.shape == (4, 1) and store.act[0].tolist() == [0.0]  # None: zeros, here overwritten
    assert set(store.arrays()) == {"rew", "terminated", "truncated", "count", "act", "obs.0"}
    with pytest.raises(UserError, match="shape"):
        store.obs_rows([{"v": np.zeros(3, np.float32)}])


def linked(capacity: int = 16) -> tuple[RingStorage, EpisodeLinks]:
    store = RingStorage(capacity)
    return store, EpisodeLinks(store)


def append_links(store: RingStorage, links: EpisodeLinks, done: list[bool], sources) -> np.ndarray:
    """Link and store len(done) samples (the storage's rows are left empty: links only)."""
    start = store.total
    prev = links.chain(start, np.array(done), sources)
    links.write(start, prev)
    store.total += len(done)
    return prev


def test_links_follow_two_interleaved_workers():
    store, links = linked()
    # worker 1: counters 0, 3, 4 (4 ends its episode); worker 2: counters 1, 2
    prev = append_links(store, links, [False, False, False, False, True], [1, 2, 2, 1, 1])
    assert prev.tolist() == [-1, -1, 1, 0, 3]
    assert links.streams == {1: (4, True), 2: (2, False)}
    # both streams continue in the next buffer: worker 2 from counter 2, worker 1 starts anew
    prev = append_links(store, links, [False, False, False], [2, 1, 2])
    assert prev.tolist() == [2, -1, 5]
    assert links.valid_slots().tolist() == [2, 3, 4, 5, 7]
    assert links.history_slots(np.array([7, 4]), 4).tolist() == [[1, 2, 5, 7], [0, 0, 3, 4]]
    with pytest.raises(UserError, match="sources"):
        links.chain(store.total, np.zeros(2, bool), [1])


def test_links_drop_transitions_whose_previous_sample_was_overwritten():
    store, links = linked(capacity=4)
    append_links(store, links, [False] * 6, None)  # counters 2..5 held, in slots 2, 3, 0, 1
    assert sorted(links.valid_slots().tolist()) == [0, 1, 3]  # counter 2's prev (1) is gone
    with pytest.raises(IndexError, match="holds no transition"):
        links.check_slots([2])
    assert links.chain_ok(np.array([0, 1, 3]), 2).tolist() == [True, True, False]


def test_sampler_draws_only_valid_slots():
    store, links = linked(capacity=64)
    sampler = SlotSampler(links)
    rng = np.random.default_rng(0)
    with pytest.raises(ValueError, match="no transition"):
        sampler.draw(rng, 8)
    done = [t % 5 == 4 for t in range(40)]  # episodes of 5: every fifth slot starts one
    append_links(store, links, done, None)
    valid = set(links.valid_slots().tolist())
    assert valid == {k for k in range(40) if k % 5}
    drawn = np.concatenate([sampler.draw(rng, 32) for _ in range(50)])
    assert set(drawn.tolist()) == valid  # every valid slot, and nothing else
    # with histories: slots whose 3 links reach an overwritten sample are never drawn
    store2, links2 = linked(capacity=8)
    append_links(store2, links2, [False] * 12, None)  # counters 4..11 held
    ok = {c % 8 for c in range(7, 12)}
    assert set(np.concatenate([SlotSampler(links2).draw(rng, 16, depth=3) for _ in range(20)]).tolist()) == ok


def test_sample_returns_a_batch_with_named_fields():
    assert tmrl.memory.Batch is Batch and "Batch" in tmrl.memory.__all__
    mem = GenericTorchMemory(memory_size=100, batch_size=4)
    mem.append(Buf(episode(0, 0, 6)))
    for batch in (mem.sample(), mem.sample(indices=[1, 2]), mem.gather(np.array([3]))):
        assert isinstance(batch, Batch)
        assert (batch.obs, batch.act, batch.rew, batch.next_obs, batch.terminated, batch.truncated) == tuple(batch)
    batch = mem.sample(indices=[2, 5])
    assert_tree_equal(batch.next_obs, mem.sample(indices=[2, 5])[3])
    assert batch.terminated.tolist() == [0.0, 1.0]
    mem.sample_preprocessor = lambda *tr: tr  # the per-item slow path of Memory.sample
    slow = mem.sample(indices=[2, 5])
    assert isinstance(slow, Batch)
    assert_tree_equal(tuple(slow), tuple(batch))
    user = TutorialMemory()
    user.append(Buf(episode(0, 0, 4)))
    assert isinstance(user.sample(indices=[0, 1]), Batch)


class ColumnsOnly:
    """A buffer whose samples can only be read as columns (reading memory fails the test)."""

    def __init__(self, columns, sources=None):
        self.columns = columns
        self.sources = sources

    @property
    def memory(self):
        raise AssertionError("the memory read buffer.memory although the columns were offered")

    def as_columns(self):
        return self.columns

    def __len__(self):
        return len(self.columns[2])


def test_column_protocol_accepts_the_network_buffer_and_routes_the_paths():
    from tmrl.networking import Buffer

    assert isinstance(Buffer(maxlen=10), ColumnBuffer)
    assert not isinstance(Buf(), ColumnBuffer)
    assert isinstance(ColumnsOnly(None), ColumnBuffer)  # the check itself never reads memory
    samples = episode(0, 0, 5)
    obs = (np.stack([s[1][0] for s in samples]), {"img": np.stack([s[1][1]["img"] for s in samples])})
    acts = np.stack([np.zeros(2, np.float32)] + [s[0] for s in samples[1:]])
    columns = (acts, obs, np.array([s[2] for s in samples]), np.array([s[3] for s in samples]),
               np.array([s[4] for s in samples]))
    by_columns = GenericTorchMemory(memory_size=10)
    by_columns.append_buffer(ColumnsOnly(columns))
    by_samples = GenericTorchMemory(memory_size=10)
    by_samples.append_buffer(Buf(samples))  # no as_columns: the per-sample path
    for name, ring in by_samples.ring_arrays().items():
        assert np.array_equal(by_columns.ring_arrays()[name], ring), name
    # a network Buffer whose samples are plain tuples offers no columns: its memory is read
    local = Buffer(maxlen=10)
    local.memory = list(samples)
    by_buffer = GenericTorchMemory(memory_size=10)
    by_buffer.append_buffer(local)
    assert np.array_equal(by_buffer.ring_arrays()["obs.0"], by_samples.ring_arrays()["obs.0"])
    # infos are only in the samples: a memory that keeps them never takes the columns
    with pytest.raises(AssertionError, match="buffer.memory"):
        GenericTorchMemory(memory_size=10, store_info=True).append_buffer(ColumnsOnly(columns))


def ring_rows(mem: GenericTorchMemory):
    """What tmrl.checkpoint hands to restore_ring: each array's rows in counter order, oldest first."""
    meta = mem.ring_meta()
    order = np.arange(meta["oldest"], meta["total"]) % mem.capacity
    arrays = {name: arr[order] for name, arr in mem.ring_arrays().items()}
    return meta, lambda name: (meta["oldest"], arrays[name])


def test_checkpoint_round_trip_of_the_composed_memory():
    np.random.seed(0)
    src = RealTimeTorchMemory(act_buf_len=2, memory_size=12, batch_size=6)
    a, b = episode(1, 0, 9), episode(2, 0, 9)
    src.append(Buf([x for pair in zip(a[:6], b[:6]) for x in pair], sources=[1, 2] * 6, ret=3.0))
    meta, rows = ring_rows(src)
    assert set(meta) == {"class", "capacity", "total", "uid", "obs_spec", "leaves", "act", "streams", "oldest",
                         "rng", "stats"}
    assert set(src.ring_arrays()) == {"rew", "terminated", "truncated", "prev", "count", "act", "obs.0", "obs.1"}
    dst = RealTimeTorchMemory(act_buf_len=2, memory_size=12, batch_size=6)
    dst.restore_ring(meta, rows)
    assert dst.total == src.total and dst.uid == src.uid and dst.stat_train_return == 3.0
    assert np.array_equal(dst.valid_slots(), src.valid_slots())
    assert np.array_equal(dst.sample_indices(), src.sample_indices())  # the generator's state came along
    # the workers' streams came along too: their episodes continue in both memories alike
    more = Buf([a[6], b[6], a[7]], sources=[1, 2, 1])
    src.append(more)
    dst.append(more)
    for name, ring in src.ring_arrays().items():
        assert np.array_equal(dst.ring_arrays()[name], ring), name
    assert_tree_equal(tuple(dst.sample(indices=src.valid_slots())), tuple(src.sample(indices=src.valid_slots())))


def test_restore_reads_a_checkpoint_meta_written_before_the_memory_was_split():
    """The keys and layout that tmrl wrote before the memory had parts: counters 0..5 of one
    episode, 2..5 still held, in a memory of 4."""
    meta = {"class": "GenericTorchMemory", "capacity": 4, "total": 6, "uid": "0123abcd", "obs_spec": ["leaf", 0],
            "leaves": [["float32", [2]]], "act": ["float32", [1]], "streams": [[0, 5, False]], "oldest": 2,
            "rng": None, "stats": [1.5, 2.5, 3, 4]}
    held = np.arange(2, 6)
    saved = {"obs.0": np.stack([held, -held], 1).astype(np.float32), "act": held[:, None].astype(np.float32),
             "rew": held.astype(np.float32), "terminated": np.zeros(4, bool), "truncated": np.zeros(4, bool),
             "prev": held - 1, "count": held}
    mem = GenericTorchMemory(memory_size=4, batch_size=2)
    mem.restore_ring(meta, lambda name: (2, saved[name]))
    assert mem.total == 6 and mem.uid == "0123abcd" and mem.stat_test_steps == 4
    assert sorted(mem.counters[mem.valid_slots()].tolist()) == [3, 4, 5]
    prev_obs, act, rew, new_obs, *_ = mem.get_transition(4 % 4)
    assert prev_obs.tolist() == [3, -3] and new_obs.tolist() == [4, -4] and act.tolist() == [4] and rew == 4
    mem.append(Buf([(np.array([6], np.float32), np.array([6, -6], np.float32), 6.0, False, False, {})]))
    assert mem.get_transition(6 % 4)[0].tolist() == [5, -5]  # the saved stream goes on


# ---- CRC debugging ------------------------------------------------------------------------------


def test_crc_mismatch_names_field_and_element():
    default = np.zeros(2, dtype=np.float32)
    samples = rtgym_run(0, [4], 2, default)
    # corrupt the action buffer the worker saw at step 2 (element 3 of the new observation)
    prev_full, act, full, rew, term, trunc = samples[2][5]["crc_sample"]
    full = (*full[:3], full[3] + 1)
    samples[2][5]["crc_sample"] = (prev_full, act, full, rew, term, trunc)
    mem = RealTimeTorchMemory(act_buf_len=2, memory_size=10, batch_size=2, crc_debug=True)
    mem.append(Buf(samples))
    mem[1]  # untouched transition passes
    with pytest.raises(CRCMismatchError, match=r"transition 2 .*new_obs\[3\]"):
        mem[2]
    assert check_transition(0, (None,) * 6, {}) is False


# ---- the slow path: a user memory written like the tutorial's -------------------------------------


class TutorialMemory(TorchMemory):
    """Implements only append_buffer, __len__ and get_transition, on self.data lists."""

    def __init__(self, device=None, nb_steps=None, sample_preprocessor=None, memory_size=1000, batch_size=4,
                 dataset_path=""):
        super().__init__(device=device, nb_steps=nb_steps, sample_preprocessor=sample_preprocessor,
                         memory_size=memory_size, batch_size=batch_size, dataset_path=dataset_path)

    def append_buffer(self, buffer):
        cols = [[b[i] for b in buffer.memory] for i in range(6)]
        if self.data:
            for col, new in zip(self.data, cols):
                col += new
        else:
            self.data.extend(cols)

    def __len__(self):
        return max(0, len(self.data[0]) - 1) if self.data else 0

    def get_transition(self, item):
        return (self.data[1][item], self.data[0][item + 1], self.data[2][item + 1], self.data[1][item + 1],
                self.data[3][item + 1], self.data[4][item + 1], self.data[5][item + 1])


def test_user_memory_works_through_the_slow_path():
    calls = []

    def preprocessor(prev_obs, act, rew, new_obs, terminated, truncated):
        calls.append(1)
        return prev_obs, act * 2, rew, new_obs, terminated, truncated

    mem = TutorialMemory(nb_steps=3, sample_preprocessor=preprocessor)
    assert mem.data == [] and len(mem) == 0
    mem.append(Buf([(np.zeros(2, np.float32), obs_of(0, 0, 0), 0.0, False, False, {})] + episode(0, 0, 5)[1:]))
    batches = list(mem)
    assert len(batches) == 3 and len(calls) == 12
    prev_obs, act, rew, new_obs, terminated, truncated = mem.sample(indices=[0, 3])
    assert isinstance(prev_obs, tuple) and prev_obs[0].shape == (2, 3)
    assert act.tolist() == [[2.0, -2.0], [8.0, -8.0]]
    assert rew.dtype == torch.float32 and terminated.tolist() == [0.0, 1.0]


def test_collate_torch_shapes():
    batch = [((np.ones(3), np.zeros((2, 2), np.uint8)), np.ones(2), np.float32(1), (np.ones(3), np.zeros((2, 2), np.uint8)),
              np.float32(0), np.float32(1)) for _ in range(5)]
    prev_obs, act, rew, new_obs, terminated, truncated = collate_torch(batch, "cpu")
    assert prev_obs[0].shape == (5, 3) and prev_obs[0].dtype == torch.float32  # float64 -> float32
    assert prev_obs[1].dtype == torch.uint8 and act.shape == (5, 2)
    assert rew.shape == (5,) and truncated.dtype == torch.float32
    with pytest.raises(UserError, match="None"):
        collate_torch([None, None])


def test_collate_torch_is_one_function_at_its_three_paths_and_tmrl_util_does_not_import_torch():
    import tmrl.batch
    import tmrl.util

    # tmrl 0.7's path (tmrl.util), the memory's and the one where it lives
    assert tmrl.util.collate_torch is tmrl.memory.collate_torch is tmrl.batch.collate_torch
    code = "import sys, tmrl.util; print('torch' in sys.modules)"
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, check=False)
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.strip() == "False", "importing tmrl.util imported torch"


def test_dataset_path_refuses_pickle(tmp_path):
    (tmp_path / "data.pkl").write_bytes(b"\x80\x04N.")
    with pytest.raises(UserError, match="pickle"):
        GenericTorchMemory(dataset_path=str(tmp_path))


def test_custom_memory_example_runs():
    proc = subprocess.run([sys.executable, str(ROOT / "examples" / "custom_memory.py")], capture_output=True,
                          text=True, timeout=120, check=False)
    assert proc.returncode == 0, proc.stderr
    assert "batch ok" in proc.stdout
