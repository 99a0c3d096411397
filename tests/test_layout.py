"""docs/layout.md's tree against the files, both ways: every module of blf_gym's sub-packages, of
baselines and of agents is named in its paragraph, and every name there is a module that exists."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SUBPACKAGES = ("envs", "kernel", "plugins", "model", "jit", "results")


def _tree() -> dict[str, set[str]]:
    """Each paragraph of the page's tree (``blf_gym/<sub>``, ``baselines``, ``agents``) -> the module
    names it lists: its text with every parenthesised comment removed, split at commas."""
    text = (ROOT / "docs" / "layout.md").read_text()
    block = text.split("```")[1]
    paras: dict[str, list[str]] = {}
    key = None
    for line in block.splitlines():
        m = re.match(r"^(?:  ([a-z_]+)/|([a-z_]+)/)\s+(.*)$", line)
        if m:
            key = f"blf_gym/{m.group(1)}" if m.group(1) else m.group(2)
            paras[key] = [m.group(3)]
        elif line.startswith(" ") and key:
            paras[key].append(line.strip())
        else:
            key = None
    out = {}
    for key in [f"blf_gym/{s}" for s in SUBPACKAGES] + ["baselines", "agents"]:
        body = " ".join(paras[key])
        while re.search(r"\([^()]*\)", body):
            body = re.sub(r"\([^()]*\)", "", body)
        out[key] = {w.strip() for w in body.split(",") if w.strip() and "/" not in w}
    return out


def _modules(folder: Path) -> set[str]:
    return {p.stem for p in folder.glob("*.py") if p.stem != "__init__"}


def test_blf_gym_top_level_holds_only_the_package_file():
    assert _modules(ROOT / "blf_gym") == set()
    subs = {p.name for p in (ROOT / "blf_gym").iterdir() if (p / "__init__.py").is_file()}
    assert subs == set(SUBPACKAGES)


@pytest.mark.parametrize("key", [f"blf_gym/{s}" for s in SUBPACKAGES] + ["baselines", "agents"])
def test_the_layout_page_names_every_module_and_only_modules(key):
    listed = _tree()[key]
    present = _modules(ROOT / key)
    assert listed - present == set(), f"docs/layout.md names modules {key} does not have"
    assert present - listed == set(), f"docs/layout.md leaves out modules of {key}"


def test_the_parser_finds_the_names():
    # the check above would pass vacuously if the parser found no names: drop one and it must differ
    tree = _tree()
    assert "simulate" in tree["blf_gym/kernel"] and "falsify" in tree["agents"] and "leso" in tree["baselines"]
    assert len(tree["blf_gym/envs"]) == len(_modules(ROOT / "blf_gym" / "envs")) >= 9
