"""The CI guard of tests/ci_skips.py, run on a tiny suite in a pytest subprocess."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from ci_skips import ALLOWED_SKIPS_IN_CI

TESTS = Path(__file__).resolve().parent

SUITE = '''
import pytest

def test_runs():
    pass

def test_needs_a_display():
    pytest.skip("Xvfb is not installed")

@pytest.mark.xfail(reason="known")
def test_known_failure():
    raise AssertionError
'''


def run_suite(tmp_path: Path, ci: str | None) -> subprocess.CompletedProcess:
    (tmp_path / "test_tiny.py").write_text(SUITE)
    env = {k: v for k, v in os.environ.items() if k != "CI"}
    env["PYTHONPATH"] = str(TESTS)
    if ci is not None:
        env["CI"] = ci
    return subprocess.run(
        [sys.executable, "-m", "pytest", "-q", "-p", "ci_skips", "-p", "no:cacheprovider", "test_tiny.py"],
        cwd=tmp_path, env=env, capture_output=True, text=True, timeout=120, check=False,
    )


def test_a_skip_fails_the_run_in_ci_with_the_reason_and_the_fix(tmp_path):
    out = run_suite(tmp_path, "true")
    assert out.returncode == 1, out.stdout
    assert "1 failed, 1 passed, 1 xfailed" in out.stdout
    assert "skipped in CI (Xvfb is not installed)" in out.stdout
    assert "ALLOWED_SKIPS_IN_CI" in out.stdout


@pytest.mark.parametrize("ci", [None, "false"])
def test_a_skip_is_a_skip_outside_ci(tmp_path, ci):
    out = run_suite(tmp_path, ci)
    assert out.returncode == 0, out.stdout
    assert "1 passed, 1 skipped, 1 xfailed" in out.stdout


def test_every_allowed_skip_names_an_existing_test_and_a_reason():
    for node, reason in ALLOWED_SKIPS_IN_CI.items():
        path, name = node.split("::")
        assert f"def {name}(" in (TESTS.parent / path).read_text(encoding="utf-8"), node
        assert len(reason) > 20, node
