"""Compatibility name of the original ``tmrl.custom.tm.utils.window``.

``WindowInterface`` is :class:`tmrl.tm.capture.WindowCapture` with the original's constructor
(a window name) and ``move_and_resize(x, y, w, h)``; the size comes from ``config.json``
(``ENV.WINDOW_WIDTH``, ``ENV.WINDOW_HEIGHT``) as in the original.
"""

from __future__ import annotations

from typing import Any

from tmrl.tm.capture import WindowCapture

__all__ = ["WindowInterface"]


class WindowInterface(WindowCapture):
    """Capture of the game window named ``window_name``.

    Raises:
        tmrl.tm.capture.CaptureUnavailable: no display, or the TrackMania extras are missing.
        tmrl.tm.capture.WindowNotFound: no such window.
    """

    def __init__(self, window_name: str = "Trackmania", **kwargs: Any) -> None:
        if "width" not in kwargs or "height" not in kwargs:
            from tmrl.config import config_constants as cfg

            kwargs.setdefault("width", cfg.WINDOW_WIDTH)
            kwargs.setdefault("height", cfg.WINDOW_HEIGHT)
        super().__init__(title=window_name, **kwargs)

    def move_and_resize(self, x: int = 1, y: int = 0, w: int | None = None, h: int | None = None,  # type: ignore[override]
                        settle: float = 2.0) -> Any:
        """Move the window to ``(x, y)`` at the configured size (``w``, ``h`` change it)."""
        if w is not None:
            self.width = int(w)
        if h is not None:
            self.height = int(h)
        return super().move_and_resize(x, y, settle=settle)
