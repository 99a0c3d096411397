"""The two example plug-in packages of examples/, installed by the README's test command, used by
name through the three commands and gym.make with no edit to blf-gym.

* ``blf-integral`` registers ``proposed_integral``, a controller with n states of its own;
* ``blf-eso4`` registers ``eso4``, an observer with 4n states that pairs with ``proposed``.
"""

from __future__ import annotations

import json
import subprocess
import sys
from importlib.metadata import entry_points
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest

import blf_gym  # noqa: F401
from blf_gym.plugins.registry import available_controllers, available_observers
from blf_gym.model.params import preset
from blf_gym.kernel.simulate import simulate

ROOT = Path(__file__).resolve().parents[1]
INSTALL = 'pip install -c constraints-cpu.txt -e ".[dev,sweep,zoo,jax,mpc,docs]" ./examples/blf_integral ./examples/blf_eso4'


@pytest.fixture(scope="module", autouse=True)
def installed():
    names = {ep.name for ep in entry_points(group="blf_gym.controllers")} | {
        ep.name for ep in entry_points(group="blf_gym.observers")}
    missing = {"proposed_integral", "eso4"} - names
    assert not missing, f"the example plug-ins {sorted(missing)} are not installed: run the README's test command ({INSTALL})"


def _cli(*args: str, tmp: Path) -> subprocess.CompletedProcess:
    p = subprocess.run([sys.executable, "-m", *args], capture_output=True, text=True, timeout=900, cwd=tmp)
    assert p.returncode == 0, p.stderr[-3000:]
    return p


def test_the_registry_lists_them():
    assert "proposed_integral" in available_controllers()
    assert "eso4" in available_observers()


def test_blf_reproduce_runs_them_by_name(tmp_path):
    out = tmp_path / "rep"
    _cli("baselines.reproduce", "--controller", "proposed", "proposed_integral", "--preset", "paper-0.1hz",
         "--duration", "5", "--out", str(out), "--no-progress", tmp=tmp_path)
    rows = {r["policy"]: r for r in json.loads((out / "results.json").read_text())["records"]}
    assert set(rows) == {"proposed", "proposed_integral"}
    for r in rows.values():
        assert sum(r["violations"]) == 0 and not r["diverged"] and r["observer"] == "leso"
    out = tmp_path / "rep_eso4"
    _cli("baselines.reproduce", "--controller", "proposed", "--observer", "eso4", "--preset", "paper-0.1hz",
         "--duration", "5", "--out", str(out), "--no-progress", tmp=tmp_path)
    data = json.loads((out / "results.json").read_text())
    assert data["records"][0]["policy"] == "proposed" and sum(data["records"][0]["violations"]) == 0
    assert data["records"][0]["observer"] == "eso4"  # the results record which observer produced them


def test_blf_eval_scores_them_by_name(tmp_path):
    out = tmp_path / "ev"
    _cli("agents.evaluate", "--controllers", "proposed", "proposed_integral", "--agents", "--scenarios",
         "paper-0.1hz", "--suite-seeds", "0", "--duration", "5", "--out", str(out), "--no-plots", "--no-progress",
         tmp=tmp_path)
    res = json.loads((out / "results.json").read_text())
    policies = {r["policy"] for r in res["records"]}
    assert {"proposed", "proposed_integral"} <= policies
    _cli("agents.evaluate", "--controllers", "proposed", "--observer", "eso4", "--agents", "--scenarios",
         "paper-0.1hz", "--suite-seeds", "0", "--duration", "5", "--out", str(tmp_path / "ev2"), "--no-plots",
         "--no-progress", tmp=tmp_path)
    recs = json.loads((tmp_path / "ev2" / "results.json").read_text())["records"]
    assert recs and all(r["observer"] == "eso4" for r in recs)


def test_gym_make_takes_them_by_name():
    env = gym.make("PlanarBLFResidual-v0", controller="proposed_integral", duration=1.0)
    obs, _ = env.reset(seed=0)
    for _ in range(10):
        obs, r, term, trunc, info = env.step(np.zeros(3, dtype=np.float32))
    assert not term and np.all(np.isfinite(obs))
    # the controller's own state is the integral of the measured error it publishes
    assert set(info["controller_outputs"]) == {"z1", "z2_hat", "integral"}
    assert np.any(info["controller_outputs"]["integral"] != 0.0)
    env = gym.make("PlanarBLFResidual-v0", observer="eso4", duration=1.0)
    obs, _ = env.reset(seed=0)
    core = env.unwrapped.core
    assert core.loop.nx == 2 * 3 + 4 * 3  # q, qd and the observer's 4n states
    for _ in range(10):
        obs, r, term, trunc, info = env.step(np.zeros(3, dtype=np.float32))
    assert not term and np.all(np.isfinite(info["x3_hat"]))


def test_the_integral_law_removes_part_of_the_steady_error():
    # integral action on a slowly varying error: over the 0.1 Hz case's last 10 s the mean error
    # (its bias) of each joint is smaller in size than the proposed law's
    sc = preset("paper-0.1hz")
    base, integ = simulate(sc, "proposed"), simulate(sc, "proposed_integral")
    late = base.t > 20.0
    assert not integ.diverged and integ.step_violations == 0
    b0 = np.abs(base.e1[late].mean(axis=0))
    b1 = np.abs(integ.e1[late].mean(axis=0))
    assert np.all(b1 < b0), (np.degrees(b0), np.degrees(b1))
