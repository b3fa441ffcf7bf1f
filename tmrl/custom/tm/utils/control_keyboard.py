"""Compatibility names of the original ``tmrl.custom.tm.utils.control_keyboard``.

The functions drive the keyboard through one :class:`tmrl.tm.control.KeyboardControl`, made on
first use.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

from tmrl.tm.control import KeyboardControl

__all__ = ["apply_control", "keyres"]

_keyboard: KeyboardControl | None = None


def _control() -> KeyboardControl:
    global _keyboard
    if _keyboard is None:
        _keyboard = KeyboardControl()
    return _keyboard


def apply_control(action: Sequence[float], window_id: Any = None) -> None:
    """Apply ``[gas, brake, steer]`` as key presses (``window_id`` is accepted and unused)."""
    _control().send(action)


def keyres() -> None:
    """Respawn with the keyboard."""
    _control().respawn()
