"""A Griffe extension for the API reference: reStructuredText roles in docstrings become code links.

The docstrings in the code use Sphinx's roles, e.g. :func:`blf_gym.results.io.cache_dir` or
:class:`~blf_gym.envs.env.PlanarBLFEnv`. Markdown would show them raw (":func:" and then the name as code).
This extension rewrites them, once the package is loaded, into mkdocs-autorefs cross-references marked
``optional``: the name is shown as code and links to its entry when the API reference documents it;
otherwise autorefs leaves it as plain code, with no warning in the strict build.

A short name is resolved the way Sphinx resolves it, from the object whose docstring holds it outward
(its members, then its parent's, up to the module and what the module imports); a name that does not
resolve is taken as a full dotted path. ``~name`` shows only the last part, ``!name`` never links,
and ``title <name>`` shows the title. Fenced code blocks and doctest lines are left alone.

mkdocs.yml enables it with ``extensions: [docs/griffe_roles.py]`` in the python handler's options. The
source is never changed, and ``import blf_gym`` does not import this file.
"""

from __future__ import annotations

import html
import re
from typing import Any

import griffe

ROLES = ("func", "meth", "class", "attr", "data", "const", "mod", "exc", "obj", "type")
# :func:`x`, :py:func:`x`, :py:class:`title <x>`; the role's text has no backtick and no newline.
ROLE_RE = re.compile(r":(?:py:)?(?P<role>" + "|".join(ROLES) + r"):`(?P<text>[^`\n]+)`")
TITLED_RE = re.compile(r"^(?P<title>.*?)\s*<(?P<target>[^<>]+)>$", re.DOTALL)
FENCE_RE = re.compile(r"^\s*(```|~~~)")


def resolve(obj: griffe.Object, target: str) -> str:
    """The full dotted path ``target`` names from the scope of ``obj`` (itself if it does not resolve)."""
    head, _, rest = target.partition(".")
    try:
        path = obj.resolve(head)
    except (griffe.NameResolutionError, griffe.AliasResolutionError, griffe.CyclicAliasError, KeyError):
        return target
    return f"{path}.{rest}" if rest else path


def replace_role(obj: griffe.Object, match: re.Match) -> str:
    """The Markdown (with an autorefs tag) for one role."""
    role, text = match["role"], match["text"].strip()
    titled = TITLED_RE.match(text)
    title, target = (titled["title"], titled["target"].strip()) if titled else (None, text)
    no_link = target.startswith("!")
    short = target.startswith("~")
    target = target.lstrip("!~").lstrip(".")
    if title is None:
        title = target.rsplit(".", 1)[-1] if short else target
    code = f"<code>{html.escape(title)}</code>"
    if no_link or not target:
        return code
    identifier = target if role == "mod" else resolve(obj, target)
    # optional: autorefs renders an identifier the site does not document as the bare code, unwarned.
    return f'<autoref identifier="{html.escape(identifier)}" optional>{code}</autoref>'


def rewrite(obj: griffe.Object, text: str) -> str:
    """``text`` with its roles rewritten, except in fenced code blocks and doctest lines."""
    out, fenced = [], False
    for line in text.splitlines(keepends=True):
        if FENCE_RE.match(line):
            fenced = not fenced
        if fenced or line.lstrip().startswith((">>>", "...")):
            out.append(line)
        else:
            out.append(ROLE_RE.sub(lambda m: replace_role(obj, m), line))
    return "".join(out)


class RolesToAutorefs(griffe.Extension):
    """Rewrite the reStructuredText roles of every docstring once the object tree is complete."""

    def on_object(self, *, obj: griffe.Object, loader: griffe.GriffeLoader, **kwargs: Any) -> None:  # noqa: ARG002
        self.rewrite_docstring(obj)

    def on_package(self, *, pkg: griffe.Module, loader: griffe.GriffeLoader, **kwargs: Any) -> None:  # noqa: ARG002
        self.rewrite_docstring(pkg)  # on_object runs for the package's members, not for the package

    @staticmethod
    def rewrite_docstring(obj: griffe.Object) -> None:
        docstring = obj.docstring
        if obj.is_alias or docstring is None or ":" not in docstring.value:
            return
        value = rewrite(obj, docstring.value)
        if value != docstring.value:
            docstring.value = value
            docstring.__dict__.pop("parsed", None)  # a cached parse would still hold the roles
