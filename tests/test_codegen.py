"""One code-generation style (issue 62, item 3): the kernel's builds and the plug-ins' glue are
generated modules (blf_gym.jit.codegen), every name in them and in the templates resolves, and
nothing in blf_gym calls exec, eval or compile.

The linter is pyflakes, an independent reader of the files: a build's module, the glue, and the
templates with their placeholders must show no undefined name."""

from __future__ import annotations

import ast
import inspect
from pathlib import Path

import pytest

from blf_gym.kernel import simulate, templates
from blf_gym.plugins.blocks import connect
from blf_gym.plugins.registry import make_controller, make_observer

ROOT = Path(__file__).resolve().parents[1]
pyflakes_api = pytest.importorskip("pyflakes.api")
from pyflakes import reporter as pyflakes_reporter  # noqa: E402


def _flakes(source: str, name: str) -> list[str]:
    """pyflakes' messages about ``source``, but for an unused import of ``sources`` (imported for its
    side effect, as every compiled module does)."""
    import io

    out, err = io.StringIO(), io.StringIO()
    pyflakes_api.check(source, name, pyflakes_reporter.Reporter(out, err))
    lines = [ln for ln in (out.getvalue() + err.getvalue()).splitlines()
             if "'blf_gym.jit.sources' imported but unused" not in ln]
    return lines


@pytest.fixture(scope="module")
def conn():
    return connect(make_controller("proposed"), make_observer("leso"), 3, make_controller("proposed").make_filter("barrier"))


@pytest.mark.parametrize("lanes", [1, simulate.LANES])
def test_a_builds_module_lints_clean_and_binds_exactly_the_build_names(conn, lanes):
    src = simulate.build_source(conn, lanes)
    assert _flakes(src, "<build>") == []
    assigned = set()
    for node in ast.parse(src).body:
        if isinstance(node, ast.Assign):
            assigned |= {t.id for t in node.targets if isinstance(t, ast.Name)}
        elif isinstance(node, ast.FunctionDef):
            assigned.add(node.name)
    missing = set(templates.BUILD_NAMES) - assigned
    assert not missing, f"a build leaves these template names to their placeholders: {sorted(missing)}"
    # each template is copied as it is written, not edited on the way
    for fn in templates.TEMPLATES:
        assert inspect.getsource(fn).rstrip() in src, fn.__name__


def test_the_placeholders_are_exactly_the_build_names():
    """templates.py's section "bound per build" assigns each name a build defines, and no other
    (a name added to one side only would run with its placeholder or be left undefined)."""
    tree = ast.parse(Path(templates.__file__).read_text())
    placeholders = set()
    for node in tree.body:
        if isinstance(node, ast.Assign) and node.lineno > _section_line(tree):
            for t in node.targets:
                for x in ast.walk(t):
                    if isinstance(x, ast.Name):
                        placeholders.add(x.id)
    placeholders -= {"BUILD_NAMES", "TEMPLATES", "ONCE_A_CALL"}
    assert placeholders == set(templates.BUILD_NAMES)


def _section_line(tree: ast.Module) -> int:
    src = Path(templates.__file__).read_text().splitlines()
    return next(i for i, ln in enumerate(src, 1) if ln.startswith("# bound per build"))


def test_the_templates_and_the_glue_lint_clean(conn):
    assert _flakes(Path(templates.__file__).read_text(), "templates.py") == []
    assert _flakes(Path(conn.module.__file__).read_text(), "glue") == []
    # the build's module is the file its machine code is cached against, in this tree's own folder
    build = Path(simulate._specialise(conn, 1).py_func.__code__.co_filename)
    assert build.parent == simulate.kernel_folder() and build.read_text() == simulate.build_source(conn, 1)
    assert simulate.kernel_folder().parent.name == "kernels"


def test_nothing_in_the_packages_calls_exec_eval_or_compile_or_silences_an_undefined_name():
    bad = []
    for pkg in ("blf_gym", "baselines", "agents"):
        for f in sorted((ROOT / pkg).rglob("*.py")):
            text = f.read_text()
            if "noqa: F821" in text:
                bad.append(f"{f.relative_to(ROOT)}: noqa: F821")
            for node in ast.walk(ast.parse(text)):
                if (isinstance(node, ast.Call) and isinstance(node.func, ast.Name)
                        and node.func.id in ("exec", "eval", "compile")):
                    bad.append(f"{f.relative_to(ROOT)}:{node.lineno}: {node.func.id}")
    assert not bad, bad


def test_a_generated_module_is_loaded_once_per_name_and_reads_its_bindings(tmp_path):
    from blf_gym.jit import codegen

    src = 'from blf_gym.jit.codegen import bound\n\nvalue = bound(__name__, "value")\n'
    m = codegen.load_module("test_codegen_once", src, tmp_path, {"value": 41})
    assert m.value == 41 and (tmp_path / "test_codegen_once.py").read_text() == src
    assert codegen.load_module("test_codegen_once", src, tmp_path, {"value": 0}) is m
    with pytest.raises(RuntimeError, match="no binding"):
        codegen.load_module("test_codegen_unbound", src, tmp_path, {})
    # a folder that cannot be made (a file stands in its way): a temporary one for this process
    (tmp_path / "afile").write_text("")
    m2 = codegen.load_module("test_codegen_elsewhere", src, tmp_path / "afile" / "sub", {"value": 2})
    assert m2.value == 2 and Path(m2.__file__).parent != tmp_path / "afile" / "sub"
