"""Every generated table in the README and docs/ is what ``python docs/tables.py`` would write now:
the env's tables from the code's declarations, the results tables from the results files in docs/."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent


def _module(path: Path):
    spec = importlib.util.spec_from_file_location(path.stem, path)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_every_generated_table_is_what_its_command_writes():
    tables = _module(ROOT / "docs" / "tables.py")
    made = tables.pages()
    assert ROOT / "docs" / "environment.md" in made and ROOT / "docs" / "control" / "protocol.md" in made
    stale = [str(p.relative_to(ROOT)) for p, text in made.items() if not p.exists() or p.read_text() != text]
    assert not stale, f"{stale} differ from what python docs/tables.py writes: run it"


def test_a_page_without_its_markers_is_refused():
    tables = _module(ROOT / "docs" / "tables.py")
    with pytest.raises(ValueError, match="no <!-- begin:x -->"):
        tables.fill("text without markers", "x", "| a |", "page.md")
    assert tables.fill("a\n<!-- begin:x -->\nold\n<!-- end:x -->\nb", "x", "new") == \
        "a\n<!-- begin:x -->\nnew\n<!-- end:x -->\nb"
