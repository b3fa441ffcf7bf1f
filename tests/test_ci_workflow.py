"""The GitHub Actions workflow (.github/workflows/tests.yml) cannot run here: its syntax is checked
against GitHub's published workflow schema (check-jsonschema, with the schema it ships: no network),
and its jobs are read to check that they run what the README says, on the three OSes and the two
Pythons the project promises."""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import yaml
from test_cli import readme_commands

REPO = Path(__file__).resolve().parents[1]
WORKFLOW = REPO / ".github" / "workflows" / "tests.yml"


def lint(path: Path) -> subprocess.CompletedProcess:
    """check-jsonschema on ``path`` with its vendored copy of GitHub's workflow schema."""
    exe = shutil.which("check-jsonschema", path=str(Path(sys.executable).parent)) or shutil.which("check-jsonschema")
    if exe is None:
        pytest.fail('check-jsonschema is missing: pip install -e ".[test]" installs it')
    return subprocess.run([exe, "--builtin-schema", "vendor.github-workflows", str(path)],
                          capture_output=True, text=True, timeout=60, check=False)


def test_the_workflow_passes_the_linter():
    out = lint(WORKFLOW)
    assert out.returncode == 0, out.stdout + out.stderr


def test_the_linter_fails_a_broken_workflow(tmp_path):
    broken = tmp_path / "tests.yml"
    text = WORKFLOW.read_text(encoding="utf-8")
    broken.write_text(text.replace("runs-on:", "run-on:"), encoding="utf-8")  # a misspelt key
    out = lint(broken)
    assert out.returncode != 0 and "run-on" in out.stdout + out.stderr, out.stdout + out.stderr


def _job() -> dict:
    jobs = yaml.safe_load(WORKFLOW.read_text(encoding="utf-8"))["jobs"]
    assert list(jobs) == ["tests"]
    return jobs["tests"]


def test_the_workflow_runs_the_readme_test_command_on_three_oses_and_two_pythons():
    job = _job()
    matrix = job["strategy"]["matrix"]
    assert sorted(matrix["os"]) == ["macos-latest", "ubuntu-latest", "windows-latest"]
    assert matrix["python"] == ["3.10", "3.12"]  # the oldest supported (pyproject) and a recent one
    assert 'requires-python = ">=3.10"' in (REPO / "pyproject.toml").read_text(encoding="utf-8")
    assert job["strategy"]["fail-fast"] is False  # a Windows failure must not hide the macOS result
    assert job["env"]["CI"] == "true"  # a skip that tests/ci_skips.py does not allow fails the job
    runs = [step for step in job["steps"] if "run" in step]
    readme_test = readme_commands()[1]
    tests = [step for step in runs if "pytest" in step["run"]]
    assert len(tests) == 1 and tests[0]["run"].strip() == readme_test  # verbatim: torch first, --timeout
    assert tests[0]["shell"] == "bash"  # the same command line on Windows too
    assert job["timeout-minutes"] <= 90


def test_the_linux_jobs_install_the_display_tools_that_ci_run_installs():
    display = [step for step in _job()["steps"] if "xvfb" in step.get("run", "")]
    assert len(display) == 1 and display[0]["if"] == "runner.os == 'Linux'"
    ci = (REPO / ".ci" / "run").read_text(encoding="utf-8")
    packages = "xvfb xdotool x11-utils"
    assert packages in ci and packages in display[0]["run"]
