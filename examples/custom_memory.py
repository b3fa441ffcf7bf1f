"""A user-written replay memory, in the style of the tmrl library tutorial.

The worker's sample compressor removes the action buffer from each real-time observation (it
can be rebuilt from the actions the memory stores anyway). The memory below decompresses in
``get_transition``: it implements only ``append_buffer``, ``__len__`` and ``get_transition``
and keeps its samples in ``self.data``; ``TorchMemory`` provides the rest (sampling, the CRC
check, collation into tensors).

The built-in ``tmrl.memory.RealTimeTorchMemory(act_buf_len=...)`` does the same job with
preallocated arrays and whole-batch gathers; a custom memory is for layouts it does not cover.

Run: ``python examples/custom_memory.py``.
"""

from __future__ import annotations

import numpy as np

from tmrl.memory import TorchMemory
from tmrl.networking import Buffer

ACT_BUF_LEN = 2
DEFAULT_ACTION = np.zeros(2, dtype=np.float32)


def my_sample_compressor(prev_act, obs, rew, terminated, truncated, info):
    """Drop the action buffer (the last ACT_BUF_LEN elements) from the observation."""
    return prev_act, obs[:-ACT_BUF_LEN], rew, terminated, truncated, info


class MyMemory(TorchMemory):
    """Columns of Python lists in ``self.data``: actions, positions, targets, rewards,
    terminated, truncated, infos."""

    def __init__(self, act_buf_len=ACT_BUF_LEN, device=None, nb_steps=None, sample_preprocessor=None,
                 memory_size=1000000, batch_size=32, dataset_path="", crc_debug=False):
        self.act_buf_len = act_buf_len
        super().__init__(device=device, nb_steps=nb_steps, sample_preprocessor=sample_preprocessor,
                         memory_size=memory_size, batch_size=batch_size, dataset_path=dataset_path,
                         crc_debug=crc_debug)

    def append_buffer(self, buffer):
        columns = (
            [s[0] for s in buffer.memory],  # actions
            [s[1][0] for s in buffer.memory],  # drone position
            [s[1][1] for s in buffer.memory],  # target position
            [s[2] for s in buffer.memory],  # rewards
            [s[3] for s in buffer.memory],  # terminated
            [s[4] for s in buffer.memory],  # truncated
            [s[5] for s in buffer.memory],  # infos
        )
        if not self.data:
            self.data.extend([] for _ in columns)
        for stored, new in zip(self.data, columns):
            stored += new
        excess = len(self.data[0]) - self.memory_size
        if excess > 0:  # forget the oldest samples
            for i, stored in enumerate(self.data):
                self.data[i] = stored[excess:]

    def __len__(self):
        # item i is the transition from sample i to sample i + 1
        return max(0, len(self.data[0]) - 1) if self.data else 0

    def _episode_start(self, idx):
        """Index of the first sample of the episode holding sample idx (or of the memory)."""
        while idx > 0 and not (self.data[4][idx - 1] or self.data[5][idx - 1]):
            idx -= 1
        return idx

    def _act_buf(self, idx):
        """The action buffer of sample idx: the last ACT_BUF_LEN actions of its episode, oldest
        first, the episode's first (default) action repeated before the episode starts."""
        start = self._episode_start(idx)
        return [self.data[0][max(start, idx - k)] for k in reversed(range(self.act_buf_len))]

    def get_transition(self, item):
        prev, now = item, item + 1
        if self.data[4][prev] or self.data[5][prev]:
            # sample `now` is a reset: no transition crosses it; use the neighbour instead
            # (a slight bias the built-in memories avoid with their valid-index mask)
            prev, now = (prev - 1, now - 1) if prev > 0 else (prev + 1, now + 1)
        prev_obs = (self.data[1][prev], self.data[2][prev], *self._act_buf(prev))
        new_obs = (self.data[1][now], self.data[2][now], *self._act_buf(now))
        return (prev_obs, self.data[0][now], self.data[3][now], new_obs,
                self.data[4][now], self.data[5][now], self.data[6][now])


def fake_worker(n_episodes: int, rng: np.random.Generator) -> Buffer:
    """Samples a worker would send for a toy drone environment (already compressed)."""
    buffer = Buffer(maxlen=100_000)
    for _ in range(n_episodes):
        target = rng.uniform(-0.5, 0.5, size=2).astype(np.float32)
        pos = np.zeros(2, dtype=np.float32)
        act_buf = [DEFAULT_ACTION] * ACT_BUF_LEN
        act = DEFAULT_ACTION  # the reset sample carries the default action
        length = int(rng.integers(3, 10))
        for t in range(length):
            if t > 0:
                act = rng.uniform(-1, 1, size=2).astype(np.float32)
                act_buf = act_buf[1:] + [act]
                pos = pos + 0.1 * act
            obs = (pos.copy(), target, *act_buf)
            rew = -float(np.linalg.norm(pos - target))
            sample = my_sample_compressor(act, obs, rew, t == length - 1, False, {})
            buffer.append_sample(sample)
    return buffer


def main() -> None:
    rng = np.random.default_rng(0)
    memory = MyMemory(device="cpu", nb_steps=2, batch_size=8)
    memory.append(fake_worker(20, rng))
    print(f"{len(memory)} transitions stored")
    for prev_obs, act, rew, new_obs, terminated, truncated in memory:  # nb_steps batches
        assert len(prev_obs) == 2 + ACT_BUF_LEN and prev_obs[0].shape == (8, 2)
        assert act.shape == (8, 2) and rew.shape == (8,) and terminated.dtype == rew.dtype
        # the newest action of the new observation's buffer is the transition's action
        assert bool((new_obs[-1] == act).all())
    print("batch ok")


if __name__ == "__main__":
    main()
