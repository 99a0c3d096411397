"""Every function of blf_gym, baselines and agents is at most 80 lines, except compiled ones marked
``# long:`` with the reason on the lines just above their definition (or their decorators)."""

from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
LIMIT = 80


def _too_long(path: Path) -> list[str]:
    text = path.read_text()
    lines = text.splitlines()
    out = []
    for node in ast.walk(ast.parse(text, str(path))):
        if not isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
            continue
        length = node.end_lineno - node.lineno + 1
        if length <= LIMIT:
            continue
        top = min([node.lineno] + [d.lineno for d in node.decorator_list]) - 1  # 0-based first line
        above = [ln.strip() for ln in lines[max(0, top - 4):top]]
        if any(ln.startswith("# long:") and len(ln) > len("# long: ") + 10 for ln in above):
            continue
        out.append(f"{path.relative_to(ROOT) if path.is_relative_to(ROOT) else path.name}:"
                   f"{node.lineno} {node.name} ({length} lines)")
    return out


def test_no_function_is_longer_than_the_limit_without_a_reason():
    bad = [b for pkg in ("blf_gym", "baselines", "agents") for p in sorted((ROOT / pkg).rglob("*.py"))
           for b in _too_long(p)]
    assert not bad, f"functions over {LIMIT} lines (split them, or mark a compiled one '# long: why'):\n" + "\n".join(bad)


def test_the_check_finds_a_planted_long_function(tmp_path):
    body = "".join(f"    x{i} = {i}\n" for i in range(LIMIT))
    (tmp_path / "m.py").write_text(f"def long_one():\n{body}\n\n# long: a stated reason for this one\n"
                                   f"def excused():\n{body}\n\n# long:\ndef no_reason():\n{body}")
    bad = _too_long(tmp_path / "m.py")
    assert [b.split()[1] for b in bad] == ["long_one", "no_reason"]
