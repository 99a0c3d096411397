"""What a compiled artefact was built from: the source files a module reaches through its imports.

numba's disk cache checks one file per function, the file that defines it. The closed loop's
kernel and the plug-ins' glue inline code from a dozen files, and a constant such as a packed
vector's offset is frozen into the machine code from yet another (``params.py``). So every cache
key in blf-gym that guards compiled code is built here, from the **import closure** of the code's
module: the module's own file and, followed recursively, every module it imports at module level
(``import x``, ``from x import y``, ``from . import y``; relative names resolved; imports inside a
function's body are not followed, since they run only when the function does, in Python).

Which imports are followed (:func:`followed`): the standard library never (its code changes only
with Python, which every key records separately), nor a package installed in ``site-packages``
(numpy, numba: a new version of those is a new install, and numba's cache index records numba's
own version); every other module is, so blf-gym's own packages, a plug-in in an editable install
or a local folder, and any local helper module a plug-in imports are all in the key. A plug-in
installed into ``site-packages`` is followed within its own top-level package.

The closure is found by reading the files (:mod:`ast`), never by importing them, so it is the same
whatever has been imported so far, and it can be asked of a copy of the package elsewhere on disk
(``path=``), which the tests do to edit a file without touching this one.

:class:`ImportClosureLocator` puts :func:`digest` into numba's own per-function cache: a function
defined in a module whose closure reaches blf_gym (blf-gym's packages, the baselines, plug-ins)
is cached under a stamp that is the digest of that closure instead of numba's hash of its one
file. It is installed into numba's list of cache locators when this module is imported (first
thing in ``import blf_gym``); numba's ``NUMBA_CACHE_LOCATOR_CLASSES``, if a user sets it, replaces
that list and so turns it off.
"""

from __future__ import annotations

import ast
import hashlib
import importlib.machinery
import importlib.util
import site
import sys
import sysconfig
from functools import lru_cache
from pathlib import Path
from typing import Any, Sequence

from numba.core import caching

__all__ = ["ImportClosureLocator", "clear", "closure", "digest", "followed", "function_digest"]

_STAMP_TAG = "blf-gym import closure v1"
"""Prefix of every stamp this module gives numba: a change of the scheme changes every stamp."""


def _installed_roots() -> tuple[Path, ...]:
    paths = {sysconfig.get_paths().get(k) for k in ("stdlib", "platstdlib", "purelib", "platlib")}
    try:
        paths.update(site.getsitepackages())
    except AttributeError:  # some virtualenv layouts lack it
        pass
    paths.add(site.getusersitepackages())
    out = []
    for p in paths:
        if p:
            try:
                out.append(Path(p).resolve())
            except OSError:
                pass
    return tuple(out)


_INSTALLED = _installed_roots()


def _is_installed(path: Path) -> bool:
    return any(path.is_relative_to(root) for root in _INSTALLED)


def _locate(name: str, path: tuple[str, ...] | None) -> Path | None:
    """The source file of module ``name`` without importing it: from ``sys.modules`` when it is
    imported and no search ``path`` is given, else through the import system's finders (the top
    package on ``path`` or ``sys.path`` and the meta-path finders, each submodule inside its
    parent's folders). None when it has no Python source file."""
    if path is None:
        mod = sys.modules.get(name)
        f = getattr(mod, "__file__", None)
        if f and f.endswith(".py"):
            return Path(f).resolve()
    parts = name.split(".")
    try:
        if path is None:
            top = sys.modules.get(parts[0])
            if top is not None and getattr(top, "__path__", None) is not None:
                locations: Any = list(top.__path__)
                spec = getattr(top, "__spec__", None)
            else:
                spec = importlib.util.find_spec(parts[0])
                locations = None if spec is None else spec.submodule_search_locations
        else:
            spec = importlib.machinery.PathFinder.find_spec(parts[0], list(path))
            locations = None if spec is None else spec.submodule_search_locations
        for i in range(1, len(parts)):
            if locations is None:
                return None
            spec = importlib.machinery.PathFinder.find_spec(".".join(parts[: i + 1]), list(locations))
            locations = None if spec is None else spec.submodule_search_locations
    except (ImportError, ValueError, AttributeError):
        return None
    origin = None if spec is None else spec.origin
    if not origin or not origin.endswith(".py"):
        return None
    return Path(origin).resolve()


def followed(name: str, root: str, file: Path) -> bool:
    """Whether the closure of ``root`` follows an import of module ``name`` found at ``file``: not
    the standard library, and not an installed package other than ``root``'s own."""
    top = name.split(".")[0]
    if top in sys.stdlib_module_names or top in sys.builtin_module_names:
        return False
    return top == root.split(".")[0] or not _is_installed(file)


@lru_cache(maxsize=512)
def _imports(file: Path, name: str, is_package: bool) -> tuple[tuple[str, ...], ...]:
    """What ``file`` (module ``name``) imports at module level, absolute names, each as the
    alternatives to try in turn: ``import a.b`` is ``("a.b",)``; ``from x import y`` is
    ``("x.y", "x")``, the submodule if y is one, else the module y is an attribute of. A parent
    package's ``__init__`` is not followed for its submodule's sake: the compiled code uses what
    it names, not what the parent runs."""
    try:
        tree = ast.parse(file.read_bytes(), filename=str(file))
    except (OSError, SyntaxError, ValueError):
        return ()
    package = name if is_package else name.rpartition(".")[0]
    out: list[tuple[str, ...]] = []

    def absolute(level: int, mod: str | None) -> str | None:
        if level == 0:
            return mod
        base = package.split(".") if package else []
        if level - 1 > len(base):
            return None
        base = base[: len(base) - (level - 1)]
        return ".".join(base + ([mod] if mod else [])) or None

    def visit(body: list[Any]) -> None:
        for node in body:
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                continue  # runs only when called, in Python
            if isinstance(node, ast.Import):
                out.extend((a.name,) for a in node.names)
            elif isinstance(node, ast.ImportFrom):
                mod = absolute(node.level, node.module)
                if mod is None or mod == "__future__":
                    continue
                for a in node.names:
                    out.append((mod,) if a.name == "*" else (f"{mod}.{a.name}", mod))
            for field in ("body", "orelse", "finalbody", "handlers"):  # if/try/with/class at module level
                sub = getattr(node, field, None)
                if isinstance(sub, list):
                    visit(sub)

    visit(tree.body)
    return tuple(dict.fromkeys(out))


@lru_cache(maxsize=256)
def closure(name: str, path: tuple[str, ...] | None = None) -> tuple[tuple[str, Path], ...]:
    """``(module name, source file)`` of ``name`` and of every module it reaches through
    module-level imports that :func:`followed` keeps, sorted by name; empty if ``name`` has no
    source file. ``path``: look the top-level packages up there (a copy of a package on disk)
    instead of in the running interpreter."""
    start = _locate(name, path)
    if start is None:
        return ()
    seen: dict[str, Path] = {name: start}
    todo = [name]
    while todo:
        mod = todo.pop()
        file = seen[mod]
        for alternatives in _imports(file, mod, file.name == "__init__.py"):
            for dep in alternatives:
                if dep.split(".")[0] in sys.stdlib_module_names:
                    break
                if dep in seen:
                    break
                f = _locate(dep, path)
                if f is None:
                    continue  # not a module: try the next alternative
                if followed(dep, name, f):
                    seen[dep] = f
                    todo.append(dep)
                break
    return tuple(sorted(seen.items()))


def _hash_closure(items: Sequence[tuple[str, Path]]) -> str:
    h = hashlib.sha256(_STAMP_TAG.encode())
    for mod, f in items:
        h.update(b"\0" + mod.encode() + b"\0")
        h.update(f.read_bytes())
    return h.hexdigest()


@lru_cache(maxsize=256)
def digest(*names: str, path: tuple[str, ...] | None = None) -> str:
    """sha256 (hex) of the sources in the union of the closures of ``names``: any edit to any of
    those files, a comment included, changes it; an edit anywhere else does not. Memoised per
    process (:func:`clear` forgets)."""
    items: dict[str, Path] = {}
    for n in names:
        items.update(closure(n, path))
    return _hash_closure(sorted(items.items()))


def function_digest(fn: Any, path: tuple[str, ...] | None = None) -> str:
    """:func:`digest` of the module that defines ``fn`` (a Python function or a numba dispatcher);
    for a function with no module file (typed into a notebook), the digest of its own source or,
    failing that, its bytecode and constants."""
    py = getattr(fn, "py_func", fn)
    mod = getattr(py, "__module__", None)
    if mod and closure(mod, path):
        return digest(mod, path=path)
    import inspect

    h = hashlib.sha256(_STAMP_TAG.encode())
    try:
        h.update(inspect.getsource(py).encode())
    except (OSError, TypeError):
        code = py.__code__
        h.update(code.co_code + repr(code.co_consts).encode() + repr(code.co_names).encode())
    return h.hexdigest()


def clear() -> None:
    """Forget the memoised closures and digests (after a file was edited in this process)."""
    for f in (_imports, closure, digest):
        f.cache_clear()


def _reaches_blf_gym(name: str) -> bool:
    return any(m == "blf_gym" or m.startswith("blf_gym.") for m, _ in closure(name))


# ------------------------------------------------------------------------------------------------
# numba's per-function cache


def _impl_class() -> Any:
    """numba's class that holds the list of cache locators (``CacheImpl``; ``_CacheImpl`` before 0.61)."""
    return getattr(caching, "CacheImpl", None) or caching._CacheImpl


class ImportClosureLocator(caching._CacheLocator):
    """numba's cache locator for functions whose module reaches blf_gym: the folder and the
    disambiguator of the locator numba would have chosen, and as the source stamp :func:`digest` of
    the function's module (its whole import closure) instead of the hash of its one file. numba
    drops an index whose stamp differs from the current one, so an edit anywhere in the closure
    recompiles the function."""

    def __init__(self, inner: Any, stamp: str):
        self._inner = inner
        self._stamp = stamp

    def __getattr__(self, name: str) -> Any:
        # what numba reads from a locator besides its methods (``_py_file``, ``_lineno``, in its
        # warning for a function it cannot cache) is the inner locator's
        return getattr(self._inner, name)

    def ensure_cache_path(self) -> None:
        self._inner.ensure_cache_path()

    def get_cache_path(self) -> str:
        return self._inner.get_cache_path()

    def get_source_stamp(self) -> Any:
        return (_STAMP_TAG, self._stamp)

    def get_disambiguator(self) -> str:
        return self._inner.get_disambiguator()

    @classmethod
    def from_function(cls, py_func: Any, py_file: str) -> Any:
        mod = getattr(py_func, "__module__", None)
        if not mod or not _reaches_blf_gym(mod):
            return None  # not blf-gym's: numba's own locators, unchanged
        for other in _impl_class()._locator_classes:
            if other is cls:
                continue
            inner = other.from_function(py_func, py_file)
            if inner is not None:
                return cls(inner, digest(mod))
        return None


def install() -> None:
    """Put :class:`ImportClosureLocator` first in numba's cache locators (once per process)."""
    classes = _impl_class()._locator_classes
    if ImportClosureLocator not in classes:
        classes.insert(0, ImportClosureLocator)


install()
