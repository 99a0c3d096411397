"""docs/griffe_roles.py, the Griffe extension that turns the docstrings' Sphinx roles into code that
links to the API reference: how it resolves and shows each form of role (the built pages are checked
in tests/test_docs_site.py)."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import pytest

griffe = pytest.importorskip("griffe", reason="the docs extra is not installed")

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def roles():
    spec = importlib.util.spec_from_file_location("griffe_roles", ROOT / "docs" / "griffe_roles.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


SOURCE = '''
"""Module. See :class:`Thing` and :func:`~pkg.other.helper`."""
from pkg.other import helper


class Thing:
    """A thing; :attr:`size` and :meth:`Thing.grow`, :data:`!NOT_LINKED`, :py:func:`the helper <helper>`.

    ```python
    keep(":func:`inside a fence`")
    ```
    >>> ":func:`in a doctest`"
    """

    size: int = 1

    def grow(self):
        """Calls :func:`helper` and :mod:`pkg.other`."""
'''


def test_roles_become_optional_autorefs_resolved_from_the_docstrings_scope(roles):
    with griffe.temporary_pypackage("pkg", {"__init__.py": SOURCE, "other.py": "def helper(): ..."}) as tmp:
        pkg = griffe.load("pkg", search_paths=[tmp.tmpdir], extensions=griffe.load_extensions(roles.RolesToAutorefs))
        module, thing, grow = pkg.docstring.value, pkg["Thing"].docstring.value, pkg["Thing.grow"].docstring.value

    def ref(identifier, text):
        return f'<autoref identifier="{identifier}" optional><code>{text}</code></autoref>'

    assert module == f"Module. See {ref('pkg.Thing', 'Thing')} and {ref('pkg.other.helper', 'helper')}."
    assert ref("pkg.Thing.size", "size") in thing
    assert ref("pkg.Thing.grow", "Thing.grow") in thing
    assert "<code>NOT_LINKED</code>" in thing and "NOT_LINKED</code></autoref>" not in thing
    assert ref("pkg.other.helper", "the helper") in thing  # an imported name: where it is defined
    assert 'keep(":func:`inside a fence`")' in thing and '":func:`in a doctest`"' in thing
    assert grow == f"Calls {ref('pkg.other.helper', 'helper')} and {ref('pkg.other', 'pkg.other')}."


def test_the_extension_is_enabled_and_blf_gym_does_not_import_it():
    assert "docs/griffe_roles.py" in (ROOT / "mkdocs.yml").read_text()
    import subprocess
    import sys

    code = ("import sys, blf_gym; bad = [m for m in sys.modules if m.split('.')[0] in "
            "('mkdocs', 'mkdocstrings', 'griffe', 'latex2mathml', 'griffe_roles', 'mathml_hook')]; "
            "assert not bad, bad")
    subprocess.run([sys.executable, "-c", code], check=True, cwd=ROOT, timeout=300)
