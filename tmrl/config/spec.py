"""The value types of the configuration schema: what a key of ``config.json`` may hold.

Each key of the table (:data:`tmrl.config.schema.SCHEMA`) is one :class:`Spec`: a boolean
(:class:`Bool`), an integer (:class:`Int`), a number (:class:`Number`), a string (:class:`Str`), one
of a set (:class:`Choice`), a fixed-length list of numbers (:class:`NumberList`), free-form data
(:class:`AnyDict`, :class:`AnyList`) or a nested section of keys (:class:`Section`). A spec checks a
value and normalises it; a violation is a :class:`SchemaViolation` naming the key path, which the
loader turns into a one-line :class:`ConfigError`.

Nothing here reads a file or touches the disk at import.
"""

from __future__ import annotations

import copy
import difflib
import json
import math
from collections.abc import Mapping, Sequence
from typing import Any

from tmrl.errors import UserError

__all__ = [
    "NO_CLASS_DEFAULT",
    "AnyDict",
    "AnyList",
    "Bool",
    "Choice",
    "ConfigError",
    "Int",
    "Number",
    "NumberList",
    "SchemaViolation",
    "Section",
    "Spec",
    "Str",
    "fmt_number",
    "join_key",
    "show",
]


class ConfigError(UserError):
    """A configuration mistake. ``str(err)`` is one line: where the value came from (the file, or
    ``--config``), the full key path, the value found and what is expected."""


class SchemaViolation(Exception):
    """Raised by :meth:`Spec.check`; the loader turns it into a :class:`ConfigError` by adding the
    source (file name or ``--config``) in front of the message.

    Args:
        path: the full key path of the bad value (``"ALG.LR_ACTOR"``; empty for the top level).
        message: the one-line explanation, starting with the key path.
    """

    def __init__(self, path: str, message: str):
        super().__init__(message)
        self.path = path
        self.message = message


class _NoClassDefault:
    def __repr__(self) -> str:
        return "<no class default>"


NO_CLASS_DEFAULT: Any = _NoClassDefault()
"""``Spec.class_default`` of a key whose argument has no default of its own in the class."""


def show(value: Any, limit: int = 80) -> str:
    """Render a found value the way it would be written in JSON (``"fast"``, ``true``, ``null``),
    shortened to ``limit`` characters so that an error stays on one line."""
    try:
        text = json.dumps(value, ensure_ascii=False)
    except (TypeError, ValueError):
        text = repr(value)
    text = " ".join(text.split())
    if len(text) > limit:
        text = text[: limit - 3] + "..."
    return text


def join_key(path: str, key: str) -> str:
    """The full path of ``key`` inside the section at ``path`` (``"ALG.LR_ACTOR"``; ``path`` is
    ``""`` for the top level)."""
    return f"{path}.{key}" if path else key


def fmt_number(x: float) -> str:
    """``x`` written for a message: ``3`` for 3.0, ``0.5`` for 0.5."""
    return str(int(x)) if float(x).is_integer() and abs(x) < 1e15 else repr(x)


class Spec:
    """One key of the schema.

    Args:
        default: the value a missing key takes (deep-copied on use).
        doc: one-line meaning, shown in ``docs/config.md``.
        nullable: ``null`` (Python ``None``) is accepted as well.
        feeds: the constructor arguments this key sets, as ``"Class.argument"`` (for example
            ``"SACAgent.lr_actor"``); :func:`arguments` collects them for one class, and a test
            checks that each class takes each argument.
        class_default: the default of that argument in the class's own signature, when the class
            has one of its own (a script that builds ``SACAgent(...)`` without the argument gets
            it; ``config.json`` gets ``default``). A test checks the signatures against it.
    """

    kind = "value"

    def __init__(
        self,
        default: Any,
        doc: str,
        *,
        nullable: bool = False,
        feeds: Sequence[str] = (),
        class_default: Any = NO_CLASS_DEFAULT,
    ):
        self.default = default
        self.doc = doc
        self.nullable = nullable
        self.feeds = tuple(feeds)
        self.class_default = class_default

    @property
    def expected(self) -> str:
        """What a valid value is, as a phrase that completes "must be ..."."""
        raise NotImplementedError

    def describe(self) -> str:
        """The expected phrase including ``or null`` for nullable keys."""
        return self.expected + (" or null" if self.nullable else "")

    def default_value(self) -> Any:
        """A deep copy of :attr:`default` (so that a caller may modify it)."""
        return copy.deepcopy(self.default)

    def check(self, value: Any, path: str, *, fill: bool = True) -> Any:
        """Validate ``value`` found at ``path`` and return it normalised (ints to floats for
        numbers, canonical spelling for choices, tuples to lists).

        Args:
            value: the value found in the configuration (already parsed from JSON).
            path: its full key path, used in the error message (``""`` for the top level).
            fill: sections fill missing keys with defaults (False to validate a partial override).

        Returns:
            The normalised value (``None`` for ``null`` when the key is nullable).

        Raises:
            SchemaViolation: naming ``path``, the value and :meth:`describe`.
        """
        if value is None and self.nullable:
            return None
        return self._check(value, path, fill=fill)

    def _check(self, value: Any, path: str, *, fill: bool) -> Any:
        raise NotImplementedError

    def fail(self, path: str, value: Any) -> SchemaViolation:
        """The error for a wrong ``value`` at ``path`` ("<path> must be <expected>, got <value>"),
        returned for the caller to raise.

        Args:
            path: the full key path of the value.
            value: the value found.
        """
        return SchemaViolation(path, f"{path} must be {self.describe()}, got {show(value)}")


class Bool(Spec):
    """``true`` or ``false`` (a JSON boolean: ``0``, ``1`` and strings are refused). Takes the
    arguments of :class:`Spec`."""

    kind = "bool"

    @property
    def expected(self) -> str:
        return "true or false"

    def _check(self, value: Any, path: str, *, fill: bool) -> Any:
        if not isinstance(value, bool):
            raise self.fail(path, value)
        return value


class Int(Spec):
    """An integer, optionally bounded (inclusive). An integral float such as ``1e6`` is accepted
    and converted, since JSON writers often produce them; booleans are refused.

    Args:
        default: see :class:`Spec`.
        doc: see :class:`Spec`.
        min: the smallest value allowed (inclusive), None for no lower bound.
        max: the largest value allowed (inclusive), None for no upper bound.
        nullable: see :class:`Spec`.
        **table: ``feeds`` and ``class_default``, see :class:`Spec`.
    """

    kind = "integer"

    def __init__(
        self,
        default: Any,
        doc: str,
        *,
        min: int | None = None,
        max: int | None = None,
        nullable: bool = False,
        **table: Any,
    ):
        super().__init__(default, doc, nullable=nullable, **table)
        self.min = min
        self.max = max

    @property
    def expected(self) -> str:
        lo, hi = self.min, self.max
        if lo is not None and hi is not None:
            return f"an integer from {lo} to {hi}"
        if lo == 1:
            return "a positive integer"
        if lo == 0:
            return "a non-negative integer"
        if lo is not None:
            return f"an integer >= {lo}"
        if hi is not None:
            return f"an integer <= {hi}"
        return "an integer"

    def _check(self, value: Any, path: str, *, fill: bool) -> Any:
        if isinstance(value, bool):
            raise self.fail(path, value)
        if isinstance(value, float) and math.isfinite(value) and value.is_integer():
            value = int(value)
        if not isinstance(value, int):
            raise self.fail(path, value)
        if (self.min is not None and value < self.min) or (self.max is not None and value > self.max):
            raise self.fail(path, value)
        return value


class Number(Spec):
    """A finite real number (an integer is accepted and converted to float), optionally bounded.

    Args:
        default: see :class:`Spec`.
        doc: see :class:`Spec`.
        min: the lower bound, None for none.
        max: the upper bound, None for none.
        min_open: the lower bound itself is refused (``min < value``).
        max_open: the upper bound itself is refused (``value < max``).
        nullable: see :class:`Spec`.
        **table: ``feeds`` and ``class_default``, see :class:`Spec`.
    """

    kind = "number"

    def __init__(
        self,
        default: Any,
        doc: str,
        *,
        min: float | None = None,
        max: float | None = None,
        min_open: bool = False,
        max_open: bool = False,
        nullable: bool = False,
        **table: Any,
    ):
        super().__init__(default, doc, nullable=nullable, **table)
        self.min = min
        self.max = max
        self.min_open = min_open
        self.max_open = max_open

    @property
    def expected(self) -> str:
        lo, hi = self.min, self.max
        if lo is not None and hi is not None:
            left = "(" if self.min_open else "["
            right = ")" if self.max_open else "]"
            return f"a number in {left}{fmt_number(lo)}, {fmt_number(hi)}{right}"
        if lo == 0 and hi is None:
            return "a positive number" if self.min_open else "a non-negative number"
        if lo is not None:
            return f"a number {'>' if self.min_open else '>='} {fmt_number(lo)}"
        if hi is not None:
            return f"a number {'<' if self.max_open else '<='} {fmt_number(hi)}"
        return "a number"

    def _check(self, value: Any, path: str, *, fill: bool) -> Any:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise self.fail(path, value)
        value = float(value)
        if not math.isfinite(value):
            raise self.fail(path, value)
        if self.min is not None and (value < self.min or (self.min_open and value == self.min)):
            raise self.fail(path, value)
        if self.max is not None and (value > self.max or (self.max_open and value == self.max)):
            raise self.fail(path, value)
        return value


class Str(Spec):
    """A string.

    Args:
        default: see :class:`Spec`.
        doc: see :class:`Spec`.
        nonempty: the empty string (or only spaces) is refused.
        forbid: characters the string may not contain (for names used in file names); when not
            empty, ``"."`` and ``".."`` are refused too.
        filename: the string becomes a file or folder name: what any of Linux, Windows and macOS
            refuses is refused everywhere (:func:`tmrl.platform.name_problem`), so that a config
            written on one system works on the others.
        nullable: see :class:`Spec`.
        **table: ``feeds`` and ``class_default``, see :class:`Spec`.
    """

    kind = "string"

    def __init__(self, default: Any, doc: str, *, nonempty: bool = False, forbid: str = "",
                 filename: bool = False, nullable: bool = False, **table: Any):
        super().__init__(default, doc, nullable=nullable, **table)
        self.nonempty = nonempty
        self.forbid = forbid
        self.filename = filename

    @property
    def expected(self) -> str:
        text = "a non-empty string" if self.nonempty else "a string"
        if self.forbid:
            text += " without " + " or ".join(self.forbid)
        if self.filename:
            text += " that every system accepts as a file name"
        return text

    def _check(self, value: Any, path: str, *, fill: bool) -> Any:
        if not isinstance(value, str):
            raise self.fail(path, value)
        if self.nonempty and not value.strip():
            raise self.fail(path, value)
        if any(c in value for c in self.forbid) or (self.forbid and value.strip() in (".", "..")):
            raise self.fail(path, value)
        if self.filename:
            from tmrl.platform import name_problem

            problem = name_problem(value)
            if problem is not None:
                raise SchemaViolation(path, f"{path} {show(value)} cannot name a file on every system: {problem}; "
                                            f"choose another {path}")
        return value


class Choice(Spec):
    """One string out of a fixed set, matched case-insensitively and returned in its canonical
    spelling (``"redqsac"`` becomes ``"REDQSAC"``).

    Args:
        default: see :class:`Spec`.
        doc: see :class:`Spec`.
        options: the allowed values, in their canonical spelling.
        nullable: see :class:`Spec`.
        **table: ``feeds`` and ``class_default``, see :class:`Spec`.
    """

    kind = "choice"

    def __init__(self, default: str, doc: str, options: Sequence[str], *, nullable: bool = False,
                 **table: Any):
        super().__init__(default, doc, nullable=nullable, **table)
        self.options = tuple(options)

    @property
    def expected(self) -> str:
        return "one of " + ", ".join(json.dumps(o) for o in self.options)

    def _check(self, value: Any, path: str, *, fill: bool) -> Any:
        if isinstance(value, str):
            wanted = value.strip().casefold()
            for option in self.options:
                if option.casefold() == wanted:
                    return option
        raise self.fail(path, value)


class NumberList(Spec):
    """A list (or tuple) of exactly ``length`` numbers, each within the bounds of ``item``.

    Args:
        default: see :class:`Spec`.
        doc: see :class:`Spec`.
        length: the number of items required.
        item: the :class:`Number` each item must satisfy.
        nullable: see :class:`Spec`.
        **table: ``feeds`` and ``class_default``, see :class:`Spec`.
    """

    kind = "list"

    def __init__(self, default: Any, doc: str, *, length: int, item: Number, nullable: bool = False,
                 **table: Any):
        super().__init__(default, doc, nullable=nullable, **table)
        self.length = length
        self.item = item

    @property
    def expected(self) -> str:
        inner = self.item.expected
        inner = inner.removeprefix("a ")
        return f"a list of {self.length} {inner.replace('number', 'numbers', 1)}"

    def _check(self, value: Any, path: str, *, fill: bool) -> Any:
        if isinstance(value, (str, bytes)) or not isinstance(value, Sequence) or len(value) != self.length:
            raise self.fail(path, value)
        out = []
        for x in value:
            try:
                out.append(self.item.check(x, path))
            except SchemaViolation:
                raise self.fail(path, value) from None
        return out


def _plain_data(value: Any, path: str) -> Any:
    """Copy of a JSON-like value (tuples become lists); refuses anything JSON cannot hold so that
    the value survives the trip through ``TMRL_CONFIG_OVERRIDE`` to child processes."""
    if value is None or isinstance(value, (bool, int, str)):
        return value
    if isinstance(value, float):
        return value
    if isinstance(value, Mapping):
        out = {}
        for k, v in value.items():
            if not isinstance(k, str):
                raise SchemaViolation(path, f"{path} must have string keys, got key {show(k)}")
            out[k] = _plain_data(v, join_key(path, k))
        return out
    if isinstance(value, (list, tuple)):
        return [_plain_data(v, f"{path}[{i}]") for i, v in enumerate(value)]
    raise SchemaViolation(path, f"{path} must hold only JSON values, got {show(value)}")


class AnyDict(Spec):
    """A free-form object (keyword arguments passed through to user code). An override replaces
    it as a whole instead of merging into it."""

    kind = "object"

    @property
    def expected(self) -> str:
        return "an object (a dict with string keys)"

    def _check(self, value: Any, path: str, *, fill: bool) -> Any:
        if not isinstance(value, Mapping):
            raise self.fail(path, value)
        return _plain_data(value, path)


class AnyList(Spec):
    """A free-form list (positional arguments passed through to user code)."""

    kind = "list"

    @property
    def expected(self) -> str:
        return "a list"

    def _check(self, value: Any, path: str, *, fill: bool) -> Any:
        if isinstance(value, (str, bytes)) or not isinstance(value, (list, tuple)):
            raise self.fail(path, value)
        return _plain_data(value, path)


class Section(Spec):
    """A nested object with a fixed set of keys. Unknown keys are refused (with a suggestion
    when one is close); missing keys take their defaults.

    Args:
        fields: key name -> :class:`Spec` of that key, in the order of ``config.json``.
        doc: one-line meaning of the section, shown in ``docs/config.md``.
    """

    kind = "section"

    def __init__(self, fields: dict[str, Spec], doc: str):
        super().__init__(None, doc)
        self.fields = fields

    @property
    def expected(self) -> str:
        return "an object (a dict of keys)"

    def default_value(self) -> dict[str, Any]:
        """A new dict with every key of the section at its default."""
        return {name: spec.default_value() for name, spec in self.fields.items()}

    def _check(self, value: Any, path: str, *, fill: bool) -> Any:
        if not isinstance(value, Mapping):
            if not path:
                raise SchemaViolation(path, f"the top level must be an object (a dict of keys), got {show(value)}")
            raise self.fail(path, value)
        for key in value:
            if not isinstance(key, str) or key not in self.fields:
                raise self.unknown(path, key)
        out: dict[str, Any] = {}
        for name, spec in self.fields.items():
            if name in value:
                out[name] = spec.check(value[name], join_key(path, name), fill=fill)
            elif fill:
                out[name] = spec.default_value()
        return out

    def unknown(self, path: str, key: Any) -> SchemaViolation:
        """The error for a ``key`` this section does not have, suggesting the closest known key
        (returned for the caller to raise).

        Args:
            path: the key path of the section (``""`` for the top level).
            key: the unknown key found.
        """
        where = join_key(path, str(key))
        close = difflib.get_close_matches(str(key), list(self.fields), n=1, cutoff=0.6)
        if not close:
            close = [k for k in self.fields if k.casefold() == str(key).casefold()]
        if close:
            hint = f"did you mean {join_key(path, close[0])}?"
        else:
            hint = "remove it (`python -m tmrl --help config` lists every key)"
        return SchemaViolation(where, f"{where} is not a known key; {hint}")

    def arguments(self, cfg: Mapping[str, Any], cls: str) -> dict[str, Any]:
        """The constructor arguments of class ``cls`` that ``cfg`` sets, by the ``feeds`` of this
        section's keys (nested sections included): ``{"lr_actor": 1e-05, ...}``, values copied.

        Args:
            cfg: a complete, validated config of this section.
            cls: the class name as written in ``feeds`` (``"SACAgent"``).
        """
        out: dict[str, Any] = {}
        for name, spec in self.fields.items():
            if isinstance(spec, Section):
                out.update(spec.arguments(cfg[name], cls))
                continue
            for target in spec.feeds:
                owner, _, arg = target.partition(".")
                if owner == cls:
                    out[arg] = copy.deepcopy(cfg[name])
        return out

    def fed_arguments(self, path: str = "") -> dict[str, dict[str, tuple[str, Any]]]:
        """For each class named in ``feeds``: ``{argument: (key path, class default)}``.

        Args:
            path: the key path of this section (``""`` for the top level).
        """
        table: dict[str, dict[str, tuple[str, Any]]] = {}
        for name, spec in self.fields.items():
            key = join_key(path, name)
            if isinstance(spec, Section):
                for owner, args in spec.fed_arguments(key).items():
                    table.setdefault(owner, {}).update(args)
                continue
            for target in spec.feeds:
                owner, _, arg = target.partition(".")
                table.setdefault(owner, {})[arg] = (key, spec.class_default)
        return table
