"""Screen capture of the TrackMania window with mss, from the window's real geometry.

:class:`WindowCapture` finds the window by its title, moves and resizes it so that its client
area (the game picture, without title bar or borders) is ``width x height`` pixels, and captures
that client area as a BGRA uint8 array ``(height, width, 4)``. The client area's position on the
screen is asked from the system at every capture, so borders, title bars and window managers
need no hard-coded offset:

- Linux (X11): python-xlib (``translate_coords`` of the client window to the root window), or the
  ``xdotool``/``xwininfo`` commands when python-xlib is missing. Wayland sessions without XWayland
  and sessions without a display are reported as such.
- Windows: ``user32`` through ctypes (``FindWindowW``, ``GetClientRect``, ``ClientToScreen``,
  ``SetWindowPos`` with ``AdjustWindowRectEx``), no pywin32.

:func:`preprocess` turns a capture into the observation image (resize, optional grayscale), with
OpenCV when installed and a NumPy fallback otherwise. ``mss``, ``Xlib`` and ``cv2`` are imported
inside the functions that use them.
"""

from __future__ import annotations

import logging
import os
import platform
import re
import shutil
import subprocess
import threading
import time
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np

from tmrl.errors import UserError
from tmrl.tm import TRACKMANIA_EXTRA_HINT

__all__ = [
    "CaptureUnavailable",
    "Geometry",
    "WindowCapture",
    "WindowNotFound",
    "WindowSizeError",
    "display_problem",
    "preprocess",
]

logger = logging.getLogger(__name__)

DEFAULT_TITLE = "Trackmania"


class CaptureUnavailable(UserError):
    """Screen capture cannot work in this session (no display, Wayland, missing package)."""


class WindowNotFound(UserError):
    """No window with the expected title."""


class WindowSizeError(UserError):
    """The window's client area does not have the expected size."""


@dataclass(frozen=True)
class Geometry:
    """Client area of a window in screen pixels.

    Attributes:
        left: x of the area's left edge on the screen.
        top: y of the area's top edge on the screen.
        width: width of the area.
        height: height of the area.
    """

    left: int
    top: int
    width: int
    height: int

    def as_monitor(self) -> dict[str, int]:
        """The area as the ``monitor`` dict mss grabs (``left``, ``top``, ``width``, ``height``)."""
        return {"left": self.left, "top": self.top, "width": self.width, "height": self.height}


def display_problem(system: str | None = None, env: dict[str, str] | None = None) -> str | None:
    """None when a screen can be captured in this session, else a one-line reason and fix.

    Args:
        system: the operating system as :func:`platform.system` names it; None for this one.
        env: the environment variables to judge (``DISPLAY``, ``WAYLAND_DISPLAY``); None for
            this process's.
    """
    system = system or platform.system()
    env = dict(os.environ) if env is None else env
    if system == "Linux":
        if not env.get("DISPLAY"):
            if env.get("WAYLAND_DISPLAY"):
                return (
                    "this is a Wayland session without XWayland (DISPLAY is unset): "
                    "screen capture needs X11; "
                    "log in with an X11 (Xorg) session, or run the game through XWayland"
                )
            return "no display (DISPLAY is unset): run from the desktop session that shows the game"
        return None
    if system == "Windows":
        return None
    return f"screen capture of the game is supported on Windows and Linux (X11), not on {system}"


# ---------------------------------------------------------------------------------------- backends
class _WindowBackend(Protocol):
    def find(self, title: str) -> Any: ...
    def geometry(self, handle: Any) -> Geometry: ...
    def move_resize(self, handle: Any, x: int, y: int, width: int, height: int) -> None: ...


class _XlibBackend:
    """X11 through python-xlib: one display connection, one round trip per geometry query."""

    def __init__(self, display_name: str | None = None) -> None:
        from Xlib import display as xdisplay  # python-xlib (trackmania extra, Linux)
        from Xlib import error as xerror

        self._xerror = xerror
        try:
            self.d = xdisplay.Display(display_name)
        except Exception as err:  # Xlib raises its own DisplayError family
            raise CaptureUnavailable(
                f"cannot open the X display {display_name or os.environ.get('DISPLAY')!r} ({err}): "
                "run from the desktop session that shows the game"
            ) from None
        self.root = self.d.screen().root
        self._lock = threading.Lock()  # one X connection shared by the threads of one capture
        self._net_wm_name = self.d.intern_atom("_NET_WM_NAME")
        self._utf8 = self.d.intern_atom("UTF8_STRING")

    def _title(self, win: Any) -> str | None:
        try:
            prop = win.get_full_property(self._net_wm_name, self._utf8)
            if prop is not None and prop.value:
                v = prop.value
                return v.decode("utf-8", "replace") if isinstance(v, bytes) else str(v)
            name = win.get_wm_name()
            if isinstance(name, bytes):
                return name.decode("latin-1")
            return name
        except self._xerror.XError:
            return None

    def find(self, title: str) -> Any:
        from Xlib import X

        todo = [self.root]
        while todo:
            win = todo.pop()
            try:
                children = win.query_tree().children
            except self._xerror.XError:
                continue
            for child in children:
                if self._title(child) == title:
                    try:
                        if child.get_attributes().map_state == X.IsViewable:
                            return child
                    except self._xerror.XError:
                        continue
                todo.append(child)
        return None

    def close(self) -> None:
        with self._lock:
            self.d.close()

    def geometry(self, handle: Any) -> Geometry:
        with self._lock:
            g = handle.get_geometry()
            origin = handle.translate_coords(self.root, 0, 0)
        # translate_coords gives the root's origin in window coordinates: negate it.
        return Geometry(-origin.x, -origin.y, g.width, g.height)

    def move_resize(self, handle: Any, x: int, y: int, width: int, height: int) -> None:
        with self._lock:
            handle.configure(x=x, y=y, width=width, height=height)
            self.d.sync()


class _XdotoolBackend:
    """X11 through the xdotool command (fallback when python-xlib is not installed)."""

    def find(self, title: str) -> Any:
        res = subprocess.run(
            ["xdotool", "search", "--onlyvisible", "--name", f"^{re.escape(title)}$"],
            capture_output=True,
            text=True,
            check=False,
        )
        ids = res.stdout.split()
        return ids[0] if ids else None

    def geometry(self, handle: Any) -> Geometry:
        res = subprocess.run(["xwininfo", "-id", str(handle)], capture_output=True, text=True, check=True)
        fields = dict(re.findall(r"^\s*(Absolute upper-left [XY]|Width|Height):\s*(-?\d+)", res.stdout, re.M))
        return Geometry(
            int(fields["Absolute upper-left X"]),
            int(fields["Absolute upper-left Y"]),
            int(fields["Width"]),
            int(fields["Height"]),
        )

    def move_resize(self, handle: Any, x: int, y: int, width: int, height: int) -> None:
        subprocess.run(["xdotool", "windowsize", str(handle), str(width), str(height)], check=False)
        subprocess.run(["xdotool", "windowmove", str(handle), str(x), str(y)], check=False)


class _Win32Backend:
    """Windows through user32 (ctypes): client rectangle and client-to-screen translation."""

    SWP_NOZORDER, SWP_NOACTIVATE = 0x0004, 0x0010

    def __init__(self) -> None:
        import ctypes
        from ctypes import wintypes

        self.ct, self.wt = ctypes, wintypes
        u = self.user32 = ctypes.windll.user32  # type: ignore[attr-defined]
        # Explicit prototypes: window handles are pointers, not C ints, on 64-bit Windows.
        u.FindWindowW.argtypes = [wintypes.LPCWSTR, wintypes.LPCWSTR]
        u.FindWindowW.restype = wintypes.HWND
        u.GetClientRect.argtypes = [wintypes.HWND, ctypes.POINTER(wintypes.RECT)]
        u.GetClientRect.restype = wintypes.BOOL
        u.ClientToScreen.argtypes = [wintypes.HWND, ctypes.POINTER(wintypes.POINT)]
        u.ClientToScreen.restype = wintypes.BOOL
        u.GetWindowLongW.argtypes = [wintypes.HWND, ctypes.c_int]
        u.GetWindowLongW.restype = wintypes.LONG
        u.AdjustWindowRectEx.argtypes = [
            ctypes.POINTER(wintypes.RECT),
            wintypes.DWORD,
            wintypes.BOOL,
            wintypes.DWORD,
        ]
        u.AdjustWindowRectEx.restype = wintypes.BOOL
        u.SetWindowPos.argtypes = [wintypes.HWND, wintypes.HWND] + [ctypes.c_int] * 4 + [wintypes.UINT]
        u.SetWindowPos.restype = wintypes.BOOL
        try:  # physical pixels, as mss captures them
            ctypes.windll.shcore.SetProcessDpiAwareness(2)  # type: ignore[attr-defined]
        except Exception:  # older Windows, or already set by mss: either way nothing to do
            pass

    def find(self, title: str) -> Any:
        return self.user32.FindWindowW(None, title) or None

    def geometry(self, handle: Any) -> Geometry:
        rect = self.wt.RECT()
        if not self.user32.GetClientRect(handle, self.ct.byref(rect)):
            raise WindowNotFound("the game window closed while capturing: start TrackMania again")
        pt = self.wt.POINT(0, 0)
        self.user32.ClientToScreen(handle, self.ct.byref(pt))
        return Geometry(pt.x, pt.y, rect.right - rect.left, rect.bottom - rect.top)

    def move_resize(self, handle: Any, x: int, y: int, width: int, height: int) -> None:
        # The outer size is the client size plus the borders and title bar that the window's own
        # styles define; (x, y) is the outer top-left corner, so the title bar stays reachable.
        rect = self.wt.RECT(0, 0, width, height)
        style = self.user32.GetWindowLongW(handle, -16)  # GWL_STYLE
        exstyle = self.user32.GetWindowLongW(handle, -20)  # GWL_EXSTYLE
        self.user32.AdjustWindowRectEx(self.ct.byref(rect), style & 0xFFFFFFFF, False, exstyle & 0xFFFFFFFF)
        self.user32.SetWindowPos(
            handle,
            None,
            x,
            y,
            rect.right - rect.left,
            rect.bottom - rect.top,
            self.SWP_NOZORDER | self.SWP_NOACTIVATE,
        )


def _default_backend(display_name: str | None) -> _WindowBackend:
    system = platform.system()
    problem = display_problem(system)
    if problem is not None and display_name is None:
        raise CaptureUnavailable(problem)
    if system == "Windows":
        return _Win32Backend()
    try:
        return _XlibBackend(display_name)
    except ImportError:
        if shutil.which("xdotool") and shutil.which("xwininfo"):
            return _XdotoolBackend()
        raise CaptureUnavailable(
            f"cannot read window geometry: {TRACKMANIA_EXTRA_HINT} (python-xlib), "
            "or install xdotool and x11-utils"
        ) from None


# ---------------------------------------------------------------------------------------- capture
class WindowCapture:
    """Capture the client area of the game window.

    Args:
        title: exact window title (default ``"Trackmania"``).
        width: expected client-area width in pixels (config ``ENV.WINDOW_WIDTH``; the original
            default is 256).
        height: expected client-area height in pixels (config ``ENV.WINDOW_HEIGHT``; the original
            default is 128).
        display: X display name on Linux (default: ``$DISPLAY``).
        backend: window backend (tests); default: the platform's.

    Not thread-safe: mss handles belong to the thread that made them; use one instance per thread.

    Raises:
        CaptureUnavailable: no display, Wayland, or a missing package.
        WindowNotFound: no visible window has this title.
    """

    def __init__(
        self,
        title: str = DEFAULT_TITLE,
        width: int = 256,
        height: int = 128,
        display: str | None = None,
        backend: _WindowBackend | None = None,
    ) -> None:
        self.title = title
        self.width = int(width)
        self.height = int(height)
        self.display = display
        self.backend = _default_backend(display) if backend is None else backend
        self.handle = self.backend.find(title)
        if self.handle is None:
            raise WindowNotFound(
                f"no visible window titled {title!r}: start TrackMania 2020 in windowed mode "
                f"(not fullscreen, not minimised) on this display"
            )
        # mss handles are bound to the thread that made them; the real-time environment captures
        # from its time-step thread and from the caller's thread (reset), so one per thread.
        self._local = threading.local()
        self._all_sct: list[Any] = []

    def geometry(self) -> Geometry:
        """The client area's current position and size on the screen."""
        return self.backend.geometry(self.handle)

    def move_and_resize(self, x: int = 0, y: int = 0, settle: float = 2.0) -> Geometry:
        """Move the window's top-left corner (its frame, where the system draws one) to ``(x, y)``
        and resize its client area to ``width x height``, then wait (up to ``settle`` seconds) for
        the window system to apply it. The capture follows the client area wherever it ends up.

        Raises:
            WindowSizeError: the window did not take the requested size (message: what to change).
        """
        self.backend.move_resize(self.handle, x, y, self.width, self.height)
        deadline = time.monotonic() + settle
        geo = self.geometry()
        # Window managers apply configure requests asynchronously; polling is the only signal.
        while (geo.width, geo.height) != (self.width, self.height) and time.monotonic() < deadline:
            time.sleep(0.02)
            geo = self.geometry()
        self.check_size(geo)
        return geo

    def check_size(self, geo: Geometry | None = None) -> Geometry:
        """Check the window's client area against the expected ``width x height``.

        Args:
            geo: the geometry to check; None to measure the window now (:meth:`geometry`).

        Returns:
            The geometry checked.

        Raises:
            WindowSizeError: the area has another size (the message says how to fix it).
        """
        geo = self.geometry() if geo is None else geo
        if (geo.width, geo.height) != (self.width, self.height):
            raise WindowSizeError(
                f"the {self.title!r} window's picture is {geo.width}x{geo.height}, expected "
                f"{self.width}x{self.height}: set the game to windowed mode "
                f"(not fullscreen, maximised or minimised), "
                f"or change ENV.WINDOW_WIDTH/ENV.WINDOW_HEIGHT in config.json"
            )
        return geo

    def _mss(self) -> Any:
        sct = getattr(self._local, "sct", None)
        if sct is None:
            try:
                import mss
            except ImportError:
                raise CaptureUnavailable(f"mss is not installed: {TRACKMANIA_EXTRA_HINT}") from None
            kwargs = {"display": self.display} if self.display and platform.system() == "Linux" else {}
            factory = getattr(mss, "MSS", None) or mss.mss  # mss >= 10 renamed the factory
            sct = self._local.sct = factory(**kwargs)
            self._all_sct.append(sct)
        return sct

    def screenshot(self) -> np.ndarray:
        """Capture the client area: BGRA uint8 ``(height, width, 4)`` at its current geometry.

        Raises:
            WindowSizeError: the client area no longer has the expected size.
        """
        geo = self.check_size()
        shot = self._mss().grab(geo.as_monitor())
        return np.frombuffer(shot.raw, dtype=np.uint8).reshape(shot.height, shot.width, 4)

    def close(self) -> None:
        """Release the mss handles (and the X connection of the window backend)."""
        for sct in self._all_sct:
            try:
                sct.close()
            except Exception:  # a handle of another thread may refuse; the process exit frees it
                pass
        self._all_sct.clear()
        self._local = threading.local()
        closer = getattr(self.backend, "close", None)
        if closer is not None:
            closer()

    def __enter__(self) -> WindowCapture:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


# ---------------------------------------------------------------------------------------- preprocessing
def _resize_bilinear(img: np.ndarray, width: int, height: int) -> np.ndarray:
    """Bilinear resize with half-pixel centres (cv2.INTER_LINEAR's convention), in NumPy."""
    h, w = img.shape[:2]
    if (w, h) == (width, height):
        return img.copy()

    def axis(n_in: int, n_out: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        src = (np.arange(n_out) + 0.5) * (n_in / n_out) - 0.5
        src = np.clip(src, 0, n_in - 1)
        i0 = np.floor(src).astype(np.intp)
        i1 = np.minimum(i0 + 1, n_in - 1)
        return i0, i1, (src - i0).astype(np.float32)

    y0, y1, fy = axis(h, height)
    x0, x1, fx = axis(w, width)
    f = img.astype(np.float32)
    if img.ndim == 3:
        fx = fx[:, None]
    top = f[y0][:, x0] * (1 - fx) + f[y0][:, x1] * fx
    bottom = f[y1][:, x0] * (1 - fx) + f[y1][:, x1] * fx
    fy = fy[:, None, None] if img.ndim == 3 else fy[:, None]
    out = top * (1 - fy) + bottom * fy
    return np.clip(np.rint(out), 0, 255).astype(np.uint8)


def preprocess(
    bgra: np.ndarray,
    width: int | None = 64,
    height: int | None = 64,
    grayscale: bool = True,
    use_cv2: bool | None = None,
) -> np.ndarray:
    """Turn a BGRA capture into an observation image.

    Args:
        bgra: ``(H, W, 4)`` or ``(H, W, 3)`` uint8, blue first.
        width: output width (config ``ENV.IMG_WIDTH``); None (or ``height`` None) keeps the
            capture's size.
        height: output height (config ``ENV.IMG_HEIGHT``); None (or ``width`` None) keeps the
            capture's size.
        grayscale: ``(height, width)`` luminance (ITU-R 601 weights) if True, else RGB
            ``(height, width, 3)``.
        use_cv2: force OpenCV (True) or NumPy (False); default: OpenCV when installed.

    Returns:
        uint8 array.
    """
    bgr = bgra[..., :3]
    cv2: Any = None
    if use_cv2 is not False:
        try:
            import cv2  # type: ignore[no-redef]
        except ImportError:
            if use_cv2:
                raise CaptureUnavailable(f"OpenCV is not installed: {TRACKMANIA_EXTRA_HINT}") from None
            cv2 = None
    if cv2 is not None:
        img = (
            bgr if width is None or height is None else cv2.resize(np.ascontiguousarray(bgr), (width, height))
        )
        return cv2.cvtColor(img, cv2.COLOR_BGR2GRAY) if grayscale else np.ascontiguousarray(img[..., ::-1])
    img = bgr if width is None or height is None else _resize_bilinear(bgr, width, height)
    if grayscale:
        gray = (
            img[..., 0] * np.float32(0.114)
            + img[..., 1] * np.float32(0.587)
            + img[..., 2] * np.float32(0.299)
        )
        return np.clip(np.rint(gray), 0, 255).astype(np.uint8)
    return np.ascontiguousarray(img[..., ::-1])
