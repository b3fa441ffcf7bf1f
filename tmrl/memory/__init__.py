"""Replay memories: the user-facing :class:`Memory` API and the built-in array-shaped memories.

Two ways to use this package:

* Subclass :class:`TorchMemory` and implement ``append_buffer``, ``__len__`` and
  ``get_transition`` (the tutorial's way). Sampling then goes through the *slow path*: one
  ``get_transition`` call per item, the CRC check, the ``sample_preprocessor``, then
  :func:`collate_torch`.
* Use :class:`GenericTorchMemory` (any observation structure) or :class:`RealTimeTorchMemory`
  (rebuilds the action buffer of real-time environments). They store samples in preallocated
  NumPy ring buffers and build a whole batch with a few vectorised gathers (the *fast path*).
  They are composed of three parts, each with its share of the checkpoint state:
  :class:`RingStorage` (the ring arrays and the write counter), :class:`EpisodeLinks` (which
  slot precedes which, per worker and episode) and :class:`SlotSampler` (draws valid slots).

What a memory reads from the buffers it is given is typed by :class:`SampleBuffer` and, for
buffers received from the network that hand over stacked arrays, :class:`ColumnBuffer`.

Vocabulary (see docs/internals.md): a *sample* is ``(act, new_obs, rew, terminated, truncated,
info)`` as recorded by a worker; a *transition* is ``(prev_obs, act, rew, new_obs, terminated,
truncated, info)``; a *batch* is a collated list of transitions without ``info``, handed over as a
:class:`tmrl.batch.Batch` (a NamedTuple, so positional unpacking works).

Every name is importable from ``tmrl.memory``; they live in these modules:

* :mod:`tmrl.memory.api`: :class:`Memory` and :class:`TorchMemory` (the user API);
* :mod:`tmrl.memory.builtin`: :class:`GenericTorchMemory` and :class:`RealTimeTorchMemory`;
* :mod:`tmrl.memory.storage`: :class:`RingStorage`, :class:`RestoreWindow` and the buffer
  Protocols;
* :mod:`tmrl.memory.episodes`: :class:`EpisodeLinks`;
* :mod:`tmrl.memory.sampler`: :class:`SlotSampler` (where the memory samples);
* :mod:`tmrl.memory.crc`: ``crc_debug`` (:func:`check_transition`, :class:`CRCMismatchError`);
* :mod:`tmrl.memory.persist`: what ``dataset_path`` loads;
* :mod:`tmrl.memory.resident`: :class:`DeviceRing`, the rings on the training GPU
  (``MEMORY_ON_DEVICE``);
* :mod:`tmrl.memory.tree`: the nested observation structures;
* :mod:`tmrl.batch`: :class:`~tmrl.batch.Batch`, :func:`collate_torch` and :func:`to_torch`.
"""

from __future__ import annotations

from tmrl.batch import Batch, collate_torch, to_torch
from tmrl.memory.api import Memory, TorchMemory
from tmrl.memory.builtin import GenericTorchMemory, RealTimeTorchMemory
from tmrl.memory.crc import CRCMismatchError, check_transition
from tmrl.memory.episodes import EpisodeLinks
from tmrl.memory.resident import DeviceRing
from tmrl.memory.sampler import SlotSampler
from tmrl.memory.storage import ColumnBuffer, RestoreWindow, RingStorage, SampleBuffer, SampleColumns

__all__ = [
    "Batch",
    "CRCMismatchError",
    "ColumnBuffer",
    "DeviceRing",
    "EpisodeLinks",
    "GenericTorchMemory",
    "Memory",
    "RealTimeTorchMemory",
    "RestoreWindow",
    "RingStorage",
    "SampleBuffer",
    "SampleColumns",
    "SlotSampler",
    "TorchMemory",
    "check_transition",
    "collate_torch",
    "to_torch",
]
