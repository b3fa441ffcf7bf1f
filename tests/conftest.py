"""Shared fixtures. Every test runs with its own empty data folder and home, so nothing touches
the developer's ~/TmrlData."""

from __future__ import annotations

import os
import socket

import pytest

# In CI a skipped test is a failure, except the few listed in tests/ci_skips.py.
pytest_plugins = ["ci_skips"]


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
