"""The second yardstick: every blf-eval record carries its score against the reference controller
(blf_gym.envs.protocol.REFERENCE), computed as score_vs_law is, and the reference is never scored
against itself."""

from __future__ import annotations

import json

import numpy as np
import pytest

from agents.evaluate import main as eval_main
from blf_gym.envs.protocol import REFERENCE

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


def _rec(policy, rmse, kind="controller", base=None, seed=None, scenario="randomized", **extra):
    """A blf-eval record on four shared episodes, as much of one as agents.report reads."""
    from blf_gym.results.metrics import score_vs_law

    law = LAW_RMSE
    r = {"policy": policy if seed is None else f"{policy}_s{seed}", "kind": kind, "scenario": scenario,
         "episodes": len(rmse), "dt": 1e-4, "suite": "randomized", "suite_seeds": 4, "noise_seeds": [1, 2, 3, 4],
         "scenario_kwargs": None, "per_episode_rmse_deg": [list(x) for x in rmse],
         "per_episode_score": [score_vs_law(p, q) for p, q in zip(rmse, law)], "failure_rate": 0.0,
         "certificate_broken": 0.0, "rmse_deg": list(np.mean(rmse, axis=0)), "violations": [0, 0, 0]}
    if base is not None:
        r["env_kwargs"] = {"controller": base}
    if seed is not None:
        r["train_seed"] = seed
    r.update(extra)
    return r


LAW_RMSE = np.array([[1.0, 2.0, 3.0], [1.5, 2.5, 1.0], [0.5, 0.7, 0.9], [2.0, 1.0, 4.0]])


def test_the_report_scores_a_residual_against_its_own_base_and_a_reference_from_another_run():
    """agents.report's second and third yardsticks: per episode, the geometric mean over joints of
    the yardstick's RMSE over the policy's, pooled over seeds by rliable's IQM; checked against
    scipy's 25 % trimmed mean of the same ratios computed here with numpy. A reference from another
    run is taken only where the proposed law's episodes agree."""
    from scipy.stats import trim_mean

    from agents.report import reference_records, seed_statistics

    rng = np.random.default_rng(0)
    tuned = LAW_RMSE / 8.0
    ppc = LAW_RMSE / 10.0
    seeds = [tuned * rng.uniform(0.5, 1.0, size=tuned.shape) for _ in range(3)]
    records = [_rec("proposed", LAW_RMSE), _rec("proposed_tuned", tuned)]
    records += [_rec("res_tuned", s, kind="residual", base="proposed_tuned", seed=k) for k, s in enumerate(seeds)]
    other_run = [_rec("proposed", LAW_RMSE), _rec("ppc", ppc)]
    yard = reference_records(records, other_run)
    assert [r["policy"] for r in yard] == ["proposed", "ppc"]
    stats = {s["policy"]: s for s in seed_statistics(records, reps=200, pi_reps=20, reference="ppc", yardsticks=yard)}
    res = stats["res_tuned"]

    def gm(yardstick, s):
        return np.exp(np.mean(np.log(yardstick / s), axis=-1))

    assert res["vs_base"]["against"] == "proposed_tuned" and res["vs_reference"]["against"] == "ppc"
    assert res["iqm"] == pytest.approx(trim_mean(np.ravel([gm(LAW_RMSE, s) for s in seeds]), 0.25), rel=1e-12)
    assert res["vs_base"]["iqm"] == pytest.approx(trim_mean(np.ravel([gm(tuned, s) for s in seeds]), 0.25), rel=1e-12)
    assert res["vs_reference"]["iqm"] == pytest.approx(trim_mean(np.ravel([gm(ppc, s) for s in seeds]), 0.25),
                                                       rel=1e-12)
    # every seed is better than its base here (factors 0.5-1), so P(improvement over the base) is 1
    assert res["vs_base"]["prob_improvement"] == pytest.approx(1.0)
    # a controller is never scored against itself; a residual over the proposed law has no third yardstick
    assert "vs_base" not in stats["proposed_tuned"] and "vs_reference" not in stats.get("ppc", {})
    # another run whose law episodes differ (one RMSE changed in the last digits) is refused
    moved = LAW_RMSE.copy()
    moved[2, 1] *= 1 + 1e-6
    with pytest.raises(ValueError, match="not the same"):
        reference_records(records, [_rec("proposed", moved), _rec("ppc", ppc)])
    # a run scored on other episodes contributes nothing, and one without the law to check is refused
    other = {"noise_seeds": [9, 9, 9, 9]}
    assert reference_records(records, [_rec("proposed", LAW_RMSE, **other), _rec("ppc", ppc, **other)]) == []
    with pytest.raises(ValueError, match="no record of the proposed law"):
        reference_records(records, [_rec("proposed", LAW_RMSE, **other), _rec("ppc", ppc)])


def test_a_report_is_the_same_on_every_call_and_leaves_numpys_global_generator_alone():
    """rliable's bootstraps draw from numpy's global generator whatever random_state they get
    (their intervals moved in the fourth digit between calls): agents.report seeds it per call and
    restores the caller's state."""
    from agents.report import seed_statistics

    rng = np.random.default_rng(1)
    records = [_rec("proposed", LAW_RMSE)]
    records += [_rec("res", LAW_RMSE * rng.uniform(0.5, 1.5, size=LAW_RMSE.shape), kind="residual", base="proposed",
                     seed=k) for k in range(3)]
    np.random.seed(123)
    before = np.random.get_state()[1].copy()
    first = seed_statistics(records, reps=300, pi_reps=30)
    assert np.array_equal(np.random.get_state()[1], before)
    np.random.random(17)  # another global state: the same statistics
    assert seed_statistics(records, reps=300, pi_reps=30) == first
