"""The proposed law's evaluation results, kept on disk between ``blf-eval`` runs.

Every score is against the law on the same episodes and noise, so every ``blf-eval`` run needs the
law's episodes: on the inner path for the baselines' rows (and the law's own row), on each agent's
env path for the agents' scores. They take 15-30 s per set on two cores, and they do not change
unless the code does: given the code, the scenarios, the noise seeds and the env arguments, the
closed loop is deterministic to the bit. So ``blf-eval`` keeps each set it computes, reduced to its
:class:`blf_gym.results.metrics.EpisodeStats`, and serves it again when every input is the same.

What must be the same (all folded into one sha256 key, the file's name):

* the source of every module the result depends on: every ``.py`` file of ``blf_gym``,
  ``baselines`` and ``agents``, and of the top-level package of each plug-in the law runs with (its
  controller and observer, found through their entry points), and the import closure of the kernel
  and of each plug-in module (:func:`blf_gym.jit.sources.digest`), which follows a plug-in's imports
  out of its package into local code;
* numpy's, numba's and llvmlite's versions, Python's, and the CPU numba compiles for (its name and
  features: the machine code, and so the last bits, depend on them);
* what was run: the path (inner, or the env's arguments), the observer, every scenario in full
  (their dataclass ``repr``, which prints every float to the bit) and the noise seeds.

Anything else (a different machine sharing a home folder, an edited file, a new numba) gives a new
key and so a fresh run. One thing the key cannot see: code that a plug-in imports from another
package installed into ``site-packages`` (not in editable mode); after reinstalling such a package
with changed code, run ``blf-eval --fresh-law`` once: it ignores the kept files and replaces them. A file that cannot be read, or
does not hold what its key says, is ignored and rewritten. Files are written atomically.
``BLF_GYM_CACHE_DIR`` moves the cache (with the compiled glue) elsewhere; deleting the folder is
always safe.
"""

from __future__ import annotations

import hashlib
import json
import platform
import sys
from functools import lru_cache
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from blf_gym.jit import sources
from blf_gym.results.io import atomic_write_text, cache_dir
from blf_gym.results.metrics import EpisodeStats

__all__ = ["code_digest", "law_key", "load_law", "store_law"]

FORMAT = 1
"""Version of the files' layout; a change makes every older file a miss."""


def _package_files(module_name: str) -> list[Path]:
    """Every ``.py`` file of the top-level package that ``module_name`` belongs to (or the module's
    own file when it is not in a package)."""
    import importlib

    top = module_name.split(".")[0]
    mod = importlib.import_module(top)
    f = getattr(mod, "__file__", None)
    if f is None:
        return []
    path = Path(f)
    if path.name == "__init__.py":
        return sorted(path.parent.rglob("*.py"))
    return [path]


def _plugin_modules(controller: str, observer: str) -> list[str]:
    """The modules that the entry points of ``controller`` and ``observer`` point at."""
    from importlib.metadata import entry_points

    out = []
    for group, name in (("blf_gym.controllers", controller), ("blf_gym.observers", observer)):
        for ep in entry_points(group=group):
            if ep.name == name:
                out.append(ep.value.split(":")[0])
    return out


@lru_cache(maxsize=None)
def code_digest(controller: str = "proposed", observer: str = "leso") -> str:
    """sha256 of the code and tools a law result depends on (see the module docstring)."""
    import llvmlite
    import llvmlite.binding as llvm
    import numba

    h = hashlib.sha256(f"blf-gym law cache {FORMAT}".encode())
    files: set[Path] = set()
    for mod in ("blf_gym", "baselines", "agents", *_plugin_modules(controller, observer)):
        files.update(_package_files(mod))
    for f in sorted(files):
        h.update(str(f.name).encode())
        h.update(f.read_bytes())
    # and the import closure of the law's kernel and of each plug-in module: what a plug-in imports
    # from outside its own package (a local helper module) is compiled into the kernel too
    h.update(sources.digest("blf_gym.kernel.simulate", *_plugin_modules(controller, observer)).encode())
    host = f"{llvm.get_host_cpu_name()} {llvm.get_host_cpu_features().flatten()}"
    for part in (np.__version__, numba.__version__, llvmlite.__version__, platform.python_version(),
                 platform.machine(), host):
        h.update(part.encode())
    return h.hexdigest()


def law_key(path: str, observer: str, scenarios: Sequence[Any], noise_seeds: Sequence[int],
            env_kwargs: dict[str, Any] | None = None) -> str:
    """The cache key of a set of law episodes: the code (:func:`code_digest`) and what was run."""
    what = {"path": path, "observer": observer, "env_kwargs": env_kwargs,
            "scenarios": [repr(sc) for sc in scenarios], "noise_seeds": [int(s) for s in noise_seeds]}
    h = hashlib.sha256(code_digest("proposed", observer).encode())
    h.update(json.dumps(what, sort_keys=True, default=str).encode())
    return h.hexdigest()


def _encode(v: Any) -> Any:
    if isinstance(v, np.ndarray):
        return {"dtype": v.dtype.str, "data": v.tolist()}
    return v


def _decode(v: Any) -> Any:
    if isinstance(v, dict) and set(v) == {"dtype", "data"}:
        return np.asarray(v["data"], dtype=np.dtype(v["dtype"]))
    return v


_FOLDER: Path | None = None
"""Set by :func:`use_folder`; None: ``law`` in blf-gym's cache folder."""


def folder() -> Path:
    """Where the law's episodes are kept: ``law`` in blf-gym's cache folder
    (:func:`blf_gym.results.io.cache_dir`) unless :func:`use_folder` named another."""
    return _FOLDER if _FOLDER is not None else cache_dir() / "law"


def use_folder(path: Path | None) -> None:
    """Keep the law's episodes in ``path`` from now on (None: the default); blf-eval's worker
    processes take their parent's folder so."""
    global _FOLDER
    _FOLDER = None if path is None else Path(path)


def load_law(key: str, count: int) -> tuple[list[EpisodeStats], float] | None:
    """The law's ``count`` episodes stored under ``key`` and the wall time they took when they were
    computed, or None (not there, unreadable, or not what the key says)."""
    try:
        doc = json.loads((folder() / f"{key}.json").read_text())
        if doc.get("format") != FORMAT or doc.get("key") != key or len(doc["episodes"]) != count:
            return None
        stats = [EpisodeStats(**{f: _decode(ep[f]) for f in EpisodeStats._fields}) for ep in doc["episodes"]]
        return stats, float(doc["wall_s"])
    except (OSError, ValueError, KeyError, TypeError):
        return None


def store_law(key: str, stats: Sequence[EpisodeStats], wall_s: float) -> None:
    """Keep the law's episodes under ``key`` (atomically; a read-only or full cache folder costs the
    reuse, not the run)."""
    doc = {"format": FORMAT, "key": key, "python": sys.version.split()[0], "wall_s": float(wall_s),
           "episodes": [{f: _encode(getattr(s, f)) for f in EpisodeStats._fields} for s in stats]}
    try:
        # NaN and inf stay as they are (a diverged episode's sums): only Python reads these files
        atomic_write_text(folder() / f"{key}.json", json.dumps(doc, allow_nan=True))
    except OSError:
        pass
