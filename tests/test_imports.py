"""Import is free: importing every tmrl module reads no config, creates no folder or file, writes
nothing in HOME or the working directory, configures no logging and starts no thread."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap

# The compatibility modules whose documented job is to read config.json when imported.
READS_CONFIG = ["tmrl.config.config_constants", "tmrl.config.config_objects"]

IMPORT_ALL = textwrap.dedent(
    """
    import importlib, json, logging, pkgutil, sys, threading
    import tmrl

    skip = set(json.loads(sys.argv[1]))
    names, failures = [], {}

    def on_error(name):
        failures[name] = repr(sys.exc_info()[1])

    for info in pkgutil.walk_packages(tmrl.__path__, "tmrl.", onerror=on_error):
        if info.name in skip:
            continue
        try:
            importlib.import_module(info.name)
            names.append(info.name)
        except BaseException as e:  # noqa: BLE001 (reported to the test)
            failures[info.name] = f"{type(e).__name__}: {e}"
    root = logging.getLogger()
    print(json.dumps({
        "imported": names,
        "failures": failures,
        "root_handlers": len(root.handlers),
        "root_level": root.level,
        "threads": sorted(t.name for t in threading.enumerate() if t is not threading.main_thread()),
        "constants_loaded": [n for n in skip if n in sys.modules],
    }))
    """
)


def test_importing_every_module_creates_and_reads_nothing(tmp_path):
    data = tmp_path / "missing" / "TmrlData"
    home = tmp_path / "home"
    home.mkdir()
    cwd = tmp_path / "cwd"
    cwd.mkdir()
    env = dict(os.environ, TMRL_DATA=str(data), HOME=str(home), USERPROFILE=str(home))
    env.pop("TMRL_CONFIG_OVERRIDE", None)
    out = subprocess.run(
        [sys.executable, "-c", IMPORT_ALL, json.dumps(READS_CONFIG)],
        capture_output=True, text=True, env=env, cwd=cwd, timeout=300, check=False,
    )
    assert out.returncode == 0, out.stderr
    report = json.loads(out.stdout.strip().splitlines()[-1])
    assert report["failures"] == {}, report["failures"]
    assert "tmrl.config.loader" in report["imported"] and "tmrl.cli" in report["imported"]
    assert report["constants_loaded"] == [], "a module imported a compatibility module at import time"
    assert not data.exists() and not data.parent.exists()
    assert list(home.iterdir()) == []
    assert list(cwd.iterdir()) == []
    assert report["root_handlers"] == 0, "a module configured logging at import"
    assert report["root_level"] == 30
    assert report["threads"] == [], "a module started a thread at import"


def test_importing_tmrl_imports_no_optional_transport_library():
    """The NATS backend is registered in tmrl.transport.BACKENDS, but its client library (nats-py)
    is imported by a NATS link's thread only; tlspyo and Twisted run in the network processes."""
    code = (
        "import sys, tmrl, tmrl.transport, tmrl.networking, tmrl.cli, tmrl.transport.nats_backend; "
        "from tmrl.transport import BACKENDS; assert 'nats' in BACKENDS; "
        "print(sorted(m for m in ('nats', 'tlspyo', 'twisted') if m in sys.modules))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300, check=False)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "[]"


def test_config_constants_creates_nothing_either(tmp_path):
    data = tmp_path / "missing"
    home = tmp_path / "home"
    home.mkdir()
    env = dict(os.environ, TMRL_DATA=str(data), HOME=str(home))
    env.pop("TMRL_CONFIG_OVERRIDE", None)
    out = subprocess.run(
        [sys.executable, "-c", "import tmrl.config.config_constants as c; print(c.TMRL_FOLDER)"],
        capture_output=True, text=True, env=env, cwd=tmp_path, timeout=120, check=False,
    )
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == str(data)
    assert not data.exists() and list(home.iterdir()) == []


def test_no_class_defines_a_method_twice():
    """A second ``def`` of the same name in a class body silently replaces the first (a worker's
    pacing method was once shadowed that way): none in the package."""
    import ast
    import importlib.util
    from pathlib import Path

    root = Path(importlib.util.find_spec("tmrl").origin).parent
    doubles = []
    for path in sorted(root.rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ClassDef):
                seen: set[str] = set()
                for item in node.body:
                    if isinstance(item, (ast.FunctionDef, ast.AsyncFunctionDef)):
                        decorated = any(
                            isinstance(d, ast.Attribute) and d.attr in ("setter", "deleter") for d in item.decorator_list
                        )
                        if item.name in seen and not decorated:
                            doubles.append(f"{path.relative_to(root)}: {node.name}.{item.name}")
                        seen.add(item.name)
    assert doubles == []
