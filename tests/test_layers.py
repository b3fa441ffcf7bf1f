"""The walls between the package's layers: the import graph of ``tmrl/`` (every ``import`` and
``from ... import`` anywhere in a file, inside functions and ``TYPE_CHECKING`` blocks too, and
``importlib.import_module`` of a literal name) checked against the layer table of
docs/internals.md ("Module map"). A module may import its own layer and the layers below it, never
a higher one, and no two modules may import each other, directly or around a circle.

The checker is tested on small packages written in a temporary folder (an upward import, a
circle, a circle closed by an import inside a function), then run on the real package.
"""

from __future__ import annotations

import ast
import itertools
import re
import textwrap
from dataclasses import dataclass
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
PACKAGE = REPO / "tmrl"
INTERNALS = REPO / "docs" / "internals.md"

# --------------------------------------------------------------------------------------------------
# the checker


@dataclass(frozen=True)
class Import:
    """One import statement of ``importer`` that reaches ``target`` (a module of the package)."""

    importer: str
    target: str
    line: int
    names: str  # what the statement imports, as written

    def where(self, root: Path) -> str:
        return f"{module_file(root, self.importer)}:{self.line} imports {self.names} ({self.target})"


def module_name(root: Path, path: Path) -> str:
    parts = list(path.relative_to(root.parent).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def module_file(root: Path, name: str) -> str:
    rel = Path(*name.split("."))
    base = root.parent / rel
    path = base / "__init__.py" if base.is_dir() else base.with_suffix(".py")
    return str(path.relative_to(root.parent))


def modules_of(root: Path) -> dict[str, Path]:
    return {module_name(root, p): p for p in sorted(root.rglob("*.py"))}


def _owner(name: str, modules: dict[str, Path]) -> str | None:
    """The module ``name`` denotes, or the closest enclosing one (``pkg.mod.attr`` -> ``pkg.mod``)."""
    while name and name not in modules:
        name = name.rpartition(".")[0]
    return name or None


def imports_of(name: str, path: Path, modules: dict[str, Path], top: str) -> list[Import]:
    """Every import of a package module in ``path`` (module ``name``), wherever it stands."""
    tree = ast.parse(path.read_text(encoding="utf-8"), filename=str(path))
    is_package = path.name == "__init__.py"
    found: list[Import] = []

    def add(target: str | None, node: ast.AST, names: str) -> None:
        if target is not None and target != name:
            found.append(Import(name, target, node.lineno, names))

    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for alias in node.names:
                if alias.name == top or alias.name.startswith(top + "."):
                    add(_owner(alias.name, modules), node, alias.name)
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = name.split(".") if is_package else name.split(".")[:-1]
                base = base[: len(base) - (node.level - 1)]
                source = ".".join(base + ([node.module] if node.module else []))
            else:
                source = node.module or ""
            if source != top and not source.startswith(top + "."):
                continue
            for alias in node.names:
                full = f"{source}.{alias.name}"
                add(full if full in modules else _owner(source, modules), node, f"{source}.{alias.name}")
        elif (
            isinstance(node, ast.Call)
            and isinstance(node.func, (ast.Attribute, ast.Name))
            and (node.func.attr if isinstance(node.func, ast.Attribute) else node.func.id) == "import_module"
            and node.args
            and isinstance(node.args[0], ast.Constant)
            and isinstance(node.args[0].value, str)
            and (node.args[0].value == top or node.args[0].value.startswith(top + "."))
        ):
            add(_owner(node.args[0].value, modules), node, f"import_module({node.args[0].value!r})")
    return found


def import_graph(root: Path) -> list[Import]:
    modules = modules_of(root)
    edges: list[Import] = []
    for name, path in modules.items():
        edges.extend(imports_of(name, path, modules, root.name))
    return edges


def layer_table(markdown: str) -> dict[str, int]:
    """``{module pattern: layer}`` from the first table with a ``module`` and a ``layer`` column
    after the "Module map" heading: every back-quoted name in the module cell gets the row's layer;
    ``pkg.*`` covers ``pkg`` and everything under it."""
    section = markdown.split("## Module map", 1)[1]
    table: dict[str, int] = {}
    columns: list[str] | None = None
    for line in section.splitlines():
        if not line.startswith("|"):
            if columns is not None and table:
                break
            continue
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        if columns is None:
            columns = [c.lower() for c in cells]
            continue
        if set("".join(cells)) <= set("-: "):
            continue
        layer = cells[columns.index("layer")]
        if not layer.isdigit():
            continue
        for pattern in re.findall(r"`([A-Za-z_][\w.]*(?:\.\*)?)`", cells[columns.index("module")]):
            table[pattern] = int(layer)
    return table


def layer_of(name: str, table: dict[str, int]) -> int | None:
    """The layer of module ``name``: its own row, else the closest ``pkg.*`` row above it."""
    if name in table:
        return table[name]
    parts = name.split(".")
    for k in range(len(parts), 0, -1):
        pattern = ".".join(parts[:k]) + ".*"
        if pattern in table:
            return table[pattern]
    return None


def unplaced(root: Path, table: dict[str, int]) -> list[str]:
    return [m for m in modules_of(root) if layer_of(m, table) is None]


def upward(root: Path, table: dict[str, int]) -> list[str]:
    """Every import of a higher layer, as ``file:line imports name (module): layer a -> b``."""
    bad = []
    for imp in import_graph(root):
        a, b = layer_of(imp.importer, table), layer_of(imp.target, table)
        if a is not None and b is not None and b > a:
            bad.append(f"{imp.where(root)}: layer {a} -> {b}")
    return bad


def circles(root: Path) -> list[str]:
    """Each import circle (a strongly connected set of modules), with one cycle through it spelt
    out import by import."""
    edges: dict[str, dict[str, Import]] = {}
    for imp in import_graph(root):
        edges.setdefault(imp.importer, {}).setdefault(imp.target, imp)
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    components: list[list[str]] = []

    def visit(v: str) -> None:  # Tarjan's algorithm (the package is small: recursion is fine)
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in edges.get(v, {}):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                components.append(sorted(comp))

    for v in sorted(modules_of(root)):
        if v not in index:
            visit(v)
    reports = []
    for comp in components:
        members = set(comp)
        path, seen = [comp[0]], {comp[0]}
        while True:  # walk inside the component until a module comes back
            nxt = next(w for w in sorted(edges[path[-1]]) if w in members)
            if nxt in seen:
                path = path[path.index(nxt):] + [nxt]
                break
            path.append(nxt)
            seen.add(nxt)
        steps = "; ".join(edges[a][b].where(root) for a, b in itertools.pairwise(path))
        reports.append(f"{' -> '.join(path)}: {steps}")
    return reports


# --------------------------------------------------------------------------------------------------
# the checker on planted packages

TABLE = """
## Module map

| module | layer | holds |
|---|---|---|
| `pkg.low`, `pkg.other` | 1 | foundations |
| `pkg.high` | 2 | above |
| `pkg.compat.*` | 3 | compatibility |
| `bench` | - | not a layer |
"""


def _package(tmp_path: Path, files: dict[str, str]) -> Path:
    root = tmp_path / "pkg"
    for rel, text in {"__init__.py": "", "compat/__init__.py": "", **files}.items():
        (root / rel).parent.mkdir(parents=True, exist_ok=True)
        (root / rel).write_text(textwrap.dedent(text))
    return root


def test_the_table_is_read_with_package_patterns():
    table = layer_table(TABLE)
    assert table == {"pkg.low": 1, "pkg.other": 1, "pkg.high": 2, "pkg.compat.*": 3}
    assert layer_of("pkg.compat", table) == 3 and layer_of("pkg.compat.deep.mod", table) == 3
    assert layer_of("pkg.lower", table) is None


def test_a_clean_package_passes(tmp_path):
    root = _package(tmp_path, {
        "low.py": "import os\n",
        "other.py": "from pkg import low\n",
        "high.py": "from pkg.low import x\nfrom . import other\n",
        "compat/shim.py": "from pkg.high import y\n",
    })
    table = layer_table(TABLE)
    assert unplaced(root, table) == ["pkg"] and unplaced(root, {**table, "pkg": 3}) == []
    assert upward(root, table) == [] and circles(root) == []


def test_an_upward_import_is_named_with_its_file_and_line(tmp_path):
    root = _package(tmp_path, {"low.py": "import os\nfrom pkg.high import thing\n", "high.py": "", "other.py": ""})
    assert upward(root, layer_table(TABLE)) == [
        "pkg/low.py:2 imports pkg.high.thing (pkg.high): layer 1 -> 2"
    ]


def test_importing_a_compatibility_module_from_below_is_upward(tmp_path):
    root = _package(tmp_path, {"high.py": "import pkg.compat.shim\n", "compat/shim.py": "", "low.py": "",
                               "other.py": ""})
    assert upward(root, layer_table(TABLE)) == ["pkg/high.py:1 imports pkg.compat.shim (pkg.compat.shim): layer 2 -> 3"]


def test_a_circle_within_one_layer_is_found(tmp_path):
    root = _package(tmp_path, {"low.py": "from pkg import other\n", "other.py": "from .low import f\n",
                               "high.py": ""})
    assert upward(root, layer_table(TABLE)) == []
    assert circles(root) == [
        (
            "pkg.low -> pkg.other -> pkg.low: pkg/low.py:1 imports pkg.other (pkg.other); "
            "pkg/other.py:1 imports pkg.low.f (pkg.low)"
        )
    ]


def test_a_lazy_import_inside_a_function_closes_a_circle(tmp_path):
    root = _package(tmp_path, {
        "low.py": "def f():\n    from pkg.other import g\n    return g\n",
        "other.py": "import pkg.low\n",
        "high.py": "",
    })
    assert len(circles(root)) == 1 and "pkg/low.py:2" in circles(root)[0]


def test_type_checking_and_import_module_count_too(tmp_path):
    root = _package(tmp_path, {
        "low.py": "from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    from pkg.high import H\n",
        "other.py": "import importlib\ndef f():\n    return importlib.import_module('pkg.high')\n",
        "high.py": "",
    })
    assert [line.split(" ")[0] for line in upward(root, layer_table(TABLE))] == ["pkg/low.py:3", "pkg/other.py:3"]


# --------------------------------------------------------------------------------------------------
# the real package


@pytest.fixture(scope="module")
def table() -> dict[str, int]:
    return layer_table(INTERNALS.read_text(encoding="utf-8"))


def test_every_module_of_the_package_has_a_layer_in_docs_internals(table):
    missing = unplaced(PACKAGE, table)
    assert missing == [], f"add these modules to the module map of docs/internals.md: {missing}"


def test_no_module_imports_a_higher_layer(table):
    bad = upward(PACKAGE, table)
    assert bad == [], "upward imports (a lower layer must not import a higher one):\n" + "\n".join(bad)


def test_no_import_circle():
    found = circles(PACKAGE)
    assert found == [], "import circles:\n" + "\n".join(found)


def test_no_module_is_over_800_lines():
    long = {str(p.relative_to(REPO)): n for p in PACKAGE.rglob("*.py")
            if (n := len(p.read_text(encoding="utf-8").splitlines())) > 800}
    assert long == {}, f"split these modules along their jobs (docs/internals.md): {long}"
