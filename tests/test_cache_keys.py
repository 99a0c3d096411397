"""Every compiled artefact's cache key covers every source compiled into it (docs/getting-started.md,
"What is cached where").

The keys come from :mod:`blf_gym.jit.sources`, which follows a module's imports on disk. The tests edit
files of a throw-away copy of the packages (found through each module's ``__file__``, so a later
move of the files keeps them valid) and ask for the keys of that copy; the end-to-end test compiles
the copy in a fresh process with its own cache folders and checks that an edit to ``vmath.exp``
reaches the machine code, and that reverting it does too (the failure this guards against: a
cached kernel that keeps returning what an older source computed)."""

from __future__ import annotations

import importlib
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import blf_gym
import baselines
from blf_gym.jit import sources
from blf_gym.plugins import blocks

# The modules whose code or constants the closed-loop kernel compiles: the templates (simulate), the
# blocks they inline, and the declarations of every packed layout and status column. Written out
# here as the reference the key is checked against, not read from the key's own code.
KERNEL_MODULES = ("jit.vmath", "model.params", "model.bounds", "model.dynamics", "model.reference", "kernel.reward",
                  "kernel.status", "model.uncertainty", "jit.views", "plugins.blocks", "kernel.simulate",
                  "plugins.registry", "results.io", "jit.sources", "jit.layout")
# Modules the kernel does not compile: an edit to them must not rebuild it.
NOT_KERNEL = ("envs.env", "envs.envcore", "envs.vector", "envs.scenarios", "results.metrics", "envs.render",
              "envs.observation", "envs.safety", "envs.levels", "envs.lookahead", "__init__")


@pytest.fixture(scope="module")
def tree(tmp_path_factory) -> Path:
    """A copy of blf_gym and baselines, without their caches."""
    root = tmp_path_factory.mktemp("tree")
    for pkg in (blf_gym, baselines):
        src = Path(pkg.__file__).parent
        shutil.copytree(src, root / src.name, ignore=shutil.ignore_patterns("__pycache__", "*.nbi", "*.nbc"))
    return root


def _copy_of(tree: Path, module) -> Path:
    """The copy's file of ``module`` (found through its ``__file__``)."""
    f = Path(module.__file__).resolve()
    top = Path(sys.modules[module.__name__.split(".")[0]].__file__).resolve().parent
    return tree / top.name / f.relative_to(top)


def _edited(tree: Path, module, text: str = "\n# an edit\n"):
    """Context: the copy's file of ``module`` with ``text`` appended; the memoised keys forgotten
    before and after."""
    import contextlib

    @contextlib.contextmanager
    def cm():
        f = _copy_of(tree, module)
        before = f.read_bytes()
        sources.clear()
        f.write_bytes(before + text.encode())
        try:
            yield f
        finally:
            f.write_bytes(before)
            sources.clear()

    return cm()


def _kernel_key(tree: Path) -> str:
    return sources.digest("blf_gym.kernel.simulate", path=(str(tree),))


def test_the_copy_gives_the_same_keys_as_the_package(tree):
    # the closure is found from the files, so the same files give the same key wherever they lie
    sources.clear()
    assert _kernel_key(tree) == sources.digest("blf_gym.kernel.simulate")
    names = {m for m, _ in sources.closure("blf_gym.kernel.simulate", path=(str(tree),))}
    assert {f"blf_gym.{m}" for m in KERNEL_MODULES} <= names
    assert not names & {f"blf_gym.{m}" for m in NOT_KERNEL}, "the kernel's key reads a module it does not compile"


@pytest.mark.parametrize("name", KERNEL_MODULES)
def test_an_edit_to_a_compiled_file_changes_the_kernel_key(tree, name):
    module = importlib.import_module(f"blf_gym.{name}")
    before = _kernel_key(tree)
    with _edited(tree, module):
        assert _kernel_key(tree) != before, f"editing {name}.py keeps the kernel's key"
    assert _kernel_key(tree) == before


@pytest.mark.parametrize("name", NOT_KERNEL)
def test_an_edit_to_a_file_the_kernel_does_not_compile_keeps_the_key(tree, name):
    module = importlib.import_module("blf_gym" if name == "__init__" else f"blf_gym.{name}")
    before = _kernel_key(tree)
    with _edited(tree, module):
        assert _kernel_key(tree) == before, f"editing {name}.py would rebuild the kernel"


def test_the_glue_key_covers_what_a_plug_in_calls_in_another_file(tree):
    # the CBF filter's apply calls innovation_exceeds from baselines/filters.py
    from baselines import cbf, filters
    from blf_gym.jit import vmath

    fn = cbf.cbf_apply
    assert fn.py_func.__globals__["innovation_exceeds"] is filters.innovation_exceeds  # the premise
    path = (str(tree),)
    before = blocks.glue_digest("src", [fn], path)
    for module in (filters, vmath, blocks):
        with _edited(tree, module):
            assert blocks.glue_digest("src", [fn], path) != before, module.__name__
    import blf_gym.envs.env as env

    with _edited(tree, env):
        assert blocks.glue_digest("src", [fn], path) == before
    assert blocks.glue_digest("other src", [fn], path) != before


def test_numba_per_function_caches_are_stamped_with_their_closure(tree):
    """Every cached numba function of blf_gym and baselines carries its module's closure digest as
    numba's source stamp, and that digest moves with an edit to vmath for a module that calls it."""
    from numba.core.caching import NullCache
    from numba.core.registry import CPUDispatcher

    import baselines.controllers  # noqa: F401 (imports every baseline module)
    import blf_gym.envs.envcore  # noqa: F401

    seen = 0
    for name, mod in list(sys.modules.items()):
        if not (name.startswith("blf_gym.") or name.startswith("baselines.")):
            continue
        for value in vars(mod).values():
            if isinstance(value, CPUDispatcher) and value.__module__ == name and value._cache is not None \
                    and not isinstance(value._cache, NullCache):
                locator = value._cache._impl.locator
                assert isinstance(locator, sources.ImportClosureLocator), f"{name}.{value.__name__}"
                assert value._cache._cache_file._source_stamp == locator.get_source_stamp()
                assert locator.get_source_stamp()[1] == sources.digest(name)
                seen += 1
    assert seen > 40  # the premise: the loop above found the cached functions
    from blf_gym.jit import vmath

    before = sources.digest("blf_gym.model.reference", path=(str(tree),))
    with _edited(tree, vmath):
        assert sources.digest("blf_gym.model.reference", path=(str(tree),)) != before


_UNCACHABLE = """
import ctypes, warnings
import blf_gym.jit.vmath  # noqa: F401 (so that the closure locator serves this module)
from numba import njit
from numba.core.errors import NumbaWarning

labs = ctypes.CDLL(None).labs  # a ctypes function: its address is a dynamic global, which numba cannot cache
labs.restype, labs.argtypes = ctypes.c_long, (ctypes.c_long,)

@njit(cache=True)
def f(x):
    return labs(x)

with warnings.catch_warnings(record=True) as seen:
    warnings.simplefilter("always")
    assert f(-3) == 3
print([(str(w.message), w.filename) for w in seen if issubclass(w.category, NumbaWarning)])
"""


def test_a_function_numba_cannot_cache_gets_numbas_warning_not_a_crash(tmp_path):
    """numba reads the locator's ``_py_file`` and ``_lineno`` when it warns that a function cannot
    be cached (here: it calls a ctypes function); the closure locator passes them on from the locator
    numba would have chosen, so the function runs and the warning names its file."""
    (tmp_path / "uncachable_mod.py").write_text(_UNCACHABLE)
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(tmp_path), str(Path(blf_gym.__file__).resolve().parents[1])]),
               BLF_GYM_CACHE_DIR=str(tmp_path / "cache"), NUMBA_CACHE_DIR=str(tmp_path / "numba"))
    out = subprocess.run([sys.executable, "-c", "import uncachable_mod"], env=env, capture_output=True, text=True,
                         cwd=tmp_path, timeout=300)
    assert out.returncode == 0, out.stderr[-2000:]
    assert "Cannot cache compiled function" in out.stdout and "uncachable_mod.py" in out.stdout, out.stdout


def test_imports_inside_functions_and_of_the_standard_library_are_not_followed(tmp_path):
    pkg = tmp_path / "pkg_for_closure"
    pkg.mkdir()
    (pkg / "__init__.py").write_text("")
    (pkg / "a.py").write_text("import os\nfrom . import b\ntry:\n    from .c import x\nexcept ImportError:\n"
                              "    pass\n\ndef f():\n    from . import d\n")
    for m in "bcd":
        (pkg / f"{m}.py").write_text("x = 1\n")
    names = [m for m, _ in sources.closure("pkg_for_closure.a", path=(str(tmp_path),))]
    assert names == ["pkg_for_closure.a", "pkg_for_closure.b", "pkg_for_closure.c"]


def test_the_law_cache_and_the_nmpc_key_read_the_closure(monkeypatch):
    from agents import lawcache

    lawcache.code_digest.cache_clear()
    before = lawcache.code_digest()
    monkeypatch.setattr(sources, "digest", lambda *a, **k: "another closure")
    lawcache.code_digest.cache_clear()
    assert lawcache.code_digest() != before
    monkeypatch.undo()
    lawcache.code_digest.cache_clear()
    assert lawcache.code_digest() == before
    pytest.importorskip("casadi")
    from baselines.mpc import NMPC, NMPCParams

    nmpc = NMPC(NMPCParams(horizon=3), compiled=False)  # builds the model only, no solver
    key = nmpc._key(False)
    monkeypatch.setattr(sources, "digest", lambda *a, **k: "another closure")
    assert nmpc._key(False) != key


_RUN = """
import sys
import numpy as np
from blf_gym.model.params import preset
from blf_gym.kernel.simulate import simulate
traj = simulate(preset("paper-0.1hz", duration=0.2), "proposed")
assert sys.modules["blf_gym"].__file__.startswith(sys.argv[1]), sys.modules["blf_gym"].__file__
print(repr(float(np.sum(traj.q)) + float(np.sum(traj.x3_hat))))
"""


@pytest.mark.slow
def test_an_edit_to_exp_reaches_a_warm_cache_and_so_does_its_revert(tmp_path):
    """The issue's case: build with an edited ``exp`` from empty caches, revert the edit, run again on
    the now warm caches. The second run must recompile (its notice says so) and give what the
    unedited code gives here, in this process, and not the edited result."""
    from blf_gym.jit import vmath
    from blf_gym.model.params import preset
    from blf_gym.kernel.simulate import simulate

    root = tmp_path / "tree"
    for pkg in (blf_gym, baselines):
        src = Path(pkg.__file__).parent
        shutil.copytree(src, root / src.name, ignore=shutil.ignore_patterns("__pycache__"))
    env = dict(os.environ, PYTHONPATH=str(root), BLF_GYM_CACHE_DIR=str(tmp_path / "cache"),
               NUMBA_CACHE_DIR=str(tmp_path / "numba"))

    def run() -> tuple[float, str]:
        p = subprocess.run([sys.executable, "-c", _RUN, str(root)], env=env, capture_output=True, text=True,
                           timeout=600, cwd=tmp_path)
        assert p.returncode == 0, p.stderr[-3000:]
        return float(p.stdout.strip().splitlines()[-1]), p.stderr

    f = _copy_of(root, vmath)
    original = f.read_text()
    edited = original.replace("    return x if x != x else out\n", "    return x if x != x else out * 1.001\n", 1)
    assert edited != original  # the premise: the edit applies
    f.write_text(edited)
    with_edit, log = run()
    assert "compiling the closed loop" in log
    f.write_text(original)
    reverted, log = run()
    assert "compiling the closed loop" in log, "the reverted source did not rebuild the kernel"
    traj = simulate(preset("paper-0.1hz", duration=0.2), "proposed")
    here = float(np.sum(traj.q)) + float(np.sum(traj.x3_hat))
    assert with_edit != here, "the edit to exp changed nothing: the test would not see a stale kernel"
    assert reverted == here
