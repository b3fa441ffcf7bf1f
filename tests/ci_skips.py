"""Test support: in CI (``CI=true``), a skipped test fails the run unless it is listed below.

A display test that skips because Xvfb is missing, or a TrackMania test that skips because an
optional package did not install, would otherwise let CI pass on a suite that quietly shrank.
Tests that carry a marker of :data:`ALLOWED_SKIP_MARKERS` (``gpu``) may skip for that marker's
reason only; the report says so.
Loaded by tests/conftest.py as a pytest plugin (not a test module).
"""

from __future__ import annotations

import os
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

ALLOWED_SKIP_MARKERS: dict[str, tuple[str, str]] = {
    # marker -> (the one skip reason it allows, why a test carrying it may skip in CI)
    "gpu": (GPU_SKIP_REASON, "CI machines have no GPU; run these on one with `pytest -m gpu`"),
}
"""Markers whose tests may skip in CI, for the given reason only (any other skip still fails)."""


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
        if item.get_closest_marker(marker) is not None and reason == allowed:
            _set_skip_reason(report, f"{reason} (allowed in CI: {why})")
            return
    report.outcome = "failed"
    report.longrepr = (
        f"skipped in CI ({reason}): CI runs every test; install what it needs in .ci/run, "
        "or list it in ALLOWED_SKIPS_IN_CI (tests/ci_skips.py) with the reason"
    )
