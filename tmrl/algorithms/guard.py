"""Non-finite guard: a training update whose loss or gradients hold NaN or inf is skipped.

One bad batch (or a numerical accident) must not turn the parameters into NaN: from there the
next checkpoint holds NaN (a restart does not help), every worker receives NaN weights and sends
NaN samples back. The guard sits between ``loss.backward()`` and the optimizers' steps:

    loss.backward()
    if not self.guard.update_ok(loss, params):
        return self.guard.skipped_metrics()   # no step, no Polyak averaging
    optimizer.step()

It costs one reduction per gradient tensor and one synchronisation per update (about 0.2 ms for
the 800k gradients of a SAC 256x256 update on one CPU core).
"""

from __future__ import annotations

import copy
import logging
import math
from collections.abc import Iterable, Mapping
from typing import Any

import torch

from tmrl.util import RateLimitedLog

__all__ = ["NonFiniteGuard", "all_finite", "copy_state_into"]

logger = logging.getLogger(__name__)


def _sum(tensors: list[torch.Tensor]) -> torch.Tensor:
    """One float sum of every element (NaN and inf propagate; +inf and -inf give NaN)."""
    return torch.stack([t.detach().float().sum() for t in tensors]).sum()


def all_finite(tensors: Iterable[Any]) -> bool:
    """Whether every floating-point tensor in ``tensors`` (nested dicts, lists and tuples, such
    as a ``state_dict``) holds only finite values."""
    found: list[torch.Tensor] = []
    _collect(tensors if isinstance(tensors, Mapping) else list(tensors), found, 0)
    if not found:
        return True
    by_device: dict[torch.device, list[torch.Tensor]] = {}
    for t in found:
        by_device.setdefault(t.device, []).append(t)
    return all(bool(torch.isfinite(_sum(ts))) for ts in by_device.values())


def copy_state_into(dst: Any, src: Any) -> Any:
    """A copy of ``src`` (nested dicts and lists of tensors and plain values, such as a
    ``state_dict``) that reuses the tensors of ``dst``, an earlier result, where they match.

    The trainer keeps the last finite state of the agent at every broadcast: copying into the
    tensors of the previous copy avoids allocating the whole state again each time (0.20 ms
    instead of 0.70 ms for a SAC 256x256 agent on this project's 2-core CPU).

    Args:
        dst: the previous copy, or ``None``.
        src: the state to copy.

    Returns:
        The copy (new containers; the tensors of ``dst`` overwritten where shape, dtype and device
        match, new tensors elsewhere). Values other than tensors, dicts and lists are deep-copied.
    """
    if isinstance(src, torch.Tensor):
        if (isinstance(dst, torch.Tensor) and dst.shape == src.shape and dst.dtype == src.dtype
                and dst.device == src.device):
            return dst.copy_(src.detach())
        return src.detach().clone()
    if isinstance(src, dict):
        old = dst if isinstance(dst, dict) else {}
        return {key: copy_state_into(old.get(key), value) for key, value in src.items()}
    if isinstance(src, list):
        olds = dst if isinstance(dst, list) and len(dst) == len(src) else [None] * len(src)
        return [copy_state_into(a, b) for a, b in zip(olds, src)]
    return copy.deepcopy(src)


def _collect(obj: Any, out: list[torch.Tensor], depth: int) -> None:
    if depth > 10:
        return
    if isinstance(obj, torch.Tensor):
        if obj.is_floating_point() or obj.is_complex():
            out.append(obj if not obj.is_complex() else torch.view_as_real(obj))
    elif isinstance(obj, Mapping):
        for v in obj.values():
            _collect(v, out, depth + 1)
    elif isinstance(obj, (list, tuple)):
        for v in obj:
            _collect(v, out, depth + 1)


class NonFiniteGuard:
    """Decides whether an update may step, counts and reports the ones it skips.

    Attributes:
        skipped: updates skipped so far.
    """

    def __init__(self) -> None:
        self.skipped = 0
        self._log = RateLimitedLog(logger, logging.WARNING, 60.0)

    def update_ok(self, loss: torch.Tensor, params: Iterable[torch.Tensor]) -> bool:
        """Whether ``loss`` and the gradients of ``params`` (after ``backward``) are finite.

        When they are not, the gradients are cleared, the update is counted and logged (the first
        one at once, then one summary line a minute), and ``False`` is returned: the caller must
        not step its optimizers.
        """
        params = list(params)
        grads = [p.grad for p in params if p.grad is not None]
        check = loss.detach().float().sum()
        if grads:
            check = check + _sum(grads)
        if self.finite(check):
            return True
        for p in params:
            p.grad = None
        return False

    def finite(self, check: torch.Tensor) -> bool:
        """Whether ``check`` (a sum of the update's losses and gradients: NaN or inf anywhere
        makes it non-finite) is finite; when it is not, the update is counted and logged like in
        :meth:`update_ok`, and the caller must not step."""
        if bool(torch.isfinite(check)):
            return True
        self.skipped += 1
        self._log(
            "skipped a training update whose loss or gradients are not finite (%d skipped so far): "
            "the parameters are unchanged",
            self.skipped,
        )
        return False

    def skipped_metrics(self) -> dict[str, Any]:
        """The metrics of a skipped update (losses unknown: NaN, which the round means ignore)."""
        return {"loss_actor": math.nan, "loss_critic": math.nan}
