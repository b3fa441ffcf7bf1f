"""Screen capture through the real capture code (python-xlib geometry + mss) of a real X window
titled "Trackmania", painted with a known image, on an Xvfb server started by the test."""

from __future__ import annotations

import os
import shutil
import subprocess
import time

import numpy as np
import pytest
from xvfb_support import xvfb_display

from tmrl.tm.capture import (
    CaptureUnavailable,
    WindowCapture,
    WindowNotFound,
    WindowSizeError,
    _resize_bilinear,
    display_problem,
    preprocess,
)

W, H = 256, 128


def known_image(w: int = W, h: int = H) -> np.ndarray:
    """RGB test card: 16 coloured columns on top, 8 coloured rows below, a marker pixel at (0, 0)."""
    img = np.zeros((h, w, 3), dtype=np.uint8)
    for i in range(16):
        img[: h // 2, i * (w // 16) : (i + 1) * (w // 16)] = (i * 16, 255 - i * 16, (i * 37) % 256)
    for j in range(8):
        img[h // 2 + j * (h // 16) : h // 2 + (j + 1) * (h // 16)] = ((j * 29) % 256, j * 32, 200 - j * 20)
    img[0, 0] = (255, 255, 0)
    return img


@pytest.fixture(scope="module")
def xvfb():
    with xvfb_display() as name:
        yield name


class PaintedWindow:
    """An X window whose background pixmap holds ``image``: the server repaints it by itself."""

    def __init__(self, display_name, image, title="Trackmania", x=37, y=23, size=None, frame_at=None):
        from Xlib import X, display

        self.d = display.Display(display_name)
        screen = self.d.screen()
        h, w = image.shape[:2]
        pixmap = screen.root.create_pixmap(w, h, screen.root_depth)
        gc = pixmap.create_gc()
        # one fill per run of equal pixels per row keeps this fast and exact
        for row in range(h):
            col = 0
            while col < w:
                end = col
                while end < w and (image[row, end] == image[row, col]).all():
                    end += 1
                r, g, b = (int(v) for v in image[row, col])
                gc.change(foreground=(r << 16) | (g << 8) | b)
                pixmap.fill_rectangle(gc, col, row, end - col, 1)
                col = end
        parent = screen.root
        if frame_at is not None:  # a parent window, as a window manager's frame would be
            parent = screen.root.create_window(
                *frame_at, w + 20, h + 40, 0, screen.root_depth, background_pixel=screen.white_pixel
            )
            parent.map()
        ww, wh = size or (w, h)
        self.win = parent.create_window(
            x,
            y,
            ww,
            wh,
            0,
            screen.root_depth,
            X.InputOutput,
            X.CopyFromParent,
            background_pixmap=pixmap,
            event_mask=X.StructureNotifyMask,
        )
        self.win.set_wm_name(title)
        self.win.map()
        while True:  # wait for the map event: the server has painted the background by then
            ev = self.d.next_event()
            if ev.type == X.MapNotify and ev.window.id == self.win.id:
                break
        self.d.sync()

    def close(self):
        self.win.destroy()
        self.d.sync()
        self.d.close()


@pytest.fixture
def window(xvfb, monkeypatch):
    monkeypatch.setenv("DISPLAY", xvfb)
    win = PaintedWindow(xvfb, known_image(), size=(200, 90))  # wrong size: the capture must fix it
    yield win
    win.close()


@pytest.mark.linux  # a display on Xvfb
def test_capture_moves_resizes_and_grabs_the_client_area(window):
    with WindowCapture("Trackmania", W, H) as cap:
        geo = cap.move_and_resize(10, 20)
        assert (geo.left, geo.top, geo.width, geo.height) == (10, 20, W, H)
        img = cap.screenshot()
    assert img.shape == (H, W, 4) and img.dtype == np.uint8
    rgb = img[..., 2::-1]  # BGRA -> RGB
    np.testing.assert_array_equal(rgb, known_image())


@pytest.mark.linux  # a display on Xvfb
def test_capture_follows_a_window_inside_a_frame(xvfb, monkeypatch):
    monkeypatch.setenv("DISPLAY", xvfb)
    win = PaintedWindow(xvfb, known_image(), x=7, y=19, frame_at=(50, 40))
    try:
        with WindowCapture("Trackmania", W, H) as cap:
            geo = cap.geometry()
            assert (geo.left, geo.top) == (57, 59)  # no hard-coded offset: the real position
            np.testing.assert_array_equal(cap.screenshot()[..., 2::-1], known_image())
    finally:
        win.close()


@pytest.mark.linux  # a display on Xvfb
def test_wrong_size_is_one_clear_error(window):
    with WindowCapture("Trackmania", W, H) as cap:
        with pytest.raises(WindowSizeError, match=r"200x90, expected 256x128.*WINDOW_WIDTH"):
            cap.screenshot()


@pytest.mark.linux  # a display on Xvfb
def test_missing_window_is_one_clear_error(xvfb, monkeypatch):
    monkeypatch.setenv("DISPLAY", xvfb)
    with pytest.raises(WindowNotFound, match="no visible window titled 'Trackmania'"):
        WindowCapture("Trackmania", W, H)


@pytest.mark.linux  # a display on Xvfb
def test_capture_and_preprocess_speed(window):
    """Prints ms per frame for capture + grayscale 64x64 (no assertion on time)."""
    with WindowCapture("Trackmania", W, H) as cap:
        cap.move_and_resize(0, 0)
        frames = 100
        for use_cv2, name in ((False, "NumPy"), (None, "OpenCV if installed")):
            t0 = time.perf_counter()
            for _ in range(frames):
                obs = preprocess(cap.screenshot(), 64, 64, grayscale=True, use_cv2=use_cv2)
            ms = (time.perf_counter() - t0) / frames * 1e3
            assert obs.shape == (64, 64) and obs.dtype == np.uint8
            print(
                f"\ncapture 256x128 + grayscale 64x64 ({name}): {ms:.2f} ms per frame "
                f"(load {os.getloadavg()[0]:.2f})"
            )


def test_display_problems_are_named():
    assert "Wayland" in display_problem("Linux", {"WAYLAND_DISPLAY": "wayland-0"})
    assert "DISPLAY is unset" in display_problem("Linux", {})
    assert display_problem("Linux", {"DISPLAY": ":0"}) is None
    assert "not on Darwin" in display_problem("Darwin", {})


def test_no_display_raises_capture_unavailable(monkeypatch):
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    if os.name == "nt":
        pytest.skip("Windows always has a display")
    with pytest.raises(CaptureUnavailable, match="DISPLAY is unset"):
        WindowCapture()


def test_preprocess_grayscale_matches_hand_computed_values():
    bgra = np.zeros((4, 4, 4), dtype=np.uint8)
    bgra[..., 2] = 200  # red
    bgra[..., 1] = 100  # green
    bgra[..., 0] = 50  # blue
    gray = preprocess(bgra, None, None, grayscale=True, use_cv2=False)
    assert gray.shape == (4, 4) and (gray == round(0.299 * 200 + 0.587 * 100 + 0.114 * 50)).all()
    rgb = preprocess(bgra, 2, 2, grayscale=False, use_cv2=False)
    assert rgb.shape == (2, 2, 3) and (rgb[0, 0] == (200, 100, 50)).all()


def test_numpy_resize_averages_2x2_blocks_when_halving():
    img = np.arange(16, dtype=np.uint8).reshape(4, 4) * 10
    out = _resize_bilinear(img, 2, 2)
    # half-pixel centres: each output pixel is the mean of a 2x2 block
    np.testing.assert_array_equal(out, np.rint([[25, 45], [105, 125]]).astype(np.uint8))


def test_numpy_resize_agrees_with_opencv_when_installed():
    cv2 = pytest.importorskip("cv2", reason="OpenCV not installed: nothing to compare with")
    img = (np.random.default_rng(0).random((128, 256, 3)) * 255).astype(np.uint8)
    diff = np.abs(_resize_bilinear(img, 64, 64).astype(int) - cv2.resize(img, (64, 64)).astype(int))
    assert diff.max() <= 1


def test_importing_tmrl_tm_imports_no_optional_package():
    import sys

    code = (
        "import sys\n"
        "import tmrl.tm, tmrl.tm.openplanet, tmrl.tm.capture, tmrl.tm.control, tmrl.tm.record\n"
        "import tmrl.tm.doctor, tmrl.tm.tools, tmrl.tm.interfaces\n"
        "print(sorted(m for m in ('mss', 'vgamepad', 'cv2', 'Xlib', 'libevdev') if m in sys.modules))\n"
    )
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert res.returncode == 0, res.stderr
    assert res.stdout.strip() == "[]"


def test_generic_pipeline_does_not_import_tmrl_tm():
    import sys

    code = (
        "import importlib, sys\n"
        "for m in ('tmrl', 'tmrl.realtime', 'tmrl.memory', 'tmrl.networking', 'tmrl.driving.reward',\n"
        "          'tmrl.driving.lidar', 'tmrl.config.loader'):\n"
        "    importlib.import_module(m)\n"
        "print('tmrl.tm' in sys.modules)\n"
    )
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert res.returncode == 0, res.stderr
    assert res.stdout.strip() == "False"


@pytest.mark.linux  # a display on Xvfb
def test_xdotool_fallback_reads_the_same_geometry(xvfb, monkeypatch):
    from tmrl.tm.capture import _XdotoolBackend

    if not (shutil.which("xdotool") and shutil.which("xwininfo")):
        pytest.skip("xdotool/xwininfo not installed (apt-get install xdotool x11-utils)")
    monkeypatch.setenv("DISPLAY", xvfb)
    win = PaintedWindow(xvfb, known_image(), x=7, y=19, frame_at=(50, 40))
    try:
        with WindowCapture("Trackmania", W, H, backend=_XdotoolBackend()) as cap:
            geo = cap.geometry()
            assert (geo.left, geo.top, geo.width, geo.height) == (57, 59, W, H)
            np.testing.assert_array_equal(cap.screenshot()[..., 2::-1], known_image())
    finally:
        win.close()
