"""Test support: two ``ast`` rules that keep the code portable to Windows and macOS (not a test
module; tests/test_portability.py runs them on the repository and on planted examples).

**POSIX-only names** (:func:`posix_only_uses`). Windows has no ``os.killpg``, no ``os.getppid``
that changes when the parent dies, no ``signal.SIGKILL``/``SIGHUP``/``SIGSTOP``/``SIGUSR1``/
``SIGUSR2``, no ``start_new_session`` or ``preexec_fn``, no ``/proc`` and no ``fcntl`` (nor
``termios``, ``resource``, ``pwd``, ``grp``, ``pty``); ``Popen.send_signal(SIGINT)`` raises there.
The names of ``os``, ``signal`` and ``select`` are those the Windows emulation removes
(tests/emulation/sitecustomize.py: ``os.getloadavg``, ``os.set_blocking``, ``select.poll``, ...),
with ``os.getppid`` and ``os.fork``.
Such a use is allowed only in ``tmrl/platform.py`` or inside an explicit platform branch:

- an ``if`` (or ``... if ... else ...``) whose test reads ``sys.platform``, ``os.name``,
  ``platform.system()``, ``hasattr(os|signal|select, ...)`` or a platform flag (a name or an
  attribute called ``POSIX``, ``WINDOWS``, ``LINUX`` or ``MACOS``, as ``tmrl.platform`` exports);
  its body and its ``else`` are both branches, and so is what follows an ``if`` of that kind whose
  body always leaves (``return``/``raise``/``continue``/``break``);
- the right of an ``and``/``or`` whose left reads the platform as above;
- the body of a ``try`` that catches ``ImportError``/``ModuleNotFoundError`` (for an import) or
  ``AttributeError`` (for a name of ``os``/``signal``), or any ``Exception``;
- in tests/ only: the body of a function in a test function, class or module marked ``linux`` or
  ``posix`` (``@pytest.mark.linux``, or ``pytestmark``): tests/conftest.py skips those off Linux
  or POSIX, so their bodies never run there. What runs when pytest collects the module on every
  OS stays under the rule: module-level statements, class bodies, decorators (a
  ``parametrize`` list) and default arguments.

**Untimed waits** (:func:`untimed_waits`). On Windows, Ctrl-C does not interrupt a thread blocked
in ``lock.acquire()``, ``queue.get()``, ``thread.join()``, ``event.wait()``, ``popen.wait()`` or
``popen.communicate()`` with no timeout (CPython 3.10 to 3.12): the program ignores Ctrl-C until
the wait ends, maybe never. The rule flags a call of one of those methods with no argument, or
only ``True`` or ``None`` (``get(True)``, ``join(None)``), and no ``timeout=`` other than ``None``
(``get(block=False)``/``acquire(blocking=False)`` do not block;
``dict.get`` and ``str.join`` always have an argument; a call in an ``async def`` runs on an event
loop, not on a blocked thread). It cannot tell a main thread from a background one: a deliberate wait on a
daemon thread is listed with its reason where the rule is run.
"""

from __future__ import annotations

import ast
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def _removed_by_the_emulation() -> dict[str, tuple[str, ...]]:
    """The emulation's lists of what Windows lacks (``OS_NAMES``, ``SIGNAL_NAMES``, ...), read from
    its source: running it would emulate Windows in this process when ``TMRL_EMULATE`` is set."""
    tree = ast.parse((Path(__file__).parent / "emulation" / "sitecustomize.py").read_text(encoding="utf-8"))
    return {stmt.targets[0].id: ast.literal_eval(stmt.value) for stmt in tree.body
            if isinstance(stmt, ast.Assign) and isinstance(stmt.targets[0], ast.Name)
            and stmt.targets[0].id.endswith("_NAMES")}


_WINDOWS = _removed_by_the_emulation()
POSIX_OS = frozenset({"getppid", "fork", *_WINDOWS["OS_NAMES"]})
POSIX_SIGNALS = frozenset(_WINDOWS["SIGNAL_NAMES"])
POSIX_SELECT = frozenset(_WINDOWS["SELECT_NAMES"])
POSIX_MODULES = frozenset({"fcntl", "termios", "resource", "pwd", "grp", "pty"})
POSIX_KEYWORDS = frozenset({"start_new_session", "preexec_fn"})
PLATFORM_FLAGS = frozenset({"POSIX", "WINDOWS", "LINUX", "MACOS"})
PLATFORM_MARKERS = frozenset({"linux", "posix"})
WAIT_METHODS = frozenset({"wait", "join", "get", "acquire", "communicate"})


@dataclass(frozen=True)
class Finding:
    """One use the rule refuses: where, which rule, and the code as written."""

    path: str  # relative to the repository, with /
    line: int
    rule: str
    code: str

    def __str__(self) -> str:
        return f"{self.path}:{self.line}: {self.rule}: {self.code}"


# --------------------------------------------------------------------------------------------------
# what a platform branch looks like


def _dotted(node: ast.AST) -> str:
    if isinstance(node, ast.Name):
        return node.id
    if isinstance(node, ast.Attribute):
        return f"{_dotted(node.value)}.{node.attr}"
    if isinstance(node, ast.Call):
        return f"{_dotted(node.func)}()"
    return ""


def reads_platform(test: ast.AST) -> bool:
    """Whether an ``if`` test (or a part of it) asks which platform this is."""
    for node in ast.walk(test):
        name = _dotted(node)
        if name in ("sys.platform", "os.name", "platform.system()", "platform.system"):
            return True
        if isinstance(node, (ast.Name, ast.Attribute)) and name.rsplit(".", 1)[-1] in PLATFORM_FLAGS:
            return True
        if (isinstance(node, ast.Call) and _dotted(node.func) == "hasattr" and node.args
                and _dotted(node.args[0]) in ("os", "signal", "select")):
            return True
    return False


def _leaves(body: list[ast.stmt]) -> bool:
    return bool(body) and isinstance(body[-1], (ast.Return, ast.Raise, ast.Continue, ast.Break))


def _catches(handler: ast.ExceptHandler, names: set[str]) -> bool:
    kinds = handler.type.elts if isinstance(handler.type, ast.Tuple) else [handler.type]
    return any(kind is not None and _dotted(kind) in names for kind in kinds)


def _marked(decorators: Iterable[ast.expr]) -> bool:
    for dec in decorators:
        target = dec.func if isinstance(dec, ast.Call) else dec
        name = _dotted(target)
        if name.startswith("pytest.mark.") and name.rsplit(".", 1)[-1] in PLATFORM_MARKERS:
            return True
    return False


def _module_marked(tree: ast.Module) -> bool:
    for stmt in tree.body:
        if isinstance(stmt, ast.Assign) and any(_dotted(t) == "pytestmark" for t in stmt.targets):
            marks = stmt.value.elts if isinstance(stmt.value, (ast.List, ast.Tuple)) else [stmt.value]
            if _marked(marks):
                return True
    return False


def _docstrings(tree: ast.Module) -> set[int]:
    """The ids of the string constants that are docstrings (they may name /proc freely)."""
    found = set()
    for node in ast.walk(tree):
        if isinstance(node, (ast.Module, ast.ClassDef, ast.FunctionDef, ast.AsyncFunctionDef)):
            body = node.body
            if body and isinstance(body[0], ast.Expr) and isinstance(body[0].value, ast.Constant):
                found.add(id(body[0].value))
    return found


# --------------------------------------------------------------------------------------------------
# the POSIX-only rule


class _PosixVisitor(ast.NodeVisitor):
    def __init__(self, path: str, source: str, tests: bool, docstrings: set[int]) -> None:
        self.path, self.lines, self.tests, self.docstrings = path, source.splitlines(), tests, docstrings
        self.branch = 0  # > 0 inside a platform branch
        self.marked_scopes = 0  # > 0 inside a class (or module) marked linux or posix
        self.catching: list[set[str]] = []  # exceptions caught around the current node
        self.findings: list[Finding] = []

    def report(self, node: ast.AST, rule: str, *, caught_by: str = "") -> None:
        if self.branch or (caught_by and any(caught_by in names for names in self.catching)):
            return
        code = self.lines[node.lineno - 1].strip()
        self.findings.append(Finding(self.path, node.lineno, rule, code))

    def _in_branch(self, nodes: Iterable[ast.AST]) -> None:
        self.branch += 1
        for node in nodes:
            self.visit(node)
        self.branch -= 1

    def _block(self, body: list[ast.stmt]) -> None:
        """A list of statements, where an ``if <platform>: ... return`` makes the rest a branch."""
        for i, stmt in enumerate(body):
            self.visit(stmt)
            if isinstance(stmt, ast.If) and reads_platform(stmt.test) and _leaves(stmt.body):
                self._in_branch(body[i + 1:])
                return

    def generic_visit(self, node: ast.AST) -> None:
        for field, value in ast.iter_fields(node):
            if isinstance(value, list) and value and isinstance(value[0], ast.stmt):
                self._block(value)
            elif isinstance(value, list):
                for item in value:
                    if isinstance(item, ast.AST):
                        self.visit(item)
            elif isinstance(value, ast.AST):
                self.visit(value)

    def visit_If(self, node: ast.If | ast.IfExp) -> None:
        if reads_platform(node.test):
            self.visit(node.test)
            self._in_branch([node.body] if isinstance(node, ast.IfExp) else node.body)
            self._in_branch([node.orelse] if isinstance(node, ast.IfExp) else node.orelse)
        else:
            self.generic_visit(node)

    visit_IfExp = visit_If

    def visit_BoolOp(self, node: ast.BoolOp) -> None:
        for i, value in enumerate(node.values):
            self.visit(value)
            if reads_platform(value):
                self._in_branch(node.values[i + 1:])
                return

    def visit_Try(self, node: ast.Try) -> None:
        caught = set()
        for handler in node.handlers:
            if handler.type is None or _catches(handler, {"Exception", "BaseException"}):
                caught |= {"ImportError", "AttributeError"}
            if _catches(handler, {"ImportError", "ModuleNotFoundError"}):
                caught.add("ImportError")
            if _catches(handler, {"AttributeError"}):
                caught.add("AttributeError")
        self.catching.append(caught)
        self._block(node.body)
        self.catching.pop()
        for handler in node.handlers:
            self.visit(handler)
        self._block(node.orelse)
        self._block(node.finalbody)

    def visit_ClassDef(self, node: ast.ClassDef) -> None:
        marked = self.tests and _marked(node.decorator_list)
        self.marked_scopes += marked  # its methods run only where the marker lets them
        self.generic_visit(node)
        self.marked_scopes -= marked

    def visit_FunctionDef(self, node: ast.FunctionDef | ast.AsyncFunctionDef) -> None:
        # Decorators, defaults and annotations run at import, when pytest collects the module on
        # every OS: only the body is behind the marker.
        for part in (*node.decorator_list, node.args, node.returns):
            if part is not None:
                self.visit(part)
        marked = bool(self.marked_scopes) or (self.tests and _marked(node.decorator_list))
        self.branch += marked
        self._block(node.body)
        self.branch -= marked

    visit_AsyncFunctionDef = visit_FunctionDef

    def visit_Attribute(self, node: ast.Attribute) -> None:
        owner = _dotted(node.value)
        if owner == "os" and node.attr in POSIX_OS:
            self.report(node, f"os.{node.attr} (POSIX only)", caught_by="AttributeError")
        elif owner == "signal" and node.attr in POSIX_SIGNALS:
            self.report(node, f"signal.{node.attr} (POSIX only)", caught_by="AttributeError")
        elif owner == "select" and node.attr in POSIX_SELECT:
            self.report(node, f"select.{node.attr} (POSIX only)", caught_by="AttributeError")
        self.generic_visit(node)

    def visit_ImportFrom(self, node: ast.ImportFrom) -> None:
        top = (node.module or "").split(".")[0]
        if top in POSIX_MODULES:
            self.report(node, f"import {top} (no such module on Windows)", caught_by="ImportError")
        for alias in node.names:
            if (node.module == "os" and alias.name in POSIX_OS) or (
                    node.module == "signal" and alias.name in POSIX_SIGNALS) or (
                    node.module == "select" and alias.name in POSIX_SELECT):
                self.report(node, f"{node.module}.{alias.name} (POSIX only)", caught_by="ImportError")

    def visit_Import(self, node: ast.Import) -> None:
        for alias in node.names:
            top = alias.name.split(".")[0]
            if top in POSIX_MODULES:
                self.report(node, f"import {top} (no such module on Windows)", caught_by="ImportError")

    def visit_Call(self, node: ast.Call) -> None:
        func = node.func
        if (isinstance(func, ast.Attribute) and func.attr == "send_signal" and node.args
                and _dotted(node.args[0]).rsplit(".", 1)[-1] == "SIGINT"):
            self.report(node, "send_signal(SIGINT) (Popen refuses it on Windows)")
        for kw in node.keywords:
            if kw.arg in POSIX_KEYWORDS and not (isinstance(kw.value, ast.Constant) and not kw.value.value):
                self.report(node, f"{kw.arg}= (POSIX only)")
        self.generic_visit(node)

    def visit_Constant(self, node: ast.Constant) -> None:
        if isinstance(node.value, str) and id(node) not in self.docstrings and (
                node.value == "/proc" or node.value.startswith("/proc/")):
            self.report(node, "/proc path (Linux only)")

    def visit_JoinedStr(self, node: ast.JoinedStr) -> None:
        first = node.values[0] if node.values else None
        if isinstance(first, ast.Constant) and isinstance(first.value, str) and first.value.startswith("/proc"):
            self.report(node, "/proc path (Linux only)")
        for value in node.values:  # (the constant parts are this string: reported once)
            if not isinstance(value, ast.Constant):
                self.visit(value)


def posix_only_uses(path: Path, *, tests: bool = False, root: Path = REPO) -> list[Finding]:
    """The POSIX-only uses of one file outside a platform branch (``tests``: the linux and posix
    markers count as branches)."""
    source = path.read_text(encoding="utf-8")
    tree = ast.parse(source, filename=str(path))
    visitor = _PosixVisitor(path.relative_to(root).as_posix(), source, tests, _docstrings(tree))
    visitor.marked_scopes = int(tests and _module_marked(tree))
    visitor.visit(tree)
    return visitor.findings


# --------------------------------------------------------------------------------------------------
# the untimed-wait rule


def _untimed_args(args: list[ast.expr]) -> bool:
    """No argument, or only ``True`` (block) or ``None`` (no timeout): ``get(True)``, ``join(None)``."""
    return len(args) <= 1 and all(isinstance(a, ast.Constant) and (a.value is True or a.value is None)
                                  for a in args)


def _blocking_wait(node: ast.Call) -> str | None:
    if not isinstance(node.func, ast.Attribute) or node.func.attr not in WAIT_METHODS:
        return None
    if not _untimed_args(node.args):
        return None
    kwargs = {kw.arg: kw.value for kw in node.keywords}
    timeout = kwargs.get("timeout")
    if (timeout is not None and not (isinstance(timeout, ast.Constant) and timeout.value is None)) or None in kwargs:
        return None  # timed, or **kwargs we cannot read
    for flag in ("block", "blocking"):
        value = kwargs.get(flag)
        if isinstance(value, ast.Constant) and value.value is False:
            return None
    return f".{node.func.attr}() without a timeout (Ctrl-C cannot interrupt it on Windows)"


def untimed_waits(path: Path, *, root: Path = REPO) -> list[Finding]:
    """The blocking waits of one file that have no timeout (those in coroutines excepted)."""
    source = path.read_text(encoding="utf-8")
    tree = ast.parse(source, filename=str(path))
    # a coroutine's waits run on an event loop: the thread is not blocked in them
    in_coroutines = {id(node) for fn in ast.walk(tree) if isinstance(fn, ast.AsyncFunctionDef)
                     for node in ast.walk(fn)}
    lines, rel = source.splitlines(), path.relative_to(root).as_posix()
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Call) and id(node) not in in_coroutines and (rule := _blocking_wait(node)):
            found.append(Finding(rel, node.lineno, rule, lines[node.lineno - 1].strip()))
    return sorted(found, key=lambda f: f.line)


def python_files(*folders: str, root: Path = REPO) -> Iterator[Path]:
    """Every ``.py`` file under the given folders of ``root``, in a stable order."""
    for folder in folders:
        yield from sorted((root / folder).rglob("*.py"))
