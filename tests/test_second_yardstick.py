"""The second yardstick: every blf-eval record carries its score against the reference controller
(agents.evaluate.REFERENCE), computed as score_vs_law is, and the reference is never scored
against itself."""

from __future__ import annotations

import json

import numpy as np
import pytest

from agents.evaluate import REFERENCE, main as eval_main

ARGS = ["--scenarios", "paper-0.1hz", "--suite-seeds", "2", "--duration", "1", "--no-progress", "--no-plots",
        "--agents"]


def _records(out) -> dict[tuple[str, str], dict]:
    return {(r["policy"], r["scenario"]): r for r in json.loads((out / "results.json").read_text())["records"]}


def test_scores_against_the_reference_are_the_reciprocal_of_its_own_and_need_not_run_it(tmp_path):
    both = tmp_path / "both"
    assert eval_main(["--controllers", "proposed", REFERENCE, *ARGS, "--out", str(both)]) == 0
    recs = _records(both)
    for group in ("paper-0.1hz", "randomized"):
        law, ref = recs[("proposed", group)], recs[(REFERENCE, group)]
        assert law["reference"] == REFERENCE and ref["score_vs_reference"] is None  # never against itself
        # geometric means of RMSE ratios on the same pooled RMSEs: one is the other's reciprocal
        assert law["score_vs_reference"] == pytest.approx(1.0 / ref["score_vs_law"], rel=1e-12)
        np.testing.assert_allclose(law["per_episode_score_vs_reference"],
                                   1.0 / np.asarray(ref["per_episode_score"]), rtol=1e-12)
    # without the reference's rows its episodes run on their own, with the same seeds: the same scores
    alone = tmp_path / "alone"
    assert eval_main(["--controllers", "proposed", *ARGS, "--out", str(alone)]) == 0
    for key, r in _records(alone).items():
        assert r["score_vs_reference"] == recs[key]["score_vs_reference"]
    # and none at all when asked
    off = tmp_path / "off"
    assert eval_main(["--controllers", "proposed", "--reference", "none", *ARGS, "--out", str(off)]) == 0
    assert all(r["reference"] is None and r["score_vs_reference"] is None for r in _records(off).values())


def test_an_unknown_reference_is_refused_by_name(capsys):
    assert eval_main(["--controllers", "proposed", "--reference", "no_such_law", *ARGS]) == 2
    assert "--reference 'no_such_law' is not a registered controller" in capsys.readouterr().err
