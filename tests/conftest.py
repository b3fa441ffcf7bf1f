"""Shared fixtures. Every test runs with its own empty data folder and home, so nothing touches
the developer's ~/TmrlData."""

from __future__ import annotations

import os
import signal
import socket

import pytest

# Tests stop their subprocesses as Ctrl-C does (SIGINT). A shell that starts the test run in the
# background (`nohup ... &`) passes SIGINT on as ignored, and an ignored signal stays ignored in
# every program started below: the server of a compatibility script then never stops. Listening to
# it here again gives the children the default (a handler, unlike SIG_IGN, does not survive exec).
if signal.getsignal(signal.SIGINT) == signal.SIG_IGN:
    signal.signal(signal.SIGINT, signal.default_int_handler)

# In CI a skipped test is a failure, except the few listed in tests/ci_skips.py.
pytest_plugins = ["ci_skips"]


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    # Tests marked posix or linux skip off their platform with the marker's one reason, the one CI
    # allows there (and only there: tests/ci_skips.py).
    from ci_skips import ALLOWED_SKIP_MARKERS, PLATFORM_MARKERS  # loaded above as a plugin

    for marker, here in PLATFORM_MARKERS.items():
        if not here():
            skip = pytest.mark.skip(reason=ALLOWED_SKIP_MARKERS[marker][0])
            for item in items:
                if item.get_closest_marker(marker) is not None:
                    item.add_marker(skip)
    # Tests marked gpu (tests/test_gpu.py) run where PyTorch sees a CUDA GPU and skip elsewhere
    # with GPU_SKIP_REASON, the reason CI allows (tests/ci_skips.py); torch is imported only when
    # such a test was collected.
    marked = [item for item in items if item.get_closest_marker("gpu") is not None]
    if not marked:
        return
    import torch
    from ci_skips import GPU_SKIP_REASON  # loaded above as a plugin (pytest_plugins)

    if torch.cuda.is_available():
        return
    for item in marked:
        item.add_marker(pytest.mark.skip(reason=GPU_SKIP_REASON))


@pytest.fixture(autouse=True)
def _isolated_data_folder(tmp_path, monkeypatch):
    data = tmp_path / "TmrlData"
    monkeypatch.setenv("TMRL_DATA", str(data))
    monkeypatch.setenv("HOME", str(tmp_path / "home"))
    monkeypatch.delenv("TMRL_CONFIG_OVERRIDE", raising=False)
    yield data


def free_port() -> int:
    """A TCP port on 127.0.0.1 that was free a moment ago."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture
def port_factory():
    return free_port


os.environ.setdefault("OMP_NUM_THREADS", "1")
