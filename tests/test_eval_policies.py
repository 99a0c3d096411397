"""blf-eval scores a registered policy (the ``blf_gym.policies`` entry points) as it scores an
agent: in the env the policy asks for, every arm in one call when the policy keeps per-arm state
(``whole_batch``), its own report in each record's provenance, and one-line errors for a name that
is not registered. The policy is docs/extending.md's recipe (it holds the torque that cancels
gravity and counts its calls), registered by patching the registry, so the test needs no solver and
follows the page's own code."""

from __future__ import annotations

import json

import importlib
import re
import sys
from pathlib import Path

import pytest

import blf_gym.plugins.registry as registry
from agents.evaluate import main as eval_main

DOC = (Path(__file__).resolve().parents[1] / "docs" / "extending.md").read_text()


@pytest.fixture
def hold(monkeypatch, tmp_path):
    m = re.search(r"<!-- recipe:policy -->\s*```python\n(.*?)```", DOC, re.S)
    assert m, "docs/extending.md has no policy recipe"
    (tmp_path / "my_hold.py").write_text(m.group(1))
    monkeypatch.syspath_prepend(str(tmp_path))
    sys.modules.pop("my_hold", None)
    my_hold = importlib.import_module("my_hold")
    made: list = []
    real_make, real_available = registry.make_policy, registry.available_policies

    def make_policy(name, **kw):
        if name == "hold":  # as the entry point hold = "my_hold:hold" would
            made.append(my_hold.hold(**kw))
            return made[-1]
        return real_make(name, **kw)

    monkeypatch.setattr(registry, "make_policy", make_policy)
    monkeypatch.setattr(registry, "available_policies", lambda: sorted([*real_available(), "hold"]))
    return made


def test_a_registered_policy_is_scored_like_an_agent_with_its_report(hold, tmp_path):
    out = tmp_path / "set"
    rc = eval_main(["--controllers", "proposed", "--agents", "--policies", "hold", "--suite-seeds", "0",
                    "--duration", "0.2", "--jobs", "1", "--no-progress", "--no-plots", "--out", str(out)])
    assert rc == 0
    records = json.loads((out / "results.json").read_text())["records"]
    rows = [r for r in records if r["policy"] == "hold"]
    assert [r["scenario"] for r in rows] == ["paper-0.1hz", "paper-0.5hz"]
    scorer = hold[-1]  # the instance that stepped the episodes
    # both presets' arms stepped together, each step one call with both rows: 20 periods of 10 ms
    assert scorer.rows == [2] * 20
    for r in rows:
        assert r["kind"] == "plain" and r["registered_policy"] == "hold"
        assert r["policy_report"] == {"calls": 20, "largest_call": 2}
        assert r["env_kwargs"]["controller"] == "none"
        # holding still against gravity is far worse than the law on a moving reference
        assert r["score_vs_law"] < 0.5


def test_an_unknown_policy_is_one_line_naming_the_registered_ones(capsys):
    rc = eval_main(["--controllers", "--agents", "--policies", "no-such", "--suite-seeds", "0", "--no-progress"])
    err = capsys.readouterr().err.strip()
    assert rc == 2 and "\n" not in err
    assert "unknown policy 'no-such'" in err and "nmpc" in err
