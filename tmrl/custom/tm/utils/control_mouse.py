"""Compatibility names of the original ``tmrl.custom.tm.utils.control_mouse``.

tmrl drives TrackMania's menus with the virtual gamepad only: these functions say so.
"""

from __future__ import annotations

from tmrl.errors import UserError

__all__ = ["mouse_close_finish_pop_up_tm20", "mouse_save_replay_tm20"]

_MESSAGE = ("mouse control of TrackMania's menus is not part of this tmrl: set ENV.VIRTUAL_GAMEPAD to true and use "
            "tmrl.custom.tm.utils.control_gamepad")


def mouse_close_finish_pop_up_tm20(small_window: bool = False) -> None:
    """Not available: see the module docstring."""
    raise UserError(_MESSAGE)


def mouse_save_replay_tm20(small_window: bool = False) -> None:
    """Not available: see the module docstring."""
    raise UserError(_MESSAGE)
