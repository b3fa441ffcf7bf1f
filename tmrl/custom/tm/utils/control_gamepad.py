"""Compatibility names of the original ``tmrl.custom.tm.utils.control_gamepad``.

Each function drives a ``vgamepad.VX360Gamepad`` (``pip install ".[trackmania]" in the checkout of this project``) through
:class:`tmrl.tm.control.GamepadControl`.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

from tmrl.tm.control import GamepadControl

__all__ = ["control_gamepad", "gamepad_close_finish_pop_up_tm20", "gamepad_reset", "gamepad_save_replay_tm20"]


def control_gamepad(gamepad: Any, control: Sequence[float]) -> None:
    """Apply ``[gas, brake, steer]`` with ``gamepad``."""
    GamepadControl(gamepad).send(control)


def gamepad_reset(gamepad: Any) -> None:
    """Respawn (B)."""
    GamepadControl(gamepad).respawn()


def gamepad_save_replay_tm20(gamepad: Any) -> None:
    """Save the replay from the finish screen."""
    GamepadControl(gamepad).save_replay()


def gamepad_close_finish_pop_up_tm20(gamepad: Any) -> None:
    """Close the pop-up shown after the finish line (A)."""
    GamepadControl(gamepad).close_finish_pop_up()
