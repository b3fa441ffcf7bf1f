"""Test support: a private Xvfb display for the screen-capture tests (not a test module)."""

from __future__ import annotations

import contextlib
import os
import select
import shutil
import subprocess
import time
from collections.abc import Iterator

import pytest


@contextlib.contextmanager
def xvfb_display(timeout: float = 20.0) -> Iterator[str]:
    """Start Xvfb on a free display and yield its name (":N"); skip the test with the reason when
    Xvfb, python-xlib or mss is missing or Xvfb does not start."""
    if not shutil.which("Xvfb"):
        pytest.skip("Xvfb is not installed (apt-get install xvfb): the capture needs a display")
    pytest.importorskip("Xlib", reason="python-xlib is not installed (pip install python-xlib)")
    pytest.importorskip("mss", reason="mss is not installed (pip install mss)")
    r, w = os.pipe()
    # -noreset: without it, reconnecting right after the last client closed fails at random.
    proc = subprocess.Popen(
        ["Xvfb", "-displayfd", str(w), "-screen", "0", "640x480x24", "-nolisten", "tcp", "-noreset"],
        pass_fds=(w,),
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    os.close(w)
    # Xvfb writes "<display number>\n" to the fd once it accepts connections: that is the event.
    # The read end stays open until Xvfb ends: closing it early makes Xvfb die of EPIPE.
    line = b""
    deadline = time.monotonic() + timeout
    while not line.endswith(b"\n") and time.monotonic() < deadline:
        ready, _, _ = select.select([r], [], [], max(deadline - time.monotonic(), 0))
        chunk = os.read(r, 64) if ready else b""
        if not chunk:
            break
        line += chunk
    try:
        if not line.endswith(b"\n"):
            proc.kill()
            proc.wait()
            pytest.skip(f"Xvfb did not start within {timeout:g} s on this machine")
        yield f":{line.decode().strip()}"
        proc.terminate()
        proc.wait(timeout=10)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        os.close(r)
