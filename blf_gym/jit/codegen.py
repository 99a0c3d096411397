"""Generated modules: the one way blf_gym specialises compiled code (the closed loop's kernel and the
plug-ins' glue; :mod:`blf_gym.kernel.simulate` says why this way).

A specialisation is Python source text, written to a file named by its content's digest and imported
like any module, so that:

* numba compiles and caches it as it does any file (``cache=True``: the machine code sits beside the
  file, keyed on it; the same source is the same file, never rewritten, so a warm start loads);
* every name in it is defined in it, by an import or an assignment, so a linter or an editor reads a
  generated file as it reads ours (``ruff check`` on the cache folder resolves every name);
* what cannot be named by an import (a plug-in function defined in a test, a script or a notebook) is
  handed over through :func:`bound`: the loader registers the objects under the module's name before
  importing it, and the module's top line reads them (``_c_output = bound(__name__, "_c_output")``).

Where the cache folder cannot be written, the file goes to a temporary folder for this process
(compiled each time, as before). Nothing here calls ``exec``: the import system loads the file.
"""

from __future__ import annotations

import importlib.util
import os
import sys
import tempfile
from pathlib import Path
from types import ModuleType
from typing import Any

__all__ = ["bound", "load_module", "module_path"]

_BINDINGS: dict[str, dict[str, Any]] = {}
_TEMP: list[Path] = []


def bound(module: str, name: str) -> Any:
    """The object the loader bound to ``name`` for the generated module ``module``."""
    try:
        return _BINDINGS[module][name]
    except KeyError:
        raise RuntimeError(f"{module}: no binding {name!r}; a generated module is imported through "
                           "blf_gym.jit.codegen.load_module, which binds it") from None


def _write(directory: Path, name: str, source: str) -> Path:
    path = directory / f"{name}.py"
    directory.mkdir(parents=True, exist_ok=True)
    if not path.is_file() or path.read_text() != source:
        tmp = path.with_name(f".{path.name}.tmp{os.getpid()}")
        tmp.write_text(source)
        os.replace(tmp, path)
    return path


def module_path(directory: Path | None, name: str, source: str) -> Path:
    """Where the module's file is (written now if absent or different): in ``directory``, or in a
    temporary folder of this process when that cannot be written."""
    if directory is not None:
        try:
            return _write(Path(directory), name, source)
        except OSError:
            pass
    if not _TEMP:
        _TEMP.append(Path(tempfile.mkdtemp(prefix="blf_gym_generated_")))
    return _write(_TEMP[0], name, source)


def load_module(name: str, source: str, directory: Path | None, bindings: dict[str, Any] | None = None) -> ModuleType:
    """Import the generated module ``name`` (a Python identifier: a digest in it makes it unique to
    ``source``) from its file in ``directory``, with ``bindings`` available to it through
    :func:`bound`. The same name twice in a process returns the module imported first."""
    modname = f"blf_gym_generated_{name}"
    if modname in sys.modules:
        return sys.modules[modname]
    path = module_path(directory, name, source)
    _BINDINGS[modname] = dict(bindings or {})
    spec = importlib.util.spec_from_file_location(modname, path)
    module = importlib.util.module_from_spec(spec)
    sys.modules[modname] = module
    try:
        spec.loader.exec_module(module)
    except BaseException:
        del sys.modules[modname]
        raise
    return module
