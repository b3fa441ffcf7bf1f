"""Non-finite guard: a training update whose loss or gradients hold NaN or inf is skipped.

One bad batch (or a numerical accident) must not turn the parameters into NaN: from there the
next checkpoint holds NaN (a restart does not help), every worker receives NaN weights and sends
NaN samples back. A skipped update changes no parameter, no target, no optimizer state (Adam's
step count and moments included) and no entropy coefficient; it is counted
(:attr:`NonFiniteGuard.skipped`) and logged.

Two ways to decide, one per kind of device (:class:`GuardedUpdate` runs either):

- **on the host** (a CPU, and the first update of each optimizer anywhere): the guard sits between
  ``loss.backward()`` and the optimizers' steps and reads one boolean::

      loss.backward()
      if not self.guard.update_ok(loss, params):
          return self.guard.skipped_metrics()   # no step, no Polyak averaging
      optimizer.step()

  It costs one reduction per gradient tensor and one read of the result (about 0.2 ms for the
  800k gradients of a SAC 256x256 update on one CPU core). On a GPU that read is a
  synchronisation: the host waits for the device at every update.
- **on the device** (CUDA; :attr:`NonFiniteGuard.device_side`): the same sum gives a 0-d
  finite flag that stays on the device. The state the steps will change is copied first
  (:class:`Rollback`: one concatenation per dtype), the steps and Polyak averaging run
  unconditionally, then ``torch.where(flag, new, copy)`` puts the copy back when the flag is
  false, a handful of kernels and no synchronisation. The count of skipped updates is a device
  tensor too, read when :attr:`NonFiniteGuard.skipped` is (the trainer reads it once per round),
  and the metrics of a skipped update are NaN, which the round's means ignore. It needs the
  optimizers' state to exist (Adam creates it at its first step), so each optimizer's first update
  is checked on the host.

The CPU keeps the host check (``device_side`` is set off a CPU only): there the read costs no
wait and the copies do. Forced on this project's 2-core CPU, the device path made a SAC update
(Pendulum-shaped, 256x256, batch 256, one thread) take 10.1 ms instead of 6.3 ms and a REDQ-SAC
update 39.0 ms instead of 24.0 ms (docs/hardware.md).
"""

from __future__ import annotations

import copy
import logging
import math
from collections.abc import Iterable, Mapping
from typing import Any

import torch

from tmrl.util import RateLimitedLog

__all__ = [
    "GuardedUpdate",
    "NonFiniteGuard",
    "Rollback",
    "all_finite",
    "copy_state_into",
    "optimizer_state",
    "stepped_tensors",
]

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

    Args:
        device_side: decide on the device when the agent's update allows it (see the module's
            notes; the agents set it when they train off a CPU).

    Attributes:
        device_side: as the argument (may be changed between updates).
    """

    def __init__(self, device_side: bool = False) -> None:
        self.device_side = bool(device_side)
        self._skipped = 0
        self._pending: torch.Tensor | None = None  # skips decided on the device, not yet read
        self._log = RateLimitedLog(logger, logging.WARNING, 60.0)

    @property
    def skipped(self) -> int:
        """Updates skipped so far. Reading it reads the device's count (one synchronisation on a
        GPU), and logs the skips found there."""
        pending, self._pending = self._pending, None
        found = int(pending) if pending is not None else 0
        if found:
            self._skipped += found
            self._log(
                "skipped a training update whose loss or gradients are not finite (%d skipped so far): "
                "the parameters are unchanged",
                self._skipped,
            )
        return self._skipped

    @skipped.setter
    def skipped(self, value: int) -> None:
        self._skipped = int(value)
        self._pending = None

    def flag(self, loss: torch.Tensor, params: Iterable[torch.Tensor]) -> torch.Tensor:
        """The device-side decision of :meth:`update_ok`: a 0-d boolean tensor, true when ``loss``
        and the gradients of ``params`` are finite. Nothing is read, cleared or counted."""
        grads = [p.grad for p in params if p.grad is not None]
        check = loss.detach().float().sum()
        if grads:
            check = check + _sum(grads)
        return torch.isfinite(check)

    def count(self, ok: torch.Tensor) -> None:
        """Count the update as skipped where the device flag ``ok`` is false (read later by
        :attr:`skipped`)."""
        missed = torch.logical_not(ok).long()
        self._pending = missed if self._pending is None else self._pending + missed

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


def stepped_tensors(optimizers: Iterable[torch.optim.Optimizer]) -> list[torch.Tensor]:
    """What the steps of ``optimizers`` change: their parameters and every tensor of their state
    (Adam's step counts and moments).

    Raises:
        RuntimeError: an optimizer has no state yet (its first step would create some that no
            copy could take back: decide that update on the host).
    """
    optimizers = list(optimizers)
    state = optimizer_state(optimizers)
    if state is None:
        raise RuntimeError("an optimizer has no state (or holds it on another device): its step cannot be undone")
    return [p for opt in optimizers for group in opt.param_groups for p in group["params"]] + state


def optimizer_state(optimizers: Iterable[torch.optim.Optimizer]) -> list[torch.Tensor] | None:
    """Every tensor of the optimizers' state, or None when a parameter has no state yet (its
    optimizer's first step creates it) or holds some on another device than its own."""
    out: list[torch.Tensor] = []
    for opt in optimizers:
        stateless = isinstance(opt, torch.optim.SGD) and all(g.get("momentum", 0) == 0 for g in opt.param_groups)
        for group in opt.param_groups:
            for p in group["params"]:
                st = opt.state.get(p)
                if not st:
                    if stateless:
                        continue
                    return None
                for value in st.values():
                    if isinstance(value, torch.Tensor):
                        if value.device != p.device:
                            return None
                        out.append(value)
    return out


class Rollback:
    """A copy of tensors that :meth:`restore_unless` puts back where a device flag is false.

    The tensors are copied into one flat tensor per (device, dtype), and put back by one
    ``torch.where`` and one ``_foreach_copy_`` per group: a few kernels whatever their number.

    Args:
        tensors: what an update is about to change (parameters, optimizer state, targets, buffers).
    """

    def __init__(self, tensors: Iterable[torch.Tensor]) -> None:
        groups: dict[tuple[torch.device, torch.dtype], list[torch.Tensor]] = {}
        seen: set[int] = set()
        for t in tensors:
            if id(t) not in seen:
                seen.add(id(t))
                groups.setdefault((t.device, t.dtype), []).append(t)
        with torch.no_grad():
            self._groups = [(ts, [t.numel() for t in ts], _flat(ts)) for ts in groups.values()]

    @torch.no_grad()
    def restore_unless(self, ok: torch.Tensor) -> None:
        """Every tensor back to its copy where ``ok`` (a 0-d boolean tensor) is false; unchanged
        (bit for bit) where it is true."""
        for ts, sizes, saved in self._groups:
            kept = torch.where(ok, _flat(ts), saved)
            parts = [part.view(t.shape) for part, t in zip(kept.split(sizes), ts)]
            if hasattr(torch, "_foreach_copy_"):
                torch._foreach_copy_(ts, parts)
            else:  # an older PyTorch: one copy per tensor
                for t, part in zip(ts, parts):
                    t.copy_(part)


def _flat(tensors: list[torch.Tensor]) -> torch.Tensor:
    return torch.cat([t.detach().reshape(-1) for t in tensors])


class GuardedUpdate:
    """The non-finite guard over one update, on the host or on the device (module's notes).

    The update calls :meth:`check` after each backward pass (stop when it returns False: host
    mode, counted already), :meth:`keep` before the steps it guards, :meth:`restore` after a phase
    whose changes must not wait for the end (CrossQ's critics, before its policy reads them), and
    :meth:`finish` on its metrics. On the host, :meth:`keep`, :meth:`restore` and :meth:`pick` do
    nothing a plain update would not: the check has stopped a bad update before its steps.

    Args:
        guard: the agent's guard (it counts).
        on_device: decide on the device (the caller checked that the optimizers' state exists).

    Attributes:
        ok: the device flag so far (true while every check passed), None before the first check
            or on the host.
    """

    def __init__(self, guard: NonFiniteGuard, on_device: bool) -> None:
        self.guard = guard
        self.on_device = bool(on_device)
        self.ok: torch.Tensor | None = None
        self._kept: list[Rollback] = []

    def check(self, loss: torch.Tensor, params: Iterable[torch.Tensor]) -> bool:
        """After a backward pass, whether ``loss`` and the gradients of ``params`` are finite: on
        the host, :meth:`NonFiniteGuard.update_ok` (False: do not step, return
        :meth:`NonFiniteGuard.skipped_metrics`); on the device, fold the flag into :attr:`ok` and
        return True."""
        if not self.on_device:
            return self.guard.update_ok(loss, params)
        flag = self.guard.flag(loss, params)
        self.ok = flag if self.ok is None else self.ok & flag
        return True

    def check_sum(self, check: torch.Tensor) -> bool:
        """:meth:`check` for a sum of the update's losses and gradients computed by the caller."""
        if not self.on_device:
            return self.guard.finite(check)
        flag = torch.isfinite(check)
        self.ok = flag if self.ok is None else self.ok & flag
        return True

    def keep(self, tensors: Iterable[torch.Tensor]) -> None:
        """On the device: copy ``tensors``, to put back by the next :meth:`restore` (or
        :meth:`finish`) unless the update is finite."""
        if self.on_device:
            self._kept.append(Rollback(tensors))

    def restore(self) -> None:
        """On the device: put back what :meth:`keep` copied since the last call, unless every
        check so far passed."""
        if self.on_device and self.ok is not None:
            for rollback in self._kept:
                rollback.restore_unless(self.ok)
        self._kept = []

    def pick(self, new: torch.Tensor, old: torch.Tensor) -> torch.Tensor:
        """``new`` (host, or a finite update), else ``old`` (for the losses an agent keeps)."""
        if not self.on_device or self.ok is None:
            return new
        return torch.where(self.ok, new, old)

    def finish(self, metrics: dict[str, Any]) -> dict[str, Any]:
        """End the update: on the device, :meth:`restore`, count the update when a check failed,
        and make its metrics NaN then (the round's means skip them, as they skip the metrics of
        an update skipped on the host). Returns the metrics."""
        if not self.on_device or self.ok is None:
            return metrics
        self.restore()
        ok = self.ok
        self.guard.count(ok)
        scalars = [k for k, v in metrics.items() if isinstance(v, torch.Tensor) and v.dim() == 0
                   and v.is_floating_point() and v.device == ok.device]
        if scalars:
            masked = torch.where(ok, torch.stack([metrics[k].detach().float() for k in scalars]), math.nan)
            metrics = dict(metrics)
            for k, v in zip(scalars, masked.unbind(0)):
                metrics[k] = v
        return metrics
