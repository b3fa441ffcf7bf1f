"""Small helpers shared by every layer: partial application, products, cached properties and
atomic file writes.

Nothing here reads configuration or touches the disk at import.
"""

from __future__ import annotations

import functools
import inspect
import math
import os
import tempfile
import time
from pathlib import Path
from typing import Any, Callable, Iterable

from tmrl import platform

__all__ = [
    "partial",
    "partial_to_dict",
    "default",
    "prod",
    "cached_property",
    "atomic_write_bytes",
    "atomic_write_text",
    "dump",
    "load",
    "reuse_freed_memory",
    "RateLimitedLog",
    "last_true_in_list",
    "show_progress_on_console",
    "resolve_device",
]


def default(*args: Any, **kwargs: Any) -> Any:
    """Placeholder callee of a bare ``partial()``.

    ``partial(f, x=partial(y=1))`` replaces this placeholder by the default value of ``f``'s
    parameter ``x``, so that only some arguments of a nested default need to be given.
    """
    raise ValueError("tmrl.util.default is a placeholder and is not meant to be called")


def partial(func: Callable[..., Any] = default, *args: Any, **kwargs: Any) -> functools.partial:
    """``functools.partial`` with tmrl's nested-default rule.

    When a keyword argument is itself a bare ``partial(...)`` (no callee given), its callee
    becomes the default value of that parameter in ``func``'s signature. Example::

        def make(memory_cls=TorchMemory): ...
        partial(make, memory_cls=partial(memory_size=10))  # TorchMemory with memory_size=10

    Raises:
        TypeError: a bare nested partial names a parameter that ``func`` has no default for.
    """
    if func is not default:
        params = None
        for key, value in kwargs.items():
            if isinstance(value, functools.partial) and value.func is default:
                if params is None:
                    params = inspect.signature(func).parameters
                param = params.get(key)
                if param is None or param.default is inspect.Parameter.empty:
                    raise TypeError(
                        f"partial({_qualname(func)}, {key}=partial(...)): {key!r} has no default to extend"
                    )
                kwargs[key] = partial(param.default, *value.args, **value.keywords)
    return functools.partial(func, *args, **kwargs)


def _qualname(obj: Any) -> str:
    module = getattr(obj, "__module__", None) or ""
    name = getattr(obj, "__qualname__", None) or getattr(obj, "__name__", None) or repr(obj)
    return f"{module}:{name}" if module else name


def partial_to_dict(p: functools.partial, version: str = "3") -> dict[str, Any]:
    """Describe a keyword-only partial as a plain dict (callee name, every parameter value).

    Parameters left at their default are included; nested callables are described recursively.
    Used to log the full set of hyperparameters of a run (for example to wandb).

    Args:
        p: a partial (``tmrl.util.partial`` or ``functools.partial``) with keyword arguments only.
        version: accepted for compatibility with tmrl 0.7, unused.

    Raises:
        ValueError: the partial has positional arguments or keywords its callee does not take.
    """
    if p.args:
        raise ValueError("partial_to_dict supports keyword arguments only")
    params = inspect.signature(p.func).parameters
    fields = {k: v.default for k, v in params.items() if v.default is not inspect.Parameter.empty}
    accepts_kwargs = any(v.kind is inspect.Parameter.VAR_KEYWORD for v in params.values())
    unknown = set(p.keywords) - set(params)
    if unknown and not accepts_kwargs:
        raise ValueError(f"{p} has keywords that {_qualname(p.func)} does not take: {sorted(unknown)}")
    fields.update(p.keywords)
    out: dict[str, Any] = {"__class__": _qualname(p.func)}
    for key, value in fields.items():
        if isinstance(value, functools.partial):
            out[key] = partial_to_dict(value, version="")
        elif inspect.isclass(value) or inspect.isfunction(value):
            try:
                out[key] = partial_to_dict(functools.partial(value), version="")
            except (ValueError, TypeError):
                # Builtins such as ``dict`` have no readable signature: name them instead.
                out[key] = _qualname(value)
        else:
            out[key] = value
    if version:
        out["__format_version__"] = version
    return out


def prod(iterable: Iterable[Any], start: Any = 1) -> Any:
    """Product of the items (``start`` for an empty iterable), like ``math.prod``."""
    return math.prod(iterable, start=start)


def last_true_in_list(values: Iterable[Any]) -> int | None:
    """Index of the last truthy item of ``values``, or ``None`` when there is none (the helper
    the original tmrl tutorial uses to find the latest end of episode in a window of samples)."""
    last = None
    for i, v in enumerate(values):
        if v:
            last = i
    return last


class cached_property:  # noqa: N801 (named like the builtin decorator it mirrors)
    """A property computed on first access and stored on the instance.

    Works as a decorator or with a lambda assigned in a class body, as in the tmrl tutorial::

        model_nograd = cached_property(lambda self: no_grad(copy_shared(self.model)))

    Delete the attribute (``del obj.name``) to have it recomputed on next access.

    Args:
        func: computes the value from the instance (``func(self)``).
    """

    def __init__(self, func: Callable[[Any], Any]):
        self.func = func
        self.name: str | None = None
        self.__doc__ = func.__doc__

    def __set_name__(self, owner: type, name: str) -> None:
        self.name = name

    def __get__(self, instance: Any, owner: type | None = None) -> Any:
        if instance is None:
            return self
        if self.name is None:
            raise TypeError("cached_property must be assigned in a class body")
        cache = instance.__dict__
        if self.name not in cache:
            cache[self.name] = self.func(instance)
        return cache[self.name]


def atomic_write_bytes(
    path: str | os.PathLike[str], data: bytes | memoryview, mode: int | None = None
) -> Path:
    """Write ``data`` to ``path`` atomically: a temporary file in the same folder, flushed and
    synced, then renamed over ``path``, then the folder synced. A crash leaves either the old file
    or the new one.

    Args:
        path: the file to write; its parent folder is created when missing.
        data: the whole content.
        mode: permission bits of the file; by default those of an ordinary new file (0o666 less
            the process umask). Pass ``0o600`` for secrets.

    Returns:
        The path.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    if mode is None:
        mode = 0o666 & ~_current_umask()
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as f:
            if hasattr(os, "fchmod"):  # absent on Windows, where the bits mean little anyway
                os.fchmod(f.fileno(), mode)
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        platform.replace(tmp, path)  # retried while a reader holds ``path`` (Windows)
    except BaseException:
        platform.remove(tmp)
        raise
    _fsync_folder(path.parent)
    return path


@functools.lru_cache(maxsize=1)
def _current_umask() -> int:
    # os.umask can only be read by setting it; read it once and restore it at once.
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


def _fsync_folder(folder: Path) -> None:
    """Make a rename in ``folder`` durable (POSIX); a no-op where folders cannot be opened."""
    try:
        fd = os.open(folder, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


def atomic_write_text(
    path: str | os.PathLike[str], text: str, encoding: str = "utf-8", mode: int | None = None
) -> Path:
    """Text version of :func:`atomic_write_bytes`.

    Args:
        path: the file to write (its folder is created when missing).
        text: the whole content.
        encoding: how ``text`` is encoded.
        mode: permission bits of the file (see :func:`atomic_write_bytes`).
    """
    return atomic_write_bytes(path, text.encode(encoding), mode=mode)


def dump(obj: Any, path: str | os.PathLike[str]) -> Path:
    """Save a data-only object (nested containers, NumPy arrays, numbers, strings, bytes, None)
    to ``path`` atomically, in tmrl's data-only format (no pickle).

    Args:
        obj: the object (only data: see :mod:`tmrl.wire`).
        path: the file to write.
    """
    from tmrl import wire

    return atomic_write_bytes(path, wire.encode(obj))


def load(path: str | os.PathLike[str]) -> Any:
    """Read an object written by :func:`dump`. Nothing in the file can execute code; the arrays
    returned are independent, writable copies.

    Args:
        path: the file written by :func:`dump`.

    Raises:
        tmrl.wire.DecodeError: the file is not in tmrl's data-only format or is truncated.
    """
    from tmrl import wire

    return wire.decode(Path(path).read_bytes(), copy=True)


# glibc mallopt parameters (malloc.h)
_M_TRIM_THRESHOLD, _M_TOP_PAD, _M_MMAP_THRESHOLD = -1, -2, -3
_MALLOC_SETTINGS = (
    (_M_MMAP_THRESHOLD, 256 << 20),  # blocks below 256 MiB come from the heap, not fresh mmaps
    (_M_TRIM_THRESHOLD, 1 << 30),  # keep up to 1 GiB freed at the heap top for the next step
    (_M_TOP_PAD, 64 << 20),  # grow the heap 64 MiB at a time
)
_malloc_tuned = False


def reuse_freed_memory() -> bool:
    """Have the C allocator keep freed blocks of up to 256 MiB for reuse (Linux with glibc).

    A training step allocates and frees the same large tensors every time (a CNN's activations
    on a batch of images are tens of MiB each). By default glibc maps blocks above 32 MiB afresh
    and hands freed heap memory back to the kernel, so each step pays a page fault per 4 KiB it
    touches: about 700,000 faults and 2.5 s of system time per TM20FULL update on a 2-core CPU.
    With this call the second step onwards reuses the first step's memory. The cost is that the
    process keeps up to 1 GiB of freed memory (its training working set) instead of returning it.

    Called by :class:`tmrl.training_offline.TorchTrainingOffline` when it is built, so the trainer
    process has it; nothing calls it on import. Idempotent; a no-op elsewhere (Windows, macOS,
    musl).

    Returns:
        True when the settings are in place.
    """
    global _malloc_tuned
    if _malloc_tuned:
        return True
    import sys

    if not sys.platform.startswith("linux"):
        return False
    try:
        if not os.confstr("CS_GNU_LIBC_VERSION"):
            return False
        import ctypes

        mallopt = ctypes.CDLL(None).mallopt
    except (ValueError, OSError, AttributeError):
        return False
    mallopt.argtypes = [ctypes.c_int, ctypes.c_int]
    mallopt.restype = ctypes.c_int
    _malloc_tuned = all(mallopt(param, value) == 1 for param, value in _MALLOC_SETTINGS)
    return _malloc_tuned


DEVICE_CHOICES = ("auto", "cpu", "cuda", "cuda:N", "mps")
"""What :func:`resolve_device` accepts (``N``: a GPU's index)."""


def resolve_device(device: str, option: str = "--device") -> str:
    """The torch device a ``--device`` option (or a setting) names, checked against this machine.

    Args:
        device: ``"auto"`` (``"cuda"`` when PyTorch sees a CUDA GPU, else ``"mps"`` on a Mac whose
            PyTorch has Apple's Metal backend, else ``"cpu"``), ``"cpu"``, ``"cuda"``, ``"cuda:N"``
            or ``"mps"``.
        option: the option or setting the value came from, named in the error.

    Returns:
        ``"cpu"``, ``"cuda"``, ``"cuda:N"`` or ``"mps"``.

    Raises:
        UserError: the value is none of these, or names a GPU that PyTorch does not see.
    """
    from tmrl.errors import UserError

    name = str(device).strip().lower()
    if name not in ("auto", "cpu", "cuda", "mps") and not (name.startswith("cuda:") and name[5:].isdigit()):
        raise UserError(f"{option} {device!r} is not a device: use {', '.join(DEVICE_CHOICES)}")
    if name == "cpu":
        return name
    import torch

    available = torch.cuda.is_available()
    mps = getattr(getattr(torch, "backends", None), "mps", None)
    mps_available = bool(mps is not None and mps.is_available())
    if name == "auto":
        return "cuda" if available else "mps" if mps_available else "cpu"
    if name == "mps":
        if not mps_available:
            raise UserError(f"{option} mps: PyTorch {torch.__version__} has no usable Metal backend here (Apple "
                            f"GPUs on macOS only); use {option} cpu, or {option} auto")
        return name
    count = torch.cuda.device_count() if available else 0
    index = int(name[5:]) if ":" in name else 0
    if index >= count:
        seen = f"it sees {count} GPU{'' if count == 1 else 's'}" if count else "it sees no CUDA GPU"
        raise UserError(f"{option} {device}: PyTorch {torch.__version__} cannot use it ({seen}); "
                        f"use {option} cpu, or {option} auto to take a GPU only when there is one")
    return name


class RateLimitedLog:
    """One log line for the first of a repeated event, then at most one summary line per
    ``interval`` seconds: a flood of drops (a hostile peer, a disconnected link) costs a few lines,
    not one per event.

    Args:
        logger: where the lines go.
        level: their level (``logging.WARNING``...).
        interval: seconds between two lines.

    Attributes:
        total: how many events were reported so far.
    """

    def __init__(self, logger: Any, level: int, interval: float = 1.0):
        self.logger = logger
        self.level = level
        self.interval = interval
        self.total = 0
        self._pending = 0
        self._last = -math.inf
        self._last_line: tuple[str, tuple[Any, ...]] | None = None

    def __call__(self, msg: str, *args: Any) -> None:
        """Report one event: logged now if the last line is older than ``interval``, else counted
        for the next summary."""
        self.total += 1
        now = time.monotonic()
        if now - self._last >= self.interval:
            self._emit(now, msg, args, self._pending)
        else:
            self._pending += 1
            self._last_line = (msg, args)

    def flush(self) -> None:
        """Log the summary of the events held back, once ``interval`` has passed (call it
        regularly: a flood that stops is still summarised)."""
        now = time.monotonic()
        if self._pending and self._last_line is not None and now - self._last >= self.interval:
            msg, args = self._last_line
            self._emit(now, msg, args, self._pending - 1)

    def _emit(self, now: float, msg: str, args: tuple[Any, ...], more: int) -> None:
        self._last = now
        self._pending = 0
        self._last_line = None
        if more:
            msg += f" (and {more} more like it in the last {self.interval:g} s)"
        self.logger.log(self.level, msg, *args)


_CONSOLE_FORMAT = "%(asctime)s %(levelname)s %(name)s: %(message)s"


def show_progress_on_console() -> bool:
    """Show tmrl's INFO messages on stderr when nothing else would show them.

    The original tmrl configured logging when imported, so a tutorial script printed its training
    progress with no set-up. Importing this package leaves logging alone; instead, the
    ``Server``, ``Trainer`` and ``RolloutWorker`` call this when they start. It does something
    only when the root logger has no handler (the script configured no logging): it then gives
    the ``tmrl`` logger a console handler at INFO level. A script that configures logging itself
    keeps full control.

    Returns:
        Whether a handler was installed by this call.
    """
    import logging
    import sys

    root = logging.getLogger()
    ours = logging.getLogger("tmrl")
    if root.handlers or any(getattr(h, "_tmrl_console", False) for h in ours.handlers):
        return False
    handler = logging.StreamHandler(sys.stderr)
    handler.setFormatter(logging.Formatter(_CONSOLE_FORMAT, datefmt="%H:%M:%S"))
    handler._tmrl_console = True  # type: ignore[attr-defined]
    ours.addHandler(handler)
    if ours.level == logging.NOTSET or ours.level > logging.INFO:
        ours.setLevel(logging.INFO)
    return True


def __getattr__(name: str) -> Any:
    # Compatibility with the original ``tmrl.util.collate_torch``: the function lives next to the
    # Batch it builds, in tmrl.batch, which imports torch; it is looked up there only when asked
    # for by this name, so that importing tmrl.util does not import torch.
    if name == "collate_torch":
        from tmrl.batch import collate_torch

        return collate_torch
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
