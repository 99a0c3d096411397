"""The ``blf-reproduce`` command (baselines.reproduce:main): outputs, selection, errors, divergence.

Runs are 1 s long (--duration 1) to stay fast; the 30 s paper cases are covered by
tests/test_closed_loop.py.
"""

from __future__ import annotations

import contextlib
import csv
import io
import json
import math
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from baselines.reproduce import main

# docs/model.md section 8, copied from its table (not imported from the code under test)
SPEC_FIELDS = (
    "policy", "kind", "scenario", "episodes", "dt", "rmse_deg", "violations", "violation_fraction",
    "max_excursion_deg", "min_margin_deg", "first_violation_s", "failure_rate", "rmse_cvar_deg",
    "torque_rms", "torque_peak", "saturated_fraction", "diverged", "wall_s",
)
PER_JOINT = ("rmse_deg", "violations", "violation_fraction", "max_excursion_deg", "min_margin_deg",
             "torque_rms", "torque_peak", "saturated_fraction")
PRESETS = ("paper-0.1hz", "paper-0.5hz")
CONTROLLERS = ("bc", "lesobc", "proposed")
# docs/model.md section 8: the trajectory channels (q_d is recorded as q_ref, the bounds as k_a / k_b)
TRAJ_ARRAYS = ("t", "q", "q_ref", "e1", "k_a", "k_b", "u", "h_u", "x3", "x3_hat", "x2_hat", "qd")


@pytest.fixture(scope="module")
def full_run(tmp_path_factory):
    out = tmp_path_factory.mktemp("reproduce") / "out"
    stdout, stderr = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(stdout), contextlib.redirect_stderr(stderr):
        rc = main(["--duration", "1", "--out", str(out), "--save-traj", "--no-progress"])
    return rc, out, stdout.getvalue(), stderr.getvalue()


def _table_rows(text: str) -> dict[tuple[str, str], str]:
    rows = {}
    for line in text.splitlines():
        parts = line.split()
        if len(parts) > 2 and parts[0] in PRESETS and parts[2] == "|":
            rows[(parts[0], parts[1])] = line
    return rows


def test_full_run_writes_six_complete_records(full_run):
    rc, out, _, _ = full_run
    assert rc == 0
    data = json.loads((out / "results.json").read_text())
    assert data["schema_version"] == 2 and data["provenance"]["versions"]["numba"]
    recs = data["records"]
    assert len(recs) == 6
    assert sorted((r["scenario"], r["policy"]) for r in recs) == sorted(
        (p, c) for p in PRESETS for c in CONTROLLERS)
    for r in recs:
        assert set(SPEC_FIELDS) <= set(r), set(SPEC_FIELDS) - set(r)
        for f in PER_JOINT:
            assert isinstance(r[f], list) and len(r[f]) == 3, f
        assert r["kind"] == "baseline"
        assert r["episodes"] == 1
        assert r["dt"] == 1e-4  # the default step (docs/model.md section 6)
        assert r["diverged"] is False
        assert r["failure_rate"] in (0.0, 1.0)
        assert r["wall_s"] >= 0.0
        assert all(v >= 0 for v in r["rmse_deg"])
        assert all(isinstance(v, int) for v in r["violations"])


def test_saved_trajectories_match_the_records(full_run):
    _, out, _, _ = full_run
    recs = json.loads((out / "results.json").read_text())["records"]
    names = sorted(p.name for p in (out / "traj").iterdir())
    assert names == sorted(f"{p}__{c}.npz" for p in PRESETS for c in CONTROLLERS)
    for r in recs:
        with np.load(out / "traj" / f"{r['scenario']}__{r['policy']}.npz") as z:
            for name in TRAJ_ARRAYS:
                assert name in z.files, name
            t = z["t"]
            assert t.shape == (1000,)  # 1 s on the 1 ms grid, t = 0 .. 0.999
            np.testing.assert_allclose(t, np.arange(1000) * 1e-3, rtol=0, atol=1e-12)
            for name in TRAJ_ARRAYS[1:]:
                assert z[name].shape == (1000, 3), name
            np.testing.assert_allclose(z["e1"], z["q"] - z["q_ref"], rtol=0, atol=1e-15)
            # the record is a function of the saved signals (docs/model.md section 8 definitions)
            e1 = z["e1"]
            np.testing.assert_allclose(r["rmse_deg"], np.degrees(np.sqrt(np.mean(e1 ** 2, axis=0))),
                                       rtol=1e-10)
            outside = ~((e1 > -z["k_b"]) & (e1 < z["k_a"]))
            assert r["violations"] == outside.sum(axis=0).tolist()
            np.testing.assert_allclose(r["torque_peak"], np.abs(z["u"]).max(axis=0), rtol=1e-12)
            np.testing.assert_allclose(r["torque_rms"], np.sqrt(np.mean(z["u"] ** 2, axis=0)), rtol=1e-10)


def test_table_shows_paper_values_beside_the_measured_rmse(full_run):
    _, out, stdout, _ = full_run
    rows = _table_rows(stdout)
    assert set(rows) == {(p, c) for p in PRESETS for c in CONTROLLERS}
    # Table 3 of Tran et al. (2020), BC at 0.1 Hz, joint 1: 24.5205 deg (and joints 2, 3)
    for v in ("24.5205", "47.3142", "43.4415"):
        assert v in rows[("paper-0.1hz", "bc")]
    # Table 4, proposed at 0.5 Hz
    for v in ("0.0159", "0.0179", "0.0197"):
        assert v in rows[("paper-0.5hz", "proposed")]
    recs = json.loads((out / "results.json").read_text())["records"]
    for r in recs:
        line = rows[(r["scenario"], r["policy"])]
        measured = line.split("|")[1].split()
        assert [float(x) for x in measured] == pytest.approx(r["rmse_deg"], abs=5.1e-5)
        assert "DIVERGED" not in line
    assert "results.json" in stdout


def test_results_csv_has_one_row_per_record(full_run):
    _, out, _, _ = full_run
    recs = json.loads((out / "results.json").read_text())["records"]
    with open(out / "results.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    assert len(rows) == len(recs) == 6
    for row, r in zip(rows, recs):
        assert (row["scenario"], row["policy"], row["kind"]) == (r["scenario"], r["policy"], "baseline")
        for j in range(3):
            assert float(row[f"rmse_deg_{j + 1}"]) == r["rmse_deg"][j]
            assert int(row[f"violations_{j + 1}"]) == r["violations"][j]


def test_one_preset_and_one_controller(tmp_path, capsys):
    rc = main(["--preset", "paper-0.5hz", "--controller", "proposed", "--duration", "1", "--no-progress",
               "--out", str(tmp_path)])
    assert rc == 0
    out = capsys.readouterr().out
    assert list(_table_rows(out)) == [("paper-0.5hz", "proposed")]
    recs = json.loads((tmp_path / "results.json").read_text())["records"]
    assert [(r["scenario"], r["policy"]) for r in recs] == [("paper-0.5hz", "proposed")]
    assert not (tmp_path / "traj").exists()  # no --save-traj


@pytest.mark.parametrize("argv, bad, accepted", [
    (["--preset", "paper-1hz"], "paper-1hz", PRESETS),
    (["--preset", "paper-0.1hz", "paper-2hz"], "paper-2hz", PRESETS),
    (["--controller", "pid"], "pid", CONTROLLERS),
    (["--controller", "proposed", "none"], "none", CONTROLLERS),
])
def test_unknown_names_exit_with_code_2(argv, bad, accepted, capsys, tmp_path):
    rc = main([*argv, "--duration", "1", "--no-progress", "--out", str(tmp_path / "o")])
    assert rc == 2
    err = capsys.readouterr().err
    assert bad in err
    for name in accepted:
        assert name in err
    assert not (tmp_path / "o").exists()  # nothing ran


def test_save_traj_needs_out(capsys):
    rc = main(["--save-traj", "--duration", "1", "--no-progress"])
    assert rc == 2
    captured = capsys.readouterr()
    assert "--out" in captured.err
    assert captured.out == ""  # rejected before any case ran


def test_the_papers_1ms_step_is_reported_as_diverged(tmp_path, capsys):
    # docs/model.md: the paper's 1 ms step diverges with Table 2's gains; it must fail loudly, and
    # with every case diverged the command fails (exit 1), still writing what it measured
    rc = main(["--dt", "1e-3", "--duration", "1", "--preset", "paper-0.1hz", "--no-progress",
               "--out", str(tmp_path)])
    assert rc == 1
    captured = capsys.readouterr()
    rows = _table_rows(captured.out)
    assert set(rows) == {("paper-0.1hz", c) for c in CONTROLLERS}
    for line in rows.values():
        assert "DIVERGED" in line
    recs = json.loads((tmp_path / "results.json").read_text())["records"]
    assert len(recs) == 3
    for r in recs:
        assert r["diverged"] is True
        assert r["dt"] == 1e-3
        assert r["failure_rate"] == 1.0
    assert "diverged" in captured.err


def test_console_script_runs(tmp_path):
    exe = Path(sys.executable).parent / "blf-reproduce"
    assert exe.exists(), exe
    env = {**os.environ, "PYTHONWARNINGS": "ignore"}
    p = subprocess.run([str(exe), "--preset", "paper-0.1hz", "--controller", "lesobc", "--duration", "1",
                        "--no-progress", "--out", str(tmp_path), "--save-traj"],
                       capture_output=True, text=True, timeout=300, env=env, cwd=tmp_path)
    assert p.returncode == 0, p.stderr
    rows = _table_rows(p.stdout)
    assert list(rows) == [("paper-0.1hz", "lesobc")]
    # Table 3, LESOBC at 0.1 Hz
    assert "0.0055" in rows[("paper-0.1hz", "lesobc")]
    recs = json.loads((tmp_path / "results.json").read_text())["records"]
    assert len(recs) == 1 and recs[0]["policy"] == "lesobc" and recs[0]["kind"] == "baseline"
    assert (tmp_path / "traj" / "paper-0.1hz__lesobc.npz").exists()
    assert math.isfinite(recs[0]["rmse_deg"][0])
