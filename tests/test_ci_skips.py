"""The CI guard of tests/ci_skips.py, run on a tiny suite in a pytest subprocess."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest
from ci_skips import (
    ALLOWED_SKIP_MARKERS,
    ALLOWED_SKIPS_IN_CI,
    LINUX_SKIP_REASON,
    POSIX_SKIP_REASON,
    linux_here,
    posix_here,
)

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


MARKED = '''
import pytest

@pytest.mark.gpu
def test_on_a_gpu():
    pytest.skip("needs a CUDA GPU")

@pytest.mark.gpu
def test_on_a_gpu_that_skips_for_another_reason():
    pytest.skip("an optional package is missing")

def test_unmarked_with_the_gpu_reason():
    pytest.skip("needs a CUDA GPU")
'''


def test_a_gpu_test_may_skip_in_ci_for_the_gpu_reason_only(tmp_path):
    (tmp_path / "pytest.ini").write_text("[pytest]\nmarkers =\n    gpu: needs a CUDA GPU\n")
    (tmp_path / "test_tiny.py").write_text(MARKED)
    env = {k: v for k, v in os.environ.items() if k != "CI"}
    env.update(PYTHONPATH=str(TESTS), CI="true")
    out = subprocess.run(
        [sys.executable, "-m", "pytest", "-q", "-ra", "-p", "ci_skips", "-p", "no:cacheprovider", "test_tiny.py"],
        cwd=tmp_path, env=env, capture_output=True, text=True, timeout=120, check=False,
    )
    assert out.returncode == 1, out.stdout
    assert "2 failed, 1 skipped" in out.stdout
    assert "needs a CUDA GPU (allowed in CI: CI machines have no GPU" in out.stdout
    assert "skipped in CI (an optional package is missing)" in out.stdout  # the marker allows one reason
    assert "test_unmarked_with_the_gpu_reason - skipped in CI (needs a CUDA GPU)" in out.stdout  # and one marker


def test_every_allowed_marker_is_registered_with_pytest():
    text = (TESTS.parent / "pyproject.toml").read_text(encoding="utf-8")
    for marker in ALLOWED_SKIP_MARKERS:
        assert f'"{marker}: ' in text, marker


PLATFORM_MARKED = '''
import pytest
from ci_skips import LINUX_SKIP_REASON, POSIX_SKIP_REASON

@pytest.mark.posix
def test_needs_posix():
    pytest.skip(POSIX_SKIP_REASON)

@pytest.mark.linux
def test_needs_linux():
    pytest.skip(LINUX_SKIP_REASON)

@pytest.mark.posix
def test_needs_posix_but_skips_for_another_reason():
    pytest.skip("an optional package is missing")

def test_unmarked_with_the_posix_reason():
    pytest.skip(POSIX_SKIP_REASON)
'''


def run_platform_suite(tmp_path: Path, windows: bool) -> subprocess.CompletedProcess:
    (tmp_path / "pytest.ini").write_text("[pytest]\nmarkers =\n    posix: p\n    linux: l\n")
    (tmp_path / "test_tiny.py").write_text(PLATFORM_MARKED)
    env = {k: v for k, v in os.environ.items() if k != "TMRL_EMULATE"}
    env.update(PYTHONPATH=str(TESTS), CI="true")
    if windows:  # tests/emulation: a Linux process without POSIX signals and process groups
        env.update(PYTHONPATH=os.pathsep.join([str(TESTS / "emulation"), str(TESTS)]), TMRL_EMULATE="windows")
    return subprocess.run(
        [sys.executable, "-m", "pytest", "-q", "-ra", "-p", "ci_skips", "-p", "no:cacheprovider", "test_tiny.py"],
        cwd=tmp_path, env=env, capture_output=True, text=True, timeout=120, check=False,
    )


def test_off_their_platform_marked_tests_may_skip_in_ci_for_their_reason_only(tmp_path):
    out = run_platform_suite(tmp_path, windows=True)
    assert out.returncode == 1, out.stdout
    assert "2 failed, 2 skipped" in out.stdout
    assert f"{POSIX_SKIP_REASON} (allowed in CI: Windows has neither" in out.stdout
    assert f"{LINUX_SKIP_REASON} (allowed in CI: only Linux has them" in out.stdout
    assert "skipped in CI (an optional package is missing)" in out.stdout  # the marker allows one reason
    assert f"test_unmarked_with_the_posix_reason - skipped in CI ({POSIX_SKIP_REASON})" in out.stdout


@pytest.mark.linux
def test_on_linux_a_marked_test_may_not_skip_in_ci(tmp_path):
    assert linux_here() and posix_here()  # where this suite's CI runs
    out = run_platform_suite(tmp_path, windows=False)
    assert out.returncode == 1, out.stdout
    assert "4 failed" in out.stdout and "skipped" not in out.stdout.splitlines()[-1]
    assert f"test_needs_linux - skipped in CI ({LINUX_SKIP_REASON})" in out.stdout
