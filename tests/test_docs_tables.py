"""Tables in docs/ that a command writes are what that command would write now."""

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


@pytest.mark.parametrize("name, fn", [("protocol.md", "protocol_table"), ("filters.md", "filters_table"),
                                      ("nmpc.md", "nmpc_table")])
def test_the_control_tables_are_written_by_their_command(name, fn):
    tables = _module(ROOT / "docs" / "control" / "tables.py")
    assert (ROOT / "docs" / "control" / name).read_text() == getattr(tables, fn)(), \
        f"docs/control/{name} differs from what python docs/control/tables.py writes: run it"
