"""The imports point one way, blf_gym <- baselines <- agents, with no cycles, and no module reads
another module's private names.

The direction and the cycles are import-linter's contracts in pyproject.toml ([tool.importlinter]),
which read every import statement, those inside functions included. The private names are
checked here from the source: ``from X import _name`` where X is one of the project's modules and
not the importing module itself.
"""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("blf_gym", "baselines", "agents")


def _modules() -> dict[str, Path]:
    out = {}
    for pkg in PACKAGES:
        for path in sorted((ROOT / pkg).rglob("*.py")):
            parts = path.relative_to(ROOT).with_suffix("").parts
            out[".".join(parts[:-1] if parts[-1] == "__init__" else parts)] = path
    return out


def _resolve(module: str, node: ast.ImportFrom, is_package: bool) -> str:
    if node.level == 0:
        return node.module or ""
    base = module.split(".")
    base = base if is_package else base[:-1]
    base = base[: len(base) - (node.level - 1)]
    return ".".join(base + ([node.module] if node.module else []))


def test_import_linter_contracts_hold():
    exe = Path(sys.executable).with_name("lint-imports")
    p = subprocess.run([str(exe), "--no-cache"], cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert p.returncode == 0, p.stdout[-3000:] + p.stderr[-2000:]
    assert "3 kept, 0 broken" in p.stdout  # the three contracts were read and checked


def test_no_module_imports_a_private_name_of_another():
    modules = _modules()
    assert {"blf_gym.kernel.simulate", "blf_gym.jit.views", "baselines.leso", "agents.loading"} <= set(modules)
    bad = []
    for module, path in modules.items():
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if not isinstance(node, ast.ImportFrom):
                continue
            source = _resolve(module, node, path.name == "__init__.py")
            if source.split(".")[0] not in PACKAGES or source == module:
                continue
            bad += [f"{module}:{node.lineno} imports {source}.{a.name}" for a in node.names
                    if a.name.startswith("_") and not a.name.startswith("__")]
    assert not bad, "\n".join(bad)


def test_the_private_name_check_sees_relative_imports():
    # the check above must resolve "from .registry import _x" in blf_gym/plugins/blocks.py to
    # blf_gym.plugins.registry, and "from ..kernel import _x" to blf_gym.kernel
    node = ast.parse("from .registry import _x").body[0]
    assert _resolve("blf_gym.plugins.blocks", node, False) == "blf_gym.plugins.registry"
    node = ast.parse("from ..kernel import _x").body[0]
    assert _resolve("blf_gym.plugins.blocks", node, False) == "blf_gym.kernel"
    node = ast.parse("from ..blf_gym.core import _y").body[0]
    assert _resolve("agents.sub.mod", node, False) == "agents.blf_gym.core"
    node = ast.parse("from .loading import _z").body[0]
    assert _resolve("agents", node, True) == "agents.loading"


LIBRARY_INTERNALS = {
    ("blf_gym.jit.sources", "caching._CacheImpl"): "numba's cache locators hang off its cache implementation; "
                                                   "no public hook installs one",
    ("blf_gym.jit.sources", "caching._CacheLocator"): "the base class numba's own locators derive from",
    ("blf_gym.jit.sources", "_impl_class()._locator_classes"): "numba's list of cache locators, where ours is put",
    ("blf_gym.jit.views", "out._getvalue"): "numba's struct proxy: the documented way to return an LLVM value "
                                            "from an intrinsic's codegen",
    ("blf_gym.kernel.templates", "out._getvalue"): "as above",
    ("blf_gym.kernel.simulate", "dispatcher._cache"): "numba's cache folder and index (_cache_dir, _is_cached): "
                                                      "to say where the kernel is cached and whether it compiles",
    ("blf_gym.kernel.simulate", "dispatcher._cache._cache_path"): "as above",
    ("blf_gym.kernel.simulate", "dispatcher._cache._cache_file"): "as above",
    ("blf_gym.kernel.simulate", "dispatcher._cache._cache_file._load_index"): "as above",
    ("agents.episodes", "pol._predict"): "SB3's policy hook behind predict(), on a tensor already batched",
    ("agents.lagrangian", "super()._setup_model"): "SB3's documented extension hooks of a subclass",
    ("agents.lagrangian", "super()._setup_learn"): "as above",
    ("agents.lagrangian", "super()._get_torch_save_params"): "as above",
    ("agents.lagrangian", "super()._excluded_save_params"): "as above",
    ("agents.lawcache", "EpisodeStats._fields"): "a namedtuple's public field list (underscored so as not to "
                                                 "clash with field names)",
    ("agents.sweep", "tuner._local_tuner"): "Ray Tune keeps a restored run's config there; no public setter",
    ("agents.sweep", "tuner._local_tuner._run_config"): "as above",
}
"""Every read of another object's underscored attribute that is allowed, with why: a library's
internals, where its public interface offers no other way. A read of a private attribute that a
project module defines is never allowed (the test below)."""


def _private_reads(path: Path) -> list[tuple[int, str, str]]:
    """(line, expression, attribute) of each ``x._name`` read where ``x`` is not ``self`` or ``cls``."""
    out = []
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Attribute) and node.attr.startswith("_") and not node.attr.startswith("__"):
            if isinstance(node.value, ast.Name) and node.value.id in ("self", "cls"):
                continue
            out.append((node.lineno, ast.unparse(node), node.attr))
    return out


def _private_definitions(path: Path) -> set[str]:
    """The underscored names a module defines: functions, classes, module and class variables, and
    attributes it sets on ``self`` (directly or through ``object.__setattr__``)."""
    out = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
            out.add(node.name)
        elif isinstance(node, ast.Name) and isinstance(node.ctx, ast.Store):
            out.add(node.id)
        elif isinstance(node, ast.Attribute) and isinstance(node.ctx, ast.Store):
            out.add(node.attr)
        elif (isinstance(node, ast.Call) and ast.unparse(node.func) == "object.__setattr__" and len(node.args) > 1
              and isinstance(node.args[1], ast.Constant)):
            out.add(node.args[1].value)
    return {n for n in out if isinstance(n, str) and n.startswith("_") and not n.startswith("__")}


def _reach_ins(modules: dict[str, Path]) -> tuple[list[str], list[str]]:
    defined = {m: _private_definitions(p) for m, p in modules.items()}
    project, unlisted = [], []
    for module, path in modules.items():
        for line, expr, attr in _private_reads(path):
            if attr in defined[module]:
                continue  # the module's own private name (another instance of its own class, say)
            if any(attr in names for m, names in defined.items() if m != module):
                project.append(f"{module}:{line} reads {expr}, private to another module")
            elif (module, expr) not in LIBRARY_INTERNALS:
                unlisted.append(f"{module}:{line} reads {expr}")
    return project, unlisted


def test_no_module_reads_another_modules_private_attribute():
    project, unlisted = _reach_ins(_modules())
    assert not project, "\n".join(project)
    assert not unlisted, "a library's internals read without a reason in LIBRARY_INTERNALS:\n" + "\n".join(unlisted)


def test_the_attribute_check_finds_a_planted_reach_in(tmp_path):
    # a module that reads another's private attribute by attribute access, not by import
    (tmp_path / "a.py").write_text("class A:\n    def __init__(self):\n        self._secret = 1\n")
    (tmp_path / "b.py").write_text("def peek(a):\n    return a._secret\n")
    project, _ = _reach_ins({"pkg.a": tmp_path / "a.py", "pkg.b": tmp_path / "b.py"})
    assert project == ["pkg.b:2 reads a._secret, private to another module"]
