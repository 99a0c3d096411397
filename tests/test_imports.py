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
    assert "2 kept, 0 broken" in p.stdout  # both contracts were read and checked


def test_no_module_imports_a_private_name_of_another():
    modules = _modules()
    assert {"blf_gym.simulate", "blf_gym.views", "baselines.leso", "agents.loading"} <= set(modules)
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
    # the check above must resolve "from .simulate import _x" in blf_gym/blocks.py to blf_gym.simulate
    node = ast.parse("from .simulate import _x").body[0]
    assert _resolve("blf_gym.blocks", node, False) == "blf_gym.simulate"
    node = ast.parse("from ..blf_gym.core import _y").body[0]
    assert _resolve("agents.sub.mod", node, False) == "agents.blf_gym.core"
    node = ast.parse("from .loading import _z").body[0]
    assert _resolve("agents", node, True) == "agents.loading"
