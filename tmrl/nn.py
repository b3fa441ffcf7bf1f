"""Module helpers the tmrl tutorial imports: ``copy_shared`` and ``no_grad``.

A training agent hands its actor to the worker-facing code through::

    model_nograd = cached_property(lambda self: no_grad(copy_shared(self.model)))

which gives a second module object whose parameters live in the same memory as the trained ones,
so that broadcasting the actor never copies weights and always sees the latest optimizer step.
"""

from __future__ import annotations

import copy
from typing import TypeVar

import torch

__all__ = ["copy_shared", "no_grad"]

M = TypeVar("M", bound=torch.nn.Module)


def copy_shared(module: M) -> M:
    """Return a copy of ``module`` whose parameters and buffers share storage with ``module``.

    The copy is a distinct module object (its own ``requires_grad`` flags, hooks, training mode,
    attributes), but every tensor in its state dict points at the same memory as the
    corresponding tensor of ``module``: an in-place update of one (an optimizer step, a
    ``load_state_dict``) is seen by the other. Replacing a tensor object (``module.w = ...``)
    breaks the link for that tensor.

    Args:
        module: any ``torch.nn.Module``.

    Returns:
        The sharing copy.
    """
    # Avoid deep-copying the tensors themselves: pre-seed deepcopy's memo so that every
    # parameter/buffer is replaced by a fresh Parameter (or tensor) over the same data.
    memo: dict[int, object] = {}
    for tensor in list(module.parameters()) + list(module.buffers()):
        if id(tensor) in memo:
            continue
        if isinstance(tensor, torch.nn.Parameter):
            memo[id(tensor)] = torch.nn.Parameter(tensor.data, requires_grad=tensor.requires_grad)
        else:
            memo[id(tensor)] = tensor.detach()
    return copy.deepcopy(module, memo)


def no_grad(module: M) -> M:
    """Turn off gradients for every parameter of ``module`` (in place) and return it.

    Args:
        module: any ``torch.nn.Module``.

    Returns:
        The same module, for chaining (``no_grad(copy_shared(model))``).
    """
    for p in module.parameters():
        p.requires_grad_(False)
    return module
