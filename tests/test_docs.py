"""The documentation is tested like the code: the site builds with ``mkdocs build --strict`` (a broken
link, a missing page or a bad reference fails), every Python block in docs/ runs, every example
under examples/ is run by some test, and every public name in the API reference has a docstring
that names its arguments.

Why a harness of our own rather than pytest-markdown-docs or pytest-examples: the blocks of one page
build on each other (the tutorial defines an interface in one block and uses it three blocks later),
so a page runs as one script in a fresh subprocess with its own data folder, and a traceback points
at the page's own line numbers. A block that cannot run here (it needs the game, another machine,
or it is a signature listing) is marked by the line ``<!-- not run: <reason> -->`` right above its
fence; the reason is required. A block made only of ``--8<-- "examples/x.py:section"`` lines shows
an example's code (pymdownx.snippets), which that example's own test runs. Blocks in other languages
are not run.
"""

from __future__ import annotations

import ast
import importlib
import inspect
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
DOCS = ROOT / "docs"
EXAMPLES = ROOT / "examples"

FENCE = re.compile(r"^(?P<indent>[ \t]*)(?P<fence>`{3,}|~{3,})\s*(?P<lang>[\w+-]*)")
#: Reason given to a block made only of ``--8<-- "file:section"`` includes (pymdownx.snippets): the
#: code is an examples/ file's, run by that example's test (test_every_example_is_run_by_a_test).
INCLUDED = "included from a file that its own test runs"
NOT_RUN = re.compile(r"^\s*<!--\s*not run:\s*(?P<reason>.*?)\s*-->\s*$")


def python_blocks(text: str) -> list[tuple[int, str, str | None]]:
    """The page's Python blocks as ``(first line number, source, reason not run or None)``."""
    lines = text.splitlines()
    blocks = []
    i = 0
    while i < len(lines):
        m = FENCE.match(lines[i])
        if not m:
            i += 1
            continue
        fence, lang, indent = m["fence"], m["lang"].lower(), len(m["indent"])
        j = i + 1
        while j < len(lines) and not lines[j].strip().startswith(fence):
            j += 1
        if lang in ("python", "py", "python3"):
            reason = None
            k = i - 1
            if k >= 0:
                nm = NOT_RUN.match(lines[k])
                if nm:
                    reason = nm["reason"]
            body = "\n".join(line[indent:] for line in lines[i + 1:j])
            if reason is None and all(not ln.strip() or ln.strip().startswith("--8<--") for ln in body.splitlines()):
                reason = INCLUDED  # the page shows a file's code: that file's own test runs it
            blocks.append((i + 2, body, reason))
        i = j + 1
    return blocks


def pages() -> list[Path]:
    return sorted(DOCS.rglob("*.md"))


def runnable_pages() -> list[Path]:
    return [p for p in pages() if any(r is None for _, _, r in python_blocks(p.read_text(encoding="utf-8")))]


RUNNER = """
import sys
page, blocks = sys.argv[1], __import__("json").loads(sys.stdin.read())
namespace = {"__name__": "__main__"}
for line, source in blocks:
    code = compile("\\n" * (line - 1) + source, page, "exec")
    exec(code, namespace)
"""


def test_block_parser_sees_fences_markers_and_indentation():
    text = "\n".join([
        "# t", "```python", "a = 1", "```", "<!-- not run: needs the game -->", "```python", "b = 2", "```",
        "```bash", "echo x", "```", "1. item", "", "    ```python", "    c = a + 1", "    ```",
        "```python", '--8<-- "examples/x.py:part"', "```",
    ])
    blocks = python_blocks(text)
    assert [(line, src, reason) for line, src, reason in blocks] == [
        (3, "a = 1", None), (7, "b = 2", "needs the game"), (15, "c = a + 1", None),
        (18, '--8<-- "examples/x.py:part"', INCLUDED)]


@pytest.mark.parametrize("page", runnable_pages(), ids=lambda p: str(p.relative_to(DOCS)))
def test_python_blocks_of_the_page_run(page, tmp_path):
    import json

    blocks = [(line, src) for line, src, reason in python_blocks(page.read_text(encoding="utf-8")) if reason is None]
    env = dict(os.environ, TMRL_DATA=str(tmp_path / "TmrlData"), MPLBACKEND="Agg", PYTHONPATH=str(ROOT))
    out = subprocess.run([sys.executable, "-c", RUNNER, str(page.relative_to(ROOT))], input=json.dumps(blocks),
                         capture_output=True, text=True, cwd=tmp_path, env=env, timeout=300, check=False)
    assert out.returncode == 0, f"{page.name}: a Python block failed\n{out.stdout[-2000:]}\n{out.stderr[-4000:]}"


def test_blocks_not_run_say_why():
    for page in pages():
        for line, _, reason in python_blocks(page.read_text(encoding="utf-8")):
            assert reason is None or len(reason) >= 8, f"{page.name}:{line}: 'not run' needs a reason"


def test_every_example_is_run_by_a_test():
    """Each examples/*.py is named in a test file other than this one (which would name them all)."""
    tests = "".join(p.read_text(encoding="utf-8") for p in (ROOT / "tests").glob("test_*.py")
                    if p.name != Path(__file__).name)
    missing = [p.name for p in sorted(EXAMPLES.glob("*.py")) if p.name not in tests]
    assert not missing, f"examples no test runs: {missing}"


def test_mkdocs_build_strict(tmp_path):
    env = dict(os.environ, NO_MKDOCS_2_WARNING="1")
    out = subprocess.run([sys.executable, "-m", "mkdocs", "build", "--strict", "--site-dir", str(tmp_path / "site")],
                         capture_output=True, text=True, cwd=ROOT, env=env, timeout=300, check=False)
    assert out.returncode == 0, out.stderr[-6000:]
    assert (tmp_path / "site" / "index.html").is_file()
    assert (tmp_path / "site" / "api" / "networking" / "index.html").is_file()


RAW_ROLE = re.compile(r":(?:py:)?(?:func|class|meth|mod|data|attr|exc|obj|const):<code>")


def test_api_reference_turns_rest_roles_into_links(tmp_path):
    """The docstrings write cross-references the reST way (``:func:`load_config```); the griffe
    extension docs/api/sphinx_roles.py must turn them into links (or plain code), never leave
    ``:func:`` on the page."""
    env = dict(os.environ, NO_MKDOCS_2_WARNING="1")
    out = subprocess.run([sys.executable, "-m", "mkdocs", "build", "--site-dir", str(tmp_path / "site")],
                         capture_output=True, text=True, cwd=ROOT, env=env, timeout=300, check=False)
    assert out.returncode == 0, out.stderr[-4000:]
    raw = {}
    for page in sorted((tmp_path / "site" / "api").rglob("index.html")):
        hits = RAW_ROLE.findall(page.read_text(encoding="utf-8"))
        if hits:
            raw[str(page.relative_to(tmp_path / "site"))] = len(hits)
    assert not raw, f"reST roles left as text: {raw}"
    # a role to another page became a link: the MLP actor's ``device: where :meth:`act_` collates``
    # names a method it inherits from tmrl.actor, documented on the actor page
    models = (tmp_path / "site" / "api" / "models" / "index.html").read_text(encoding="utf-8")
    assert re.search(r'<a class="autorefs autorefs-internal"[^>]*href="\.\./actor/#tmrl\.actor\.\w+\.act_"', models)


# --- docstrings of the API reference ----------------------------------------------------------

def reference_modules() -> list[str]:
    """The modules the API reference pages render (``::: module`` lines)."""
    names = []
    for page in sorted((DOCS / "api").glob("*.md")):
        for line in page.read_text(encoding="utf-8").splitlines():
            m = re.match(r"^:::\s+([\w.]+)", line)
            if m:
                names.append(m[1])
    return names


def _public_objects(module):
    """Public classes and functions of ``module``: its ``__all__``, else the public names it defines."""
    exported = getattr(module, "__all__", None)
    names = exported if exported is not None else [n for n in vars(module) if not n.startswith("_")]
    for name in names:
        obj = getattr(module, name, None)
        if not (inspect.isclass(obj) or inspect.isfunction(obj)):
            continue
        if exported is None and getattr(obj, "__module__", None) != module.__name__:
            continue  # imported from elsewhere: documented where it is defined
        yield name, obj


def _arguments(func) -> list[str]:
    try:
        sig = inspect.signature(func)
    except (TypeError, ValueError):
        return []
    return [p.name for p in sig.parameters.values()
            if p.name not in ("self", "cls") and p.kind not in (p.VAR_POSITIONAL, p.VAR_KEYWORD)]


def _undocumented(qualname: str, func, context: str = "") -> list[str]:
    """Problems of ``func``'s docstring: none, or arguments it does not name. ``context`` (the class
    docstring, for a method) may name arguments shared by all the methods of a class."""
    doc = inspect.getdoc(func) or ""
    if not doc.strip():
        return [f"{qualname}: no docstring"]
    doc += "\n" + context
    missing = [a for a in _arguments(func) if not re.search(rf"(?<![\w]){re.escape(a)}(?![\w])", doc)]
    return [f"{qualname}: arguments not described: {', '.join(missing)}"] if missing else []


def _protocol_methods(objects) -> dict[str, str]:
    """Methods documented by the Protocols among ``objects``: a class implementing a Protocol's
    method is documented by it (as an override is by its base class)."""
    documented = {}
    for _, obj in objects:
        if inspect.isclass(obj) and getattr(obj, "_is_protocol", False):
            for attr, member in vars(obj).items():
                if inspect.isfunction(member) and (member.__doc__ or "").strip():
                    documented[attr] = member.__doc__
    return documented


def docstring_problems(module_name: str) -> list[str]:
    module = importlib.import_module(module_name)
    problems = []
    if not (module.__doc__ or "").strip():
        problems.append(f"{module_name}: no module docstring")
    objects = list(_public_objects(module))
    by_protocol = _protocol_methods(objects)
    for name, obj in objects:
        qual = f"{module_name}.{name}"
        if inspect.isfunction(obj):
            problems += _undocumented(qual, obj)
            continue
        init = obj.__dict__.get("__init__")
        if init is not None and inspect.isfunction(init):
            # the class docstring or __init__'s describes the constructor's arguments, or, for a
            # subclass that says it takes its base's arguments, a base class's docstring
            doc = "\n".join((inspect.getdoc(c) or "") + "\n" + (c.__dict__.get("__init__").__doc__ or "")
                            if inspect.isfunction(c.__dict__.get("__init__")) else (inspect.getdoc(c) or "")
                            for c in obj.__mro__ if c.__module__.startswith("tmrl"))
            if not (inspect.getdoc(obj) or "").strip():
                problems.append(f"{qual}: no docstring")
            missing = [a for a in _arguments(init) if not re.search(rf"(?<![\w]){re.escape(a)}(?![\w])", doc)]
            if missing:
                problems.append(f"{qual}(): arguments not described: {', '.join(missing)}")
        elif not (obj.__doc__ or "").strip():
            problems.append(f"{qual}: no docstring")
        for attr, member in obj.__dict__.items():
            if attr.startswith("_") or not inspect.isfunction(member):
                continue
            # an override documented by the base class it overrides, or a Protocol's method, is documented
            if not (member.__doc__ or "").strip() and (
                    attr in by_protocol or any((getattr(base.__dict__.get(attr), "__doc__", None) or "").strip()
                                               for base in obj.__mro__[1:])):
                continue
            problems += _undocumented(f"{qual}.{attr}", member, inspect.getdoc(obj) or "")
    return problems


def test_the_api_reference_covers_the_tutorial_api():
    modules = set(reference_modules())
    for name in ("tmrl.networking", "tmrl.util", "tmrl.envs", "tmrl.actor", "tmrl.memory", "tmrl.training",
                 "tmrl.training_offline", "tmrl.realtime"):
        assert name in modules, f"docs/api does not render {name}"


@pytest.mark.parametrize("module_name", reference_modules())
def test_public_names_in_the_reference_have_docstrings_with_their_arguments(module_name):
    problems = docstring_problems(module_name)
    assert not problems, "\n".join(problems)


def test_docstring_check_catches_a_missing_argument():
    src = 'def f(alpha, beta):\n    """Do it.\n\n    Args:\n        alpha: the first.\n    """\n'
    ns: dict = {}
    exec(compile(ast.parse(src), "<t>", "exec"), ns)
    assert _undocumented("f", ns["f"]) == ["f: arguments not described: beta"]
