"""The results record (docs/model.md section 8) from hand-built trajectories, and results.json / .csv I/O.

Every expected value is computed here from the definitions in docs/model.md section 8 with plain Python
loops (math module), independently of blf_gym.results.metrics' vectorised code; a few are also written
out as literals with the arithmetic in a comment.
"""

from __future__ import annotations

import csv
import json
import math
from types import SimpleNamespace

import numpy as np
import pytest

from blf_gym.results.metrics import read_results, summarize, violation_mask, write_results

# docs/model.md section 8, copied from its table (not imported from the code under test)
SPEC_FIELDS = (
    "policy", "kind", "scenario", "episodes", "dt", "rmse_deg", "violations", "violation_fraction",
    "max_excursion_deg", "min_margin_deg", "first_violation_s", "failure_rate", "rmse_cvar_deg",
    "torque_rms", "torque_peak", "saturated_fraction", "diverged", "wall_s",
    "score_vs_law", "certificate_broken", "law_failure_rate",
)
# the per-episode arrays live in the JSON only; provenance fields are JSON text in the CSV
CSV_PROVENANCE = ("suite", "suite_seeds", "scenario_kwargs", "env_kwargs", "train_seed", "noise_seeds", "observer",
                  "law_reused", "registered_policy", "policy_report", "level")
SPEC_PER_JOINT = ("rmse_deg", "violations", "violation_fraction", "max_excursion_deg", "min_margin_deg",
                  "torque_rms", "torque_peak", "saturated_fraction")


def _signals(t, e1, ka, kb, u, sat):
    """Arrays as a Trajectory holds them: t (S,), the rest (S, n); bounds given per sample."""
    t = np.asarray(t, dtype=float)
    e1 = np.asarray(e1, dtype=float)
    S, n = e1.shape
    return {
        "t": t,
        "e1": e1,
        "k_a": np.repeat(np.asarray(ka, dtype=float)[:, None], n, axis=1),
        "k_b": np.repeat(np.asarray(kb, dtype=float)[:, None], n, axis=1),
        "u": np.asarray(u, dtype=float),
        "saturated": np.asarray(sat, dtype=float),
    }


# Episode A: 4 samples, bounds shrinking in time.
#   joint 1 reaches e1 == k_a exactly at t = 3 ms (equality is a violation, excursion 0);
#   joint 2 reaches e1 == -k_b exactly at t = 2 ms and is 0.05 beyond -k_b at t = 3 ms;
#   joint 3 stays well inside.
EP_A = SimpleNamespace(signals=_signals(
    t=[0.000, 0.001, 0.002, 0.003],
    e1=[[0.00, 0.00, 0.01],
        [0.05, 0.00, 0.01],
        [-0.05, -0.20, 0.01],
        [0.10, -0.25, 0.01]],
    ka=[0.4, 0.3, 0.2, 0.1],
    kb=[0.5, 0.4, 0.2, 0.2],
    u=[[1.0, -2.0, 0.5],
       [3.0, 0.0, 0.5],
       [-4.0, 1.0, 0.5],
       [0.0, 0.0, -0.5]],
    sat=[[0, 0, 0], [1, 0, 0], [1, 0, 0], [0, 0, 0]],
), step_violations=2, diverged=False)

# Episode B: 2 samples, joint 1 is 0.05 above k_a = 0.1 at t = 1 ms (the earliest violation of all).
EP_B = SimpleNamespace(signals=_signals(
    t=[0.000, 0.001],
    e1=[[0.00, 0.00, 0.02],
        [0.15, 0.00, -0.02]],
    ka=[0.1, 0.1],
    kb=[0.3, 0.3],
    u=[[-6.0, 0.0, 0.0],
       [2.0, 0.0, 0.1]],
    sat=[[1, 0, 0], [0, 0, 1]],
))

# Episode C: a plain dict of signals, 3 samples, no violation.
EP_C = _signals(
    t=[0.000, 0.001, 0.002],
    e1=[[0.001, -0.002, 0.0],
        [0.002, 0.0, 0.003],
        [0.0, 0.001, 0.0]],
    ka=[0.5, 0.5, 0.5],
    kb=[0.5, 0.5, 0.5],
    u=[[0.1, 0.2, 0.3], [0.1, 0.2, 0.3], [0.1, 0.2, 0.3]],
    sat=[[0, 0, 0], [0, 0, 0], [0, 0, 0]],
)

# Episode D: no violating 1 ms sample, but violating integration steps (finer than the samples):
# still a failed episode.
EP_D = SimpleNamespace(signals=_signals(
    t=[0.000, 0.001],
    e1=[[0.01, 0.0, 0.0], [0.0, 0.01, 0.0]],
    ka=[0.2, 0.2],
    kb=[0.2, 0.2],
    u=[[0.0, 0.0, 0.0], [0.0, 0.0, 0.0]],
    sat=[[0, 0, 0], [0, 0, 0]],
), step_violations=3, diverged=False)


def _sig(ep):
    return ep.signals if hasattr(ep, "signals") else ep


def _hand_record(episodes):
    """docs/model.md section 8 by loops over samples; bounds from the open interval (-k_b, k_a)."""
    n = 3
    sq = [0.0] * n
    count = 0
    viol = [0] * n
    exc = [0.0] * n
    margin = [math.inf] * n
    usq = [0.0] * n
    upeak = [0.0] * n
    sat = [0.0] * n
    first = None
    fails = 0
    ep_rmse = []
    for ep in episodes:
        s = _sig(ep)
        S = len(s["t"])
        ep_sq = [0.0] * n
        failed = getattr(ep, "step_violations", 0) > 0 or getattr(ep, "diverged", False)
        for k in range(S):
            for j in range(n):
                e, ka, kb, u = (float(s["e1"][k][j]), float(s["k_a"][k][j]), float(s["k_b"][k][j]),
                                float(s["u"][k][j]))
                sq[j] += e * e
                ep_sq[j] += e * e
                inside = -kb < e < ka
                if not inside:
                    viol[j] += 1
                    failed = True
                    first = float(s["t"][k]) if first is None else min(first, float(s["t"][k]))
                exc[j] = max(exc[j], e - ka, -kb - e)
                margin[j] = min(margin[j], ka - e, e + kb)
                usq[j] += u * u
                upeak[j] = max(upeak[j], abs(u))
                sat[j] += float(s["saturated"][k][j])
        count += S
        fails += failed
        ep_rmse.append(sum(math.degrees(math.sqrt(ep_sq[j] / S)) for j in range(n)) / n)
    worst = sorted(ep_rmse, reverse=True)
    k = max(1, math.ceil(0.5 * len(worst)))
    return {
        "episodes": len(episodes),
        "rmse_deg": [math.degrees(math.sqrt(sq[j] / count)) for j in range(n)],
        "violations": viol,
        "violation_fraction": [viol[j] / count for j in range(n)],
        "max_excursion_deg": [math.degrees(exc[j]) for j in range(n)],
        "min_margin_deg": [math.degrees(margin[j]) for j in range(n)],
        "first_violation_s": first,
        "failure_rate": fails / len(episodes),
        "rmse_cvar_deg": sum(worst[:k]) / k,
        "torque_rms": [math.sqrt(usq[j] / count) for j in range(n)],
        "torque_peak": upeak,
        "saturated_fraction": [sat[j] / count for j in range(n)],
    }


def _assert_close(got, want, name):
    if isinstance(want, list):
        assert isinstance(got, list) and len(got) == len(want), name
        for g, w in zip(got, want):
            assert g == pytest.approx(w, rel=1e-12, abs=1e-12), (name, got, want)
    elif want is None:
        assert got is None, name
    else:
        assert got == pytest.approx(want, rel=1e-12, abs=1e-12), (name, got, want)


@pytest.fixture(scope="module")
def record():
    return summarize([EP_A, EP_B, EP_C, EP_D], "mylaw", "residual", "suite-x", 1e-4, wall_s=1.25)


PER_EPISODE = ("per_episode_rmse_deg", "per_episode_score", "per_episode_violations", "per_episode_failed")


def test_record_has_every_spec_field_and_nothing_else(record):
    # the second yardstick's fields are always there (None without a reference)
    assert set(record) == set(SPEC_FIELDS) | set(PER_EPISODE) | {"reference", "score_vs_reference",
                                                                "per_episode_score_vs_reference"}
    for f in SPEC_PER_JOINT:
        assert len(record[f]) == 3, f
    assert (record["policy"], record["kind"], record["scenario"], record["dt"], record["wall_s"]) == (
        "mylaw", "residual", "suite-x", 1e-4, 1.25)
    assert record["episodes"] == 4
    json.dumps(record, allow_nan=False)  # plain Python types only


def test_record_matches_hand_computation(record):
    want = _hand_record([EP_A, EP_B, EP_C, EP_D])
    for name, value in want.items():
        _assert_close(record[name], value, name)
    assert record["diverged"] is False


def test_record_literal_values(record):
    # 11 samples in all (4 + 2 + 3 + 2).
    # Violations: joint 1 at A t=3ms (0.10 == k_a) and B t=1ms (0.15 > 0.1); joint 2 at A t=2ms
    # (-0.20 == -k_b) and t=3ms (-0.25 < -0.2); joint 3 never.
    assert record["violations"] == [2, 2, 0]
    assert record["violation_fraction"] == pytest.approx([2 / 11, 2 / 11, 0.0], abs=1e-15)
    # excursion: joint 1 0.15 - 0.1 = 0.05 rad; joint 2 -0.2 - (-0.25) = 0.05 rad; joint 3 none
    assert record["max_excursion_deg"] == pytest.approx([math.degrees(0.05)] * 2 + [0.0], abs=1e-12)
    # margins: joint 1 0.1 - 0.15 = -0.05; joint 2 -0.25 + 0.2 = -0.05; joint 3: B t=0 0.1 - 0.02
    assert record["min_margin_deg"] == pytest.approx(
        [-math.degrees(0.05), -math.degrees(0.05), math.degrees(0.08)], abs=1e-12)
    # A's first violation is at 2 ms (joint 2), B's at 1 ms (joint 1): the earliest over episodes
    assert record["first_violation_s"] == pytest.approx(0.001, abs=0)
    # A, B (samples) and D (integration steps only) failed; C did not
    assert record["failure_rate"] == 0.75
    # joint 1 torque: squares 1 + 9 + 16 + 0 + 36 + 4 + 3 * 0.01 + 0 = 66.03 over 11 samples
    assert record["torque_rms"][0] == pytest.approx(math.sqrt(66.03 / 11), rel=1e-14)
    assert record["torque_peak"] == [6.0, 2.0, 0.5]
    # joint 1 clipped at A 1 ms, A 2 ms, B 0 ms; joint 3 at B 1 ms
    assert record["saturated_fraction"] == pytest.approx([3 / 11, 0.0, 1 / 11], abs=1e-15)


def test_rmse_is_pooled_over_samples_not_averaged_over_episodes(record):
    # joint 2 error squares: A 0.04 + 0.0625, C 4e-6 + 1e-6, D 1e-4 -> over 11 samples
    pooled = math.degrees(math.sqrt((0.04 + 0.0625 + 5e-6 + 1e-4) / 11))
    assert record["rmse_deg"][1] == pytest.approx(pooled, rel=1e-13)
    per_episode = [math.sqrt((0.04 + 0.0625) / 4), 0.0, math.sqrt(5e-6 / 3), math.sqrt(1e-4 / 2)]
    assert record["rmse_deg"][1] != pytest.approx(math.degrees(sum(per_episode) / 4), rel=1e-3)


def test_rmse_cvar_is_the_mean_of_the_worst_half():
    # one joint carries all the error, so an episode's mean-over-joints RMSE is |c| / 3 (in rad)
    def flat(c, S=5):
        return _signals(t=np.arange(S) * 1e-3, e1=[[c, 0.0, 0.0]] * S, ka=[1.0] * S, kb=[1.0] * S,
                        u=np.zeros((S, 3)), sat=np.zeros((S, 3)))

    eps = [flat(0.01), flat(0.04), flat(0.02), flat(0.03)]
    rec = summarize(eps, "p", "plain", "s", 1e-4)
    assert rec["rmse_cvar_deg"] == pytest.approx(math.degrees((0.04 + 0.03) / 2 / 3), rel=1e-13)
    # 3 episodes: ceil(0.5 * 3) = 2 worst
    rec = summarize(eps[:3], "p", "plain", "s", 1e-4)
    assert rec["rmse_cvar_deg"] == pytest.approx(math.degrees((0.04 + 0.02) / 2 / 3), rel=1e-13)
    # 1 episode: itself (at least one)
    rec = summarize(eps[:1], "p", "plain", "s", 1e-4)
    assert rec["rmse_cvar_deg"] == pytest.approx(math.degrees(0.01 / 3), rel=1e-13)
    assert rec["failure_rate"] == 0.0 and rec["first_violation_s"] is None
    assert rec["violations"] == [0, 0, 0] and rec["max_excursion_deg"] == [0.0, 0.0, 0.0]


def test_equality_with_a_bound_is_a_violation():
    e1 = np.array([[0.1, -0.2, 0.0999999, -0.1999999, 0.3, -0.5]])
    ka = np.full_like(e1, 0.1)
    kb = np.full_like(e1, 0.2)
    np.testing.assert_array_equal(violation_mask(e1, ka, kb), [[True, True, False, False, True, True]])


def test_a_diverged_episode_fails_and_marks_the_record():
    div = SimpleNamespace(signals=EP_C, diverged=True, step_violations=0)
    rec = summarize([EP_C, div], "p", "baseline", "s", 1e-3)
    assert rec["diverged"] is True
    assert rec["failure_rate"] == 0.5
    assert rec["violations"] == [0, 0, 0]
    # an episode that diverged before its first sample (no samples at all)
    empty = SimpleNamespace(signals=_signals(t=np.zeros(0), e1=np.zeros((0, 3)), ka=np.zeros(0),
                                             kb=np.zeros(0), u=np.zeros((0, 3)), sat=np.zeros((0, 3))),
                            diverged=True)
    rec = summarize([EP_C, empty], "p", "baseline", "s", 1e-3)
    assert rec["diverged"] is True and rec["episodes"] == 2 and rec["failure_rate"] == 0.5
    _assert_close(rec["rmse_deg"], _hand_record([EP_C])["rmse_deg"], "rmse_deg")


def test_summarize_rejects_an_unknown_kind_and_no_episodes():
    with pytest.raises(ValueError, match="kind"):
        summarize([EP_C], "p", "baselines", "s", 1e-4)
    with pytest.raises(ValueError, match="kind"):
        summarize([EP_C], "p", "rl", "s", 1e-4)
    for kind in ("baseline", "plain", "residual"):
        assert summarize([EP_C], "p", kind, "s", 1e-4)["kind"] == kind
    with pytest.raises(ValueError):
        summarize([], "p", "plain", "s", 1e-4)


# ---------------------------------------------------------------------------------------------
# results.json / results.csv


def test_write_and_read_results_round_trip(record, tmp_path):
    other = summarize([EP_C], "bc", "baseline", "paper-0.1hz", 1e-4, wall_s=0.5)
    jp, cp = write_results([record, other], tmp_path / "out")
    assert jp == tmp_path / "out" / "results.json" and cp == tmp_path / "out" / "results.csv"
    data = json.loads(jp.read_text())
    assert data["schema_version"] == 2
    assert data["records"] == [record, other]
    assert read_results(jp) == [record, other]
    # no temporary files left behind by the atomic writes
    assert sorted(p.name for p in (tmp_path / "out").iterdir()) == ["results.csv", "results.json"]


def test_results_csv_spreads_per_joint_fields(record, tmp_path):
    other = summarize([EP_C], "bc", "baseline", "paper-0.1hz", 1e-4)
    _, cp = write_results([record, other], tmp_path)
    with open(cp, newline="") as f:
        rows = list(csv.DictReader(f))
    assert len(rows) == 2
    header = list(rows[0])
    expected = []
    for fld in SPEC_FIELDS:
        expected += [f"{fld}_{j}" for j in (1, 2, 3)] if fld in SPEC_PER_JOINT else [fld]
    assert header == expected + ["reference", "score_vs_reference"] + list(CSV_PROVENANCE)
    for row, rec in zip(rows, (record, other)):
        assert row["policy"] == rec["policy"] and row["kind"] == rec["kind"]
        assert int(row["episodes"]) == rec["episodes"]
        for fld in SPEC_PER_JOINT:
            for j in range(3):
                assert float(row[f"{fld}_{j + 1}"]) == rec[fld][j], (fld, j)
        assert float(row["rmse_cvar_deg"]) == rec["rmse_cvar_deg"]
    assert float(rows[0]["first_violation_s"]) == 0.001
    assert rows[1]["first_violation_s"] == ""  # null -> empty cell


def test_write_results_rejects_a_record_missing_a_field(record, tmp_path):
    for missing in ("rmse_cvar_deg", "wall_s", "kind"):
        bad = {k: v for k, v in record.items() if k != missing}
        with pytest.raises(ValueError, match=missing):
            write_results([record, bad], tmp_path)
    assert not (tmp_path / "results.json").exists()


def test_read_results_checks_the_schema_version(tmp_path):
    p = tmp_path / "results.json"
    p.write_text(json.dumps({"schema_version": 3, "records": []}))
    with pytest.raises(ValueError, match="schema_version"):
        read_results(p)
    # the earlier schema is read, its missing fields None
    p.write_text(json.dumps({"schema_version": 1, "records": [{"policy": "x", "rmse_deg": [1, 2, 3]}]}))
    rec = read_results(p)[0]
    assert rec["policy"] == "x" and rec["per_episode_score"] is None and rec["score_vs_law"] is None
    p.write_text(json.dumps({"records": []}))
    with pytest.raises(ValueError, match="schema_version"):
        read_results(p)


def test_written_files_have_ordinary_permissions(tmp_path):
    import os
    import stat

    from blf_gym.results.io import atomic_write_text

    atomic_write_text(tmp_path / "a.txt", "x")
    umask = os.umask(0)
    os.umask(umask)
    mode = stat.S_IMODE(os.stat(tmp_path / "a.txt").st_mode)
    assert mode == 0o666 & ~umask  # not mkstemp's 0600


# ---------------------------------------------------------------------------------------------
# score_vs_law and the per-episode arrays


def test_score_vs_law_is_the_geometric_mean_of_the_law_over_the_policy():
    from blf_gym.results.metrics import score_vs_law

    law = [0.2, 0.4, 0.8]
    assert score_vs_law(law, law) == pytest.approx(1.0)
    assert score_vs_law([0.1, 0.2, 0.4], law) == pytest.approx(2.0)  # half the error on every joint
    assert score_vs_law([0.1, 0.4, 0.8], law) == pytest.approx(2.0 ** (1 / 3))  # on one joint of three
    assert score_vs_law([0.4, 0.8, 1.6], law) == pytest.approx(0.5)
    assert score_vs_law(None, law) == 0.0  # an episode with no samples
    assert score_vs_law(law, None) is None  # no law, no score


def _ep(err, bound=1.0, n=20):
    """An episode whose error is ``err`` (rad, per joint) at every sample, bounds +-bound."""
    t = np.arange(n) * 1e-3
    e = np.tile(np.asarray(err, dtype=float), (n, 1))
    return _signals(t, e, np.full(n, bound), np.full(n, bound), np.zeros((n, 3)), np.zeros((n, 3)))


def test_per_episode_scores_and_the_certificate():
    law = [_ep([0.1, 0.1, 0.1]), _ep([0.1, 0.1, 0.1]), _ep([2.0, 0.1, 0.1])]  # the law breaks episode 3
    pol = [_ep([0.05, 0.05, 0.05]), _ep([2.0, 0.1, 0.1]), _ep([2.0, 0.1, 0.1])]
    rec = summarize(pol, "p", "residual", "s", 1e-4, law=law)
    assert rec["per_episode_score"] == pytest.approx([2.0, 0.05 ** (1 / 3), 1.0])
    assert rec["per_episode_failed"] == [False, True, True]
    assert rec["per_episode_violations"] == [0, 20, 20]
    # broken where the policy violates and the law does not: episode 2 only
    assert rec["certificate_broken"] == pytest.approx(1 / 3)
    assert rec["law_failure_rate"] == pytest.approx(1 / 3)
    np.testing.assert_allclose(rec["per_episode_rmse_deg"][0], np.degrees([0.05] * 3))
    with pytest.raises(ValueError, match="law trajectories"):
        summarize(pol, "p", "residual", "s", 1e-4, law=law[:2])
    assert summarize(pol, "p", "residual", "s", 1e-4)["per_episode_score"] is None
