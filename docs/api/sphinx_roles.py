"""Griffe extension for the API reference: reST cross-references in docstrings become links.

tmrl's docstrings refer to other objects the Sphinx way (``:func:`load_config```,
``:class:`~tmrl.util.partial```, ``:mod:`.reward```), which Markdown would show as a stray
``:func:`` next to the name. This extension, loaded by mkdocstrings (``extensions:`` in
mkdocs.yml), rewrites each role into an optional mkdocs-autorefs reference before the docstring is
rendered: a link when the target is rendered somewhere in the reference, plain code otherwise (no
warning either way). It also turns reST's ``text::`` (an indented literal block follows) into
``text:``. The docstrings themselves are not changed.
"""

from __future__ import annotations

import re
from typing import Any

import griffe

ROLE = re.compile(r":(?:py:)?(?:func|class|meth|mod|data|attr|exc|obj|const):`(?P<target>[^`]+)`")
LITERAL_BLOCK = re.compile(r"(?<=\S)::$", flags=re.MULTILINE)
BARE_LITERAL_BLOCK = re.compile(r"^[ \t]*::[ \t]*$", flags=re.MULTILINE)


def _module_of(obj: griffe.Object) -> griffe.Object:
    while not obj.is_module and obj.parent is not None:
        obj = obj.parent
    return obj


def _identifier(obj: griffe.Object, target: str) -> str:
    """The full path ``target`` names from ``obj``'s docstring (``target`` itself when unknown)."""
    if target.startswith("."):  # relative to the module (a package's submodule, a module's name)
        module = _module_of(obj)
        return module.path + target
    first, _, rest = target.partition(".")
    scope: griffe.Object | None = obj
    while scope is not None:
        try:
            resolved = scope.resolve(first)
        except (griffe.NameResolutionError, KeyError, AttributeError):
            resolved = _inherited(scope, first)
            if resolved is None:
                scope = scope.parent
                continue
        return f"{resolved}.{rest}" if rest else resolved
    return target


def _inherited(scope: griffe.Object, name: str) -> str | None:
    """The path of a member ``name`` that class ``scope`` inherits (where it is defined)."""
    if not scope.is_class:
        return None
    try:
        member = scope.all_members.get(name)
    except (griffe.AliasResolutionError, griffe.CyclicAliasError, KeyError, AttributeError):
        return None
    if member is None:
        return None
    return member.target_path if member.is_alias else member.path


def rewrite(obj: griffe.Object, text: str) -> str:
    """``text`` (a docstring of ``obj``) with its reST roles and literal-block markers rewritten."""

    def link(match: re.Match[str]) -> str:
        target = match["target"].strip().lstrip("!")
        short = target.startswith("~")
        target = target.lstrip("~")
        title = target.rsplit(".", 1)[-1] if short else target.lstrip(".")
        return f'<autoref identifier="{_identifier(obj, target)}" optional><code>{title}</code></autoref>'

    text = ROLE.sub(link, text)
    text = BARE_LITERAL_BLOCK.sub("", text)
    return LITERAL_BLOCK.sub(":", text)


class SphinxRoles(griffe.Extension):
    """Rewrites the docstrings of every object of a loaded package (see the module docstring)."""

    def on_package(self, *, pkg: griffe.Module, loader: Any, **kwargs: Any) -> None:
        seen: set[int] = set()

        def walk(obj: griffe.Object) -> None:
            if id(obj) in seen:
                return
            seen.add(id(obj))
            if obj.docstring is not None:
                obj.docstring.value = rewrite(obj, obj.docstring.value)
            for member in obj.members.values():
                if not member.is_alias:
                    walk(member)

        walk(pkg)
