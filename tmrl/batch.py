"""The training batch, and the collation that builds it: what the replay memory hands to
``agent.train``.

A :class:`Batch` is a NamedTuple, so code written for the 6-tuple of tmrl 0.7
(``o, a, r, o2, d, t = batch``, ``batch[3]``) keeps working, and new code reads the fields by
name. :func:`collate_torch` turns a list of transitions into one structure of batched tensors (the
slow path of :class:`tmrl.memory.TorchMemory`); :func:`to_torch` converts arrays that are already
batched (the fast path of the built-in memories). ``tmrl.util.collate_torch`` and
``tmrl.memory.collate_torch`` are this function.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any, NamedTuple

import numpy as np
import torch

from tmrl.errors import UserError

__all__ = ["Batch", "collate_torch", "to_torch"]


class Batch(NamedTuple):
    """One batch of transitions, collated on the training device.

    Attributes:
        obs: observations (a tensor, or a tuple/list/dict of tensors with a leading batch axis).
        act: actions ``(B, *action_shape)``.
        rew: rewards ``(B,)``.
        next_obs: the observations that followed, same structure as ``obs``.
        terminated: 1.0 where the episode ended for good (no bootstrap), ``(B,)``.
        truncated: 1.0 where the episode was cut short (bootstrap anyway), ``(B,)``.
    """

    obs: Any
    act: Any
    rew: Any
    next_obs: Any
    terminated: Any
    truncated: Any


# ==== collation ===================================================================================


def _move(tensor: torch.Tensor, device: Any) -> torch.Tensor:
    """Move a CPU tensor to ``device``; through pinned memory and a non-blocking copy for CUDA."""
    if device is None:
        return tensor
    dev = torch.device(device)
    if dev.type == "cpu":
        return tensor
    if dev.type == "cuda":
        # Pinned host memory lets the host-to-device copy run asynchronously; the training step
        # that consumes the batch is queued on the same stream, so ordering is preserved.
        return tensor.pin_memory().to(dev, non_blocking=True)
    return tensor.to(dev)


def _array_to_tensor(arr: np.ndarray, device: Any) -> torch.Tensor:
    if arr.dtype == np.float64:
        # NumPy's default float is float64; models are float32, so batches are too.
        arr = arr.astype(np.float32)
    elif arr.dtype == object:
        raise UserError(
            "cannot collate a non-numeric observation or action element into a tensor: "
            "make the obs_preprocessor/sample_compressor produce arrays or numbers"
        )
    return _move(torch.from_numpy(np.ascontiguousarray(arr)), device)


def to_torch(tree: Any, device: Any = None) -> Any:
    """Convert a nested structure whose leaves are already-batched NumPy arrays into the same
    structure with tensors on ``device`` (float64 becomes float32; tuples stay tuples, lists stay
    lists, dicts stay dicts).

    Args:
        tree: nested tuples/lists/dicts of arrays (or tensors).
        device: target device; ``None`` leaves tensors on the CPU.

    Returns:
        The same structure with ``torch.Tensor`` leaves.
    """
    if isinstance(tree, torch.Tensor):
        return _move(tree, device)
    if isinstance(tree, np.ndarray):
        return _array_to_tensor(tree, device)
    if isinstance(tree, Mapping):
        return {k: to_torch(v, device) for k, v in tree.items()}
    if isinstance(tree, tuple) and hasattr(tree, "_fields"):  # namedtuple
        return type(tree)(*(to_torch(v, device) for v in tree))
    if isinstance(tree, (tuple, list)):
        return type(tree)(to_torch(v, device) for v in tree)
    return _array_to_tensor(np.asarray(tree), device)


def collate_torch(batch: Sequence[Any], device: Any = None) -> Any:
    """Collate a list of nested structures (NumPy arrays, numbers or tensors as leaves) into one
    structure of batched tensors on ``device``.

    Sequences are transposed (a batch of observation tuples becomes a tuple of stacked tensors),
    mappings are collated key by key, leaves are stacked along a new first dimension. float64
    leaves become float32. :meth:`tmrl.memory.Memory.__getitem__` returns ``rew``,
    ``terminated`` and ``truncated`` as ``np.float32``, so they collate to float32 tensors of
    shape ``(B,)``.

    Args:
        batch: a non-empty list of items with the same structure.
        device: target device (``"cpu"``, ``"cuda"``...); CUDA copies use pinned memory and
            ``non_blocking=True``.

    Returns:
        The collated structure.

    Raises:
        UserError: a leaf is ``None`` or not numeric.
    """
    elem = batch[0]
    if isinstance(elem, torch.Tensor):
        stacked = torch.stack(list(batch))
        if stacked.dtype == torch.float64:
            stacked = stacked.float()
        return _move(stacked, device)
    if isinstance(elem, np.ndarray):
        return _array_to_tensor(np.stack(batch), device)
    if isinstance(elem, Mapping):
        return {key: collate_torch([d[key] for d in batch], device) for key in elem}
    if isinstance(elem, tuple) and hasattr(elem, "_fields"):
        return type(elem)(*(collate_torch(list(col), device) for col in zip(*batch)))
    if isinstance(elem, (tuple, list)):
        return type(elem)(collate_torch(list(col), device) for col in zip(*batch))
    if elem is None:
        raise UserError(
            "cannot collate None: only the first sample of an episode may have a None action, "
            "and it never starts a transition; check the memory's get_transition"
        )
    return _array_to_tensor(np.asarray(batch), device)
