"""blf-eval keeps the proposed law's episodes between runs (agents/lawcache.py).

A reused result must be the result a fresh run gives, bit for bit, and anything that could change
that result must change the key. A damaged file is a miss, never an error or a wrong score."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

import agents.eval_runner as runner  # where the run looks the episodes up
import agents.evaluate as ev
from agents.lawcache import _package_files, code_digest, law_key, load_law, store_law
from agents.loading import PRETRAINED
from blf_gym.results.metrics import EpisodeStats

AGENT = str(PRETRAINED / "ppo_residual")
ARGS = ["--suite-seeds", "3", "--duration", "0.3", "--no-progress", "--no-plots"]


@pytest.fixture
def cache():
    import agents.lawcache as lawcache

    return lawcache.folder()  # this test's own, empty (conftest.py)


def _records(out: Path) -> list[dict]:
    return [{k: v for k, v in r.items() if k not in ("wall_s", "law_reused")}
            for r in json.loads((out / "results.json").read_text())["records"]]


def _count(monkeypatch) -> dict[str, int]:
    """Counts the law's simulations: "inner", the proposed law's row on the inner path (one call per
    group), "env", the agents' references on the env path (one call for all groups)."""
    calls = {"inner": 0, "env": 0}
    real_episodes, real_groups = ev.controller_episodes, ev.law_reference_groups

    def episodes(name, scs, *a, **k):
        calls["inner"] += name == "proposed"
        return real_episodes(name, scs, *a, **k)

    def groups(gs, meta=None, threads=None):
        calls["env"] += 1
        return real_groups(gs, meta, threads)

    monkeypatch.setattr(runner, "controller_episodes", episodes)
    monkeypatch.setattr(runner, "law_reference_groups", groups)
    return calls


def test_a_second_run_reuses_the_law_and_scores_to_the_bit(cache, tmp_path, monkeypatch, capsys):
    calls = _count(monkeypatch)
    ARGS = [*globals()["ARGS"], "--jobs", "1"]  # the counting patch holds in this process only
    assert ev.main(["--agents", AGENT, "--out", str(tmp_path / "a"), *ARGS]) == 0
    # four groups (two presets, three randomized and three stress episodes): the law's row on the
    # inner path per group, and the agent's env reference for all groups in one batched run; the
    # second yardstick's episodes (blf_gym.envs.protocol.REFERENCE on the inner path) are kept too, per group
    assert calls == {"inner": 4, "env": 1}
    assert len(list(cache.glob("*.json"))) == 4 + 4 + 4
    calls.update(inner=0, env=0)
    assert ev.main(["--agents", AGENT, "--out", str(tmp_path / "b"), *ARGS]) == 0
    assert calls == {"inner": 0, "env": 0}
    assert _records(tmp_path / "a") == _records(tmp_path / "b")
    recs = json.loads((tmp_path / "b" / "results.json").read_text())["records"]
    assert [r.get("law_reused", False) for r in recs] == [r["policy"] == "proposed" for r in recs]
    assert not any(r.get("law_reused") for r in json.loads((tmp_path / "a" / "results.json").read_text())["records"])
    # --fresh-law simulates again, and gets the same bits
    assert ev.main(["--agents", AGENT, "--out", str(tmp_path / "c"), "--fresh-law", *ARGS]) == 0
    assert calls == {"inner": 4, "env": 1}
    assert _records(tmp_path / "a") == _records(tmp_path / "c")


def test_a_damaged_or_foreign_file_is_a_miss(cache, tmp_path, monkeypatch):
    scs = ev.build_scenarios([], 2, {}, 0.2, "randomized")[0][1]
    stats = ev.law_reference(scs, None, threads=1)
    key = law_key("inner", "leso", scs, [0, 1])
    store_law(key, stats, 1.5)
    got = load_law(key, 2)
    assert got is not None and got[1] == 1.5
    for a, b in zip(got[0], stats):
        for f in EpisodeStats._fields:
            x, y = getattr(a, f), getattr(b, f)
            assert (np.array_equal(x, y) and np.asarray(x).dtype == np.asarray(y).dtype) if isinstance(y, np.ndarray) \
                else x == y, f
    path = cache / f"{key}.json"
    assert load_law(key, 3) is None  # not the episodes asked for
    text = path.read_text()
    path.write_text(text[: len(text) // 2])
    assert load_law(key, 2) is None  # truncated
    other = law_key("inner", "leso", scs, [0, 2])
    path.rename(cache / f"{other}.json")
    store_law(key, stats, 1.0)
    (cache / f"{other}.json").write_text((cache / f"{key}.json").read_text())
    assert load_law(other, 2) is None  # a file whose inside names another key


def test_everything_a_result_depends_on_changes_the_key():
    scs = ev.build_scenarios([], 2, {}, 0.2, "randomized")[0][1]
    base = law_key("inner", "leso", scs, [0, 1])
    nudged = [replace(scs[0], angle_noise_std=np.nextafter(scs[0].angle_noise_std, 1.0)), scs[1]]
    others = [
        law_key("inner", "leso", nudged, [0, 1]),  # one float, one ulp
        law_key("inner", "leso", scs, [0, 2]),  # a noise seed
        law_key("inner", "leso", scs[:1], [0]),
        law_key("env", "leso", scs, [0, 1], {"control_period": 0.01}),
        law_key("env", "leso", scs, [0, 1], {"control_period": 0.002}),
        law_key("inner", "eso4", scs, [0, 1]),
    ]
    assert len({base, *others}) == len(others) + 1
    # the code: every source file of the packages the closed loop and the scoring live in
    names = {p.name for p in _package_files("blf_gym")} | {p.name for p in _package_files("baselines")}
    assert {"simulate.py", "envcore.py", "metrics.py", "blocks.py", "controllers.py"} <= names
    assert "evaluate.py" in {p.name for p in _package_files("agents")}
    assert len(code_digest()) == 64


def test_a_baseline_scored_without_the_law_s_row_gets_the_same_reference(tmp_path):
    # the law is then run (or reused) only as bc's reference: bc's score must not depend on it
    tiny = ["--agents", "--suite-seeds", "2", "--duration", "0.3", "--no-progress", "--no-plots"]
    assert ev.main(["--controllers", "bc", "--out", str(tmp_path / "alone"), *tiny]) == 0
    assert ev.main(["--controllers", "proposed", "bc", "--out", str(tmp_path / "both"), "--fresh-law", *tiny]) == 0
    alone = [r for r in _records(tmp_path / "alone") if r["policy"] == "bc"]
    both = [r for r in _records(tmp_path / "both") if r["policy"] == "bc"]
    assert len(alone) == 4 and alone == both


def test_blf_eval_help_lists_the_common_cases_and_the_reuse():
    text = ev._parser().format_help()
    for case in ("blf-eval --agents runs/mine ", "blf-eval --agents runs/mine --suite-seeds 0", "--fresh-law",
                 "law_reused"):
        assert case in text, case
