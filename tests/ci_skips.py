"""Test support: in CI (``CI=true``), a skipped test fails the run unless it is listed below.

A display test that skips because Xvfb is missing, or a TrackMania test that skips because an
optional package did not install, would otherwise let CI pass on a suite that quietly shrank.
Tests that carry a marker of :data:`ALLOWED_SKIP_MARKERS` (``gpu``, ``posix``, ``linux``) may skip
for that marker's reason only; the report says so. A ``posix`` or ``linux`` test may skip only off
its platform (:data:`PLATFORM_MARKERS`): on Linux, where CI runs them all, its skip still fails.
Loaded by tests/conftest.py as a pytest plugin (not a test module).
"""

from __future__ import annotations

import os
import sys
from collections.abc import Callable
from typing import Any

import pytest

ALLOWED_SKIPS_IN_CI: dict[str, str] = {
    # node id without parameters -> why it may skip in CI
    "tests/test_tm_control.py::test_uinput_without_permission_names_the_udev_rule": (
        "CI runs as root, and root can open a file whatever its permissions"
    ),
}
"""The only tests that may skip in CI, each with its reason."""

GPU_SKIP_REASON = "needs a CUDA GPU"
"""Why a test marked ``gpu`` skips where PyTorch sees no CUDA GPU (tests/conftest.py skips it)."""

POSIX_SKIP_REASON = "needs POSIX (signals, process groups, file modes or paths): not on Windows"
"""Why a test marked ``posix`` skips where :func:`posix_here` is false (tests/conftest.py)."""

LINUX_SKIP_REASON = "needs Linux (/proc, prctl, inotify, Xvfb or uinput)"
"""Why a test marked ``linux`` skips where :func:`linux_here` is false (tests/conftest.py)."""


def posix_here() -> bool:
    """Whether this process has POSIX signals, process groups, file modes and paths: Linux and
    macOS; not Windows, nor a Linux process that emulates it (tests/emulation,
    ``TMRL_EMULATE=windows``)."""
    return os.name == "posix" and hasattr(os, "killpg")


def linux_here() -> bool:
    """Whether this is Linux (and not a Linux process that emulates Windows)."""
    return sys.platform.startswith("linux") and posix_here()


ALLOWED_SKIP_MARKERS: dict[str, tuple[str, str]] = {
    # marker -> (the one skip reason it allows, why a test carrying it may skip in CI)
    "gpu": (GPU_SKIP_REASON, "CI machines have no GPU; run these on one with `pytest -m gpu`"),
    "posix": (POSIX_SKIP_REASON, "Windows has neither; the Linux and macOS jobs run these"),
    "linux": (LINUX_SKIP_REASON, "only Linux has them; the Linux job runs these"),
}
"""Markers whose tests may skip in CI, for the given reason only (any other skip still fails)."""

PLATFORM_MARKERS: dict[str, Callable[[], bool]] = {"posix": posix_here, "linux": linux_here}
"""Markers that may skip only off their platform: marker -> whether this is that platform."""


def in_ci() -> bool:
    """Whether this run is CI's (``CI`` set to true, as CI services and .ci/run's caller do)."""
    return os.environ.get("CI", "").strip().lower() in ("1", "true", "yes")


def _skip_reason(report: pytest.TestReport) -> str:
    longrepr: Any = report.longrepr
    if isinstance(longrepr, tuple) and len(longrepr) == 3:
        return str(longrepr[2]).removeprefix("Skipped: ")
    return str(longrepr)


def _set_skip_reason(report: pytest.TestReport, reason: str) -> None:
    longrepr: Any = report.longrepr
    if isinstance(longrepr, tuple) and len(longrepr) == 3:
        report.longrepr = (longrepr[0], longrepr[1], f"Skipped: {reason}")


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_makereport(item: pytest.Item, call: pytest.CallInfo[None]) -> Any:
    outcome = yield
    report: pytest.TestReport = outcome.get_result()
    if not report.skipped or hasattr(report, "wasxfail") or not in_ci():
        return
    if item.nodeid.split("[", 1)[0] in ALLOWED_SKIPS_IN_CI:
        return
    reason = _skip_reason(report)
    for marker, (allowed, why) in ALLOWED_SKIP_MARKERS.items():
        on_its_platform = marker in PLATFORM_MARKERS and PLATFORM_MARKERS[marker]()
        if item.get_closest_marker(marker) is not None and reason == allowed and not on_its_platform:
            _set_skip_reason(report, f"{reason} (allowed in CI: {why})")
            return
    report.outcome = "failed"
    report.longrepr = (
        f"skipped in CI ({reason}): CI runs every test; install what it needs in .ci/run, "
        "or list it in ALLOWED_SKIPS_IN_CI (tests/ci_skips.py) with the reason"
    )
