"""The replay memory's user API: the abstract :class:`Memory` and :class:`TorchMemory`, which a
custom memory subclasses (the tutorial's way), and the per-item *slow path* of sampling: one
``get_transition`` call per item, the CRC check, the ``sample_preprocessor``, then
:func:`~tmrl.batch.collate_torch`.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Callable, Iterator, Sequence
from typing import Any

import numpy as np

from tmrl.batch import Batch, collate_torch
from tmrl.errors import UserError
from tmrl.memory.crc import check_transition
from tmrl.memory.persist import refuse_pickled_dataset

__all__ = ["Memory", "TorchMemory"]


def _seed_from_global() -> int:
    # Drawn from NumPy's global generator so that np.random.seed(...) makes sampling reproducible.
    return int(np.random.randint(0, 2**31 - 1))


class Memory(ABC):
    """A replay memory: stores what workers send and samples training batches.

    Subclasses implement :meth:`append_buffer`, :meth:`__len__`, :meth:`get_transition` and
    :meth:`collate` (:class:`TorchMemory` provides ``collate``). When overriding ``__init__``, call
    ``super().__init__`` and accept at least the same arguments.

    Args:
        device: device on which batches are collated (``"cpu"``, ``"cuda"``...).
        nb_steps: number of batches one iteration over the memory yields (steps per round).
        sample_preprocessor: optional ``f(prev_obs, act, rew, new_obs, terminated, truncated)``
            returning the same six values, applied to every sampled transition (augmentation).
        memory_size: capacity, in samples.
        batch_size: transitions per batch.
        dataset_path: optional folder of a tmrl checkpoint (or saved memory) whose samples
            pre-fill built-in memories; ignored by user memories. Empty: start empty.
        crc_debug: check every sampled transition against the full sample the worker stored in
            ``info["crc_sample"]`` (pipeline debugging; slow).

    Attributes:
        data: list where user memories keep their samples (starts empty, as in the tutorial).
        stat_train_return: the workers' latest training episode return, copied by :meth:`append`.
        stat_test_return: the workers' latest test episode return, copied by :meth:`append`.
        stat_train_steps: the workers' latest training episode length, copied by :meth:`append`.
        stat_test_steps: the workers' latest test episode length, copied by :meth:`append`.
        rng: the NumPy generator used to draw batch indices.
    """

    def __init__(
        self,
        device: Any,
        nb_steps: int,
        sample_preprocessor: Callable[..., tuple] | None = None,
        memory_size: int = 1000000,
        batch_size: int = 256,
        dataset_path: str = "",
        crc_debug: bool = False,
    ) -> None:
        if int(memory_size) < 1:
            raise UserError(f"memory_size must be at least 1, got {memory_size}: fix MEMORY_SIZE")
        if int(batch_size) < 1:
            raise UserError(f"batch_size must be at least 1, got {batch_size}: fix BATCH_SIZE")
        self.device = device
        self.nb_steps = nb_steps
        self.sample_preprocessor = sample_preprocessor
        self.memory_size = int(memory_size)
        self.batch_size = int(batch_size)
        self.dataset_path = dataset_path
        self.crc_debug = bool(crc_debug)
        self.data: list[Any] = []
        self.stat_train_return = 0.0
        self.stat_test_return = 0.0
        self.stat_train_steps = 0
        self.stat_test_steps = 0
        self.rng = np.random.default_rng(_seed_from_global())
        refuse_pickled_dataset(dataset_path)

    # --- to implement --------------------------------------------------------------------------

    @abstractmethod
    def append_buffer(self, buffer: Any) -> None:
        """Store the samples of ``buffer`` (a ``tmrl.networking.Buffer``: ``buffer.memory`` is a
        list of ``(act, new_obs, rew, terminated, truncated, info)``, oldest first)."""
        raise NotImplementedError

    @abstractmethod
    def __len__(self) -> int:
        """Number of transitions that can be sampled: ``get_transition`` accepts ``0..len-1``."""
        raise NotImplementedError

    @abstractmethod
    def get_transition(self, item: int) -> tuple:
        """Rebuild one transition.

        Args:
            item: an index below ``len(self)`` (for the built-in memories: a slot number).

        Returns:
            ``(prev_obs, act, rew, new_obs, terminated, truncated, info)``; ``info`` must be the
            sample's info dict when CRC debugging is used.
        """
        raise NotImplementedError

    @abstractmethod
    def collate(self, batch: list[tuple], device: Any) -> tuple:
        """Turn a list of ``(prev_obs, act, rew, new_obs, terminated, truncated)`` into one batch
        of tensors on ``device``.

        Args:
            batch: the transitions (as :meth:`get_transition` returns them).
            device: where the tensors go.
        """
        raise NotImplementedError

    # --- provided ------------------------------------------------------------------------------

    def append(self, buffer: Any) -> None:
        """Copy the episode statistics of ``buffer`` and store its samples (nothing happens for an
        empty buffer)."""
        if len(buffer) == 0:
            return
        self.stat_train_return = buffer.stat_train_return
        self.stat_test_return = buffer.stat_test_return
        self.stat_train_steps = buffer.stat_train_steps
        self.stat_test_steps = buffer.stat_test_steps
        self.append_buffer(buffer)

    def __iter__(self) -> Iterator[Batch]:
        """Yield ``nb_steps`` batches."""
        for _ in range(int(self.nb_steps)):
            yield self.sample()

    def __getitem__(self, item: int) -> tuple:
        """One transition ready for collation: ``get_transition``, then the CRC check (when
        ``crc_debug``), then ``sample_preprocessor``; ``rew``, ``terminated`` and ``truncated``
        are returned as ``np.float32``.

        Returns:
            ``(prev_obs, act, rew, new_obs, terminated, truncated)``.
        """
        prev_obs, act, rew, new_obs, terminated, truncated, info = self.get_transition(item)
        if self.crc_debug:
            check_transition(item, (prev_obs, act, new_obs, rew, terminated, truncated), info)
        if self.sample_preprocessor is not None:
            prev_obs, act, rew, new_obs, terminated, truncated = self.sample_preprocessor(
                prev_obs, act, rew, new_obs, terminated, truncated
            )
        return prev_obs, act, np.float32(rew), new_obs, np.float32(terminated), np.float32(truncated)

    def sample_indices(self) -> np.ndarray:
        """Draw ``batch_size`` indices uniformly in ``range(len(self))`` (with replacement).

        Raises:
            ValueError: the memory holds no transition yet.
        """
        length = len(self)
        if length <= 0:
            raise ValueError("cannot sample from a memory that holds no transition yet")
        return self.rng.integers(0, length, size=self.batch_size)

    def sample(self, indices: Sequence[int] | np.ndarray | None = None) -> Batch:
        """Build one batch.

        Args:
            indices: the items to use; ``None`` draws ``batch_size`` of them with
                :meth:`sample_indices`.

        Returns:
            ``Batch(obs, act, rew, next_obs, terminated, truncated)`` collated by
            :meth:`collate` (a ``collate`` that returns something other than six values has
            its result returned as it is).
        """
        if indices is None:
            indices = self.sample_indices()
        collated = self.collate([self[int(i)] for i in indices], self.device)
        if isinstance(collated, (tuple, list)) and len(collated) == len(Batch._fields):
            return Batch(*collated)
        return collated


class TorchMemory(Memory, ABC):
    """A :class:`Memory` whose batches are PyTorch tensors (collated by :func:`collate_torch`).

    Same arguments as :class:`Memory`.
    """

    def collate(self, batch: list[tuple], device: Any) -> tuple:
        """Collate with :func:`collate_torch`.

        Args:
            batch: the transitions (as :meth:`get_transition` returns them).
            device: where the tensors go.
        """
        return collate_torch(batch, device)
