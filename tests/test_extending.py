"""docs/extending.md, followed recipe by recipe from the page's own code blocks.

Each recipe is one file: a controller module, an observer module, a row of the observation table
and a patch of blf_gym/kernel/reward.py. The expected values are independent of the code under test: the
integral state against a sum of the recorded error, the observer against the true velocity, the
observation entry against the law's published output, the reward term against the recorded torques.
"""

from __future__ import annotations

import importlib
import json
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest

import blf_gym  # noqa: F401 (registers the ids)
import blf_gym.envs.observation as observation
from blf_gym.model.params import preset
from blf_gym.kernel.simulate import ClosedLoop, simulate

ROOT = Path(__file__).resolve().parents[1]
DOC = (ROOT / "docs" / "extending.md").read_text()


def recipe(name: str) -> str:
    m = re.search(rf"<!-- recipe:{name} -->\s*```(\w+)\n(.*?)```", DOC, re.S)
    assert m, f"docs/extending.md has no recipe {name!r}"
    return m.group(2)


@pytest.fixture(scope="module")
def modules(tmp_path_factory):
    d = tmp_path_factory.mktemp("recipes")
    (d / "my_pid.py").write_text(recipe("controller"))
    (d / "my_hgo.py").write_text(recipe("observer"))
    sys.path.insert(0, str(d))
    try:
        yield importlib.import_module("my_pid"), importlib.import_module("my_hgo")
    finally:
        sys.path.remove(str(d))


@pytest.mark.slow
def test_the_controller_recipe_integrates_its_own_state(modules):
    my_pid, _ = modules
    sc = preset("paper-0.1hz", duration=2.0)
    tr = simulate(sc, my_pid.my_pid())
    assert not tr.diverged, tr.message
    loop = ClosedLoop([sc], my_pid.my_pid())
    loop.advance(sc.sim.n_steps, record_samples=0)
    n = 3
    s = loop.X[0, 2 * n + loop.connection.n_obs :]
    # s = integral of (y - q_d) dt (no noise: y = q); the 1 ms samples' rectangle sum is within
    # a fraction of a per cent of ODE3's integral over 2 s
    want = tr.e1.sum(axis=0) * sc.sim.sample_period
    np.testing.assert_allclose(s, want, rtol=5e-3, atol=1e-7)
    assert np.all(np.abs(s) > 0)
    # the published output is the measured error at the start of the last integration step
    err = loop.outputs()["error"][0]
    assert np.all(np.abs(err) < 0.05) and np.any(err != 0.0)


@pytest.mark.slow
def test_the_observer_recipe_estimates_the_velocity_and_is_refused_where_it_cannot_serve(modules):
    my_pid, my_hgo = modules
    sc = preset("paper-0.1hz", duration=2.0)
    tr = simulate(sc, my_pid.my_pid(), my_hgo.my_hgo())
    assert not tr.diverged, tr.message
    late = tr.t > 0.5
    assert np.abs(tr.x1_hat - tr.q)[late].max() < 0.05  # it tracks the angles
    # Without a disturbance state it lags the true velocity by the quasi-static error of its
    # equations, qd - x2_hat = 2 x3 / k0 (x3 the recorded true lumped disturbance): a wrong gain
    # (3 k0, say) would move it by half
    bias = 2.0 * tr.x3[late] / 150.0
    assert np.all(np.abs((tr.qd - tr.x2_hat)[late] - bias).max(axis=0) < 0.2 * np.abs(bias).max(axis=0))
    assert np.all(np.isnan(tr.x3_hat))  # it has no x3_hat, and the record says so
    with pytest.raises(ValueError, match=r"controller 'proposed'\.output reads the signal 'x3_hat', which no block "
                                         r"provides with observer 'my_hgo'"):
        simulate(sc, "proposed", my_hgo.my_hgo())
    with pytest.raises(ValueError, match="'x3_hat'.*my_hgo"):
        gym.make("PlanarBLFResidual-v0", controller=my_pid.my_pid(), observer=my_hgo.my_hgo())


def test_the_observation_recipe_adds_an_opt_in_entry(monkeypatch):
    row = eval(recipe("observation").strip().rstrip(","), {"Entry": observation.Entry})  # noqa: S307 (our own doc)
    assert row.kind == "optional"
    monkeypatch.setattr(observation, "OBSERVATION", observation.OBSERVATION + (row,))
    default = gym.make("PlanarBLFResidual-v0")
    assert default.observation_space.shape == (31,)  # opt-in: the shipped agents' layout is unchanged
    env = gym.make("PlanarBLFResidual-v0", observation_extras=("z1",))
    assert env.observation_space.shape == (34,)
    names = [r[0] for r in observation.observation_layout(3, extras=("z1",))]
    assert names[-3:] == ["z1_1 = y_1 - q_d_1 (the law's)", "z1_2 = y_2 - q_d_2 (the law's)",
                          "z1_3 = y_3 - q_d_3 (the law's)"]
    obs0, _ = default.reset(seed=3)
    obs, _ = env.reset(seed=3)
    np.testing.assert_array_equal(obs[:31], obs0)
    for _ in range(3):
        obs, _, _, _, info = env.step(np.zeros(3, dtype=np.float32))
    np.testing.assert_array_equal(obs[-3:], info["controller_outputs"]["z1"].astype(np.float32))
    assert np.any(obs[-3:] != 0.0)
    with pytest.raises(ValueError, match="observation_extras"):
        gym.make("PlanarBLFResidual-v0", observation_extras=("nonexistent",))
    with pytest.raises(ValueError, match="z2_hat.*'none'"):
        gym.make("PlanarBLF-v0", observation_extras=("z2_hat",))  # plain mode publishes no z2_hat


def _apply(patch: str, path: Path) -> None:
    """Apply the recipe's hunks: each replaces its context and '-' lines by its context and '+' lines."""
    text = path.read_text()
    for hunk in patch.split("\n@@")[1:]:
        lines = hunk.split("\n")[1:]
        old = [ln[1:] for ln in lines if ln[:1] in (" ", "-")]
        new = [ln[1:] for ln in lines if ln[:1] in (" ", "+")]
        before = "\n".join(old).rstrip("\n")
        assert text.count(before) == 1, f"hunk context not found once in {path.name}:\n{before}"
        text = text.replace(before, "\n".join(new).rstrip("\n"))
    path.write_text(text)


_REWARD_PROBE = r"""
import json, numpy as np, gymnasium as gym, blf_gym
assert blf_gym.__file__.startswith(%(root)r), blf_gym.__file__
out = {}
for w in (0.0, 0.5):
    env = gym.make("PlanarBLFResidual-v0", reward_weights={"saturation": w}, record=True, duration=0.5,
                   max_torque=5.0, terminate_on_violation=False)
    env.reset(seed=0)
    steps = [env.step(np.zeros(3, dtype=np.float32)) for _ in range(5)]
    out[str(w)] = [float(s[1]) for s in steps]
    out["term" + str(w)] = [float(s[4]["reward_info"]["saturation"]) for s in steps]
    out["u"] = env.unwrapped.core.trajectory(0).u.tolist()
print(json.dumps(out))
"""


@pytest.mark.slow
def test_the_reward_recipe_is_a_change_in_one_file(tmp_path):
    shutil.copytree(ROOT / "blf_gym", tmp_path / "blf_gym", ignore=shutil.ignore_patterns("__pycache__"))
    _apply(recipe("reward"), tmp_path / "blf_gym" / "kernel" / "reward.py")
    env = {**os.environ, "PYTHONPATH": str(tmp_path)}
    p = subprocess.run([sys.executable, "-c", _REWARD_PROBE % {"root": str(tmp_path)}], capture_output=True,
                       text=True, timeout=600, env=env, cwd=tmp_path)
    assert p.returncode == 0, p.stderr[-3000:]
    res = json.loads(p.stdout.strip().splitlines()[-1])
    u = np.array(res["u"])  # (50 samples, 3): 10 samples per 10 ms agent step
    at_limit = [np.mean(np.abs(u[10 * k : 10 * k + 10]) >= 5.0) for k in range(5)]
    assert 0 < max(at_limit) and min(at_limit) < 1  # the check below sees both cases
    np.testing.assert_allclose(res["term0.5"], [-0.5 * f for f in at_limit], rtol=1e-12, atol=0)
    # the default alive grows by the term's weight times its bound (1), so the reward changes by 0.5 (1 - fraction)
    got = np.array(res["0.5"]) - np.array(res["0.0"])
    np.testing.assert_allclose(got, [0.5 * (1 - f) for f in at_limit], rtol=1e-9, atol=1e-12)


_KNOB_PROBE = r"""
import json, numpy as np, blf_gym
from blf_gym.envs import scenarios
from blf_gym.model.params import preset
assert blf_gym.__file__.startswith(%(root)r), blf_gym.__file__
out = {"names": list(scenarios.VARIATIONS), "doc": scenarios.__doc__, "suites": {}}
for suite, seeds in (("randomized", range(10_000, 10_060)), ("stress", range(20_000, 20_200))):
    rows = []
    for s in seeds:
        rng = np.random.default_rng(s)
        sc = scenarios.sample_suite(rng, name=suite)
        rows.append({"repr": repr(sc), "wrench": list(sc.force.wrench), "outside": scenarios.outside_training(sc),
                     "state": repr(rng.bit_generator.state)})
    out["suites"][suite] = rows
sc = scenarios.apply_variations(preset("paper-0.1hz"), {"lateral_force": 5.0, "force": 30.0})
out["applied"] = list(sc.force.wrench)
try:
    scenarios.check_variations({"lateral_force": 25.0})
except ValueError as exc:
    out["refused"] = str(exc)
print(json.dumps(out))
"""


def test_the_scenario_knob_recipe_is_one_row_and_changes_no_existing_draw(tmp_path):
    from dataclasses import replace as dc_replace

    from blf_gym.envs import scenarios

    shutil.copytree(ROOT / "blf_gym", tmp_path / "blf_gym", ignore=shutil.ignore_patterns("__pycache__"))
    path = tmp_path / "blf_gym" / "envs" / "scenarios.py"
    text = path.read_text()
    end = "\n)\n\"\"\"The scenario knobs, one row each"
    assert text.count(end) == 1  # the end of the KNOBS table, where the page says to add the row
    path.write_text(text.replace(end, "\n" + recipe("knob").rstrip("\n") + end))
    p = subprocess.run([sys.executable, "-c", _KNOB_PROBE % {"root": str(tmp_path)}], capture_output=True, text=True,
                       timeout=300, env={**os.environ, "PYTHONPATH": str(tmp_path)}, cwd=tmp_path)
    assert p.returncode == 0, p.stderr[-3000:]
    res = json.loads(p.stdout.strip().splitlines()[-1])
    assert res["names"] == [*scenarios.VARIATIONS, "lateral_force"]
    assert "``lateral_force``" in res["doc"] and "f_ext along +y" in res["doc"]  # the generated table
    np.testing.assert_array_equal(res["applied"], [30.0, 5.0, 0.0])
    assert "variation 'lateral_force' must be a finite real number in [-20, 20] N" in res["refused"]
    for suite, seeds in (("randomized", range(10_000, 10_060)), ("stress", range(20_000, 20_200))):
        rows = res["suites"][suite]
        lateral = np.array([r["wrench"][1] for r in rows])
        pushed = 0
        for s, row in zip(seeds, rows):
            rng = np.random.default_rng(s)
            before = scenarios.sample_suite(rng, name=suite)  # this package, without the knob
            # every existing knob draws what it drew before, and the suite's generator ends where it
            # did: with the new knob's value put back to the base's 0 N, the scenario is the same
            wrench = (row["wrench"][0], 0.0, row["wrench"][2])
            assert row["state"] == repr(rng.bit_generator.state)
            assert row["repr"] == repr(dc_replace(before, force=dc_replace(before.force, wrench=tuple(row["wrench"]))))
            assert tuple(before.force.wrench) == wrench
            assert set(row["outside"]) - {"lateral_force"} == set(scenarios.outside_training(before))
            pushed += "lateral_force" in row["outside"]
        if suite == "randomized":
            assert np.all(np.abs(lateral) <= 10.0) and np.ptp(lateral) > 10.0  # drawn, across its range
            assert pushed == 0
        else:
            assert np.all(np.abs(lateral) <= 40.0)
            assert 25 <= pushed <= 75  # pushed one time in four: 50 of 200 expected (binomial sd 6.1)


def test_an_observation_row_reads_any_named_signal(monkeypatch):
    """Rows of each source kind, appended to the table, are filled from their signals: the true
    angles, an observer state, a bound's second derivative and a last-step column, each compared
    with the same signal read independently (the loop's state, the bounds' own function, info)."""
    from blf_gym.model.bounds import BOUND_LEN, bounds_into

    E = observation.Entry
    rows = (E("q_true", None, "q_{j}", "rad", -50.0, 50.0, "optional", "state:q"),
            E("x1h", None, "x1_hat_{j}", "rad", -50.0, 50.0, "optional", "observer:x1_hat"),
            E("kbdd", 1, "k_b''", "rad/s^2", -1e3, 1e3, "optional", "bounds:k_b_ddot"),
            E("x3_last", None, "x3_{j}", "rad/s^2", -1e9, 1e9, "optional", "last:x3", 1e4))
    monkeypatch.setattr(observation, "OBSERVATION", observation.OBSERVATION + rows)
    env = gym.make("PlanarBLFResidual-v0", observation_extras=tuple(r.group for r in rows),
                   terminate_on_violation=False)
    assert env.observation_space.shape == (41,)
    core = env.unwrapped.core
    env.reset(seed=2)
    sc = core.scenarios[0]
    rng = np.random.default_rng(0)
    for _ in range(5):
        obs, _, _, _, info = env.step(rng.uniform(-0.5, 0.5, 3).astype(np.float32))
        X = core.loop.X[0]
        np.testing.assert_array_equal(obs[31:34], X[:3].astype(np.float32))
        np.testing.assert_array_equal(obs[34:37], X[6:9].astype(np.float32))  # the LESO's first state part
        bnd = np.zeros(BOUND_LEN)
        bounds_into(float(info["time"]), sc.bounds.pack(), bnd)
        assert obs[37] == np.float32(bnd[2 + 3])  # k_b'' (k_a, k_a', k_a'', then k_b, k_b', k_b'')
        np.testing.assert_array_equal(obs[38:41], (1e4 * np.tanh(info["x3"] / 1e4)).astype(np.float32))
    bad = (E("oops", None, "?", "-", -1.0, 1.0, "optional", "nowhere:x"),
           E("short", None, "k_a", "rad", 0.0, 10.0, "optional", "bounds:k_a"))
    monkeypatch.setattr(observation, "OBSERVATION", observation.OBSERVATION + bad)
    with pytest.raises(ValueError, match="'oops': unknown source 'nowhere:x'"):
        gym.make("PlanarBLFResidual-v0", observation_extras=("oops",))
    with pytest.raises(ValueError, match="'short': its source 'bounds:k_a' has 1 entries, not 3"):
        gym.make("PlanarBLFResidual-v0", observation_extras=("short",))


def test_the_algorithm_recipe_trains_and_loads_through_its_entry_point(tmp_path):
    """The recipe's entry-point table, installed as a distribution of its own (a dist-info folder on
    the path, as pip would leave it), makes ``blf-train --algo a2c`` train SB3's A2C, and the run
    loads back through the same entry point; without the table the name is refused."""
    import subprocess
    import sys

    table = recipe("algorithm")
    m = re.search(r'\[project\.entry-points\."blf_gym\.algorithms"\]\n(\w+) = "([\w.]+:\w+)"', table)
    assert m, table
    name, target = m.groups()
    dist = tmp_path / "site" / "my_algorithms-0.1.dist-info"
    dist.mkdir(parents=True)
    (dist / "METADATA").write_text("Metadata-Version: 2.1\nName: my-algorithms\nVersion: 0.1\n")
    (dist / "entry_points.txt").write_text(f"[blf_gym.algorithms]\n{name} = {target}\n")
    cfg = tmp_path / "a2c.yaml"
    cfg.write_text("n_envs: 2\nnormalize: false\nenv:\n  control_period: 0.01\n  duration: 0.2\n"
                   "hyperparams: {n_steps: 8}\npolicy_kwargs:\n  net_arch: [16]\neval_freq: 1000\n"
                   "checkpoint_freq: 1000\n")
    out = tmp_path / "run"
    script = (
        "import json, sys\n"
        "from agents.train import main\n"
        f"assert main(['--algo', {name!r}, '--mode', 'residual', '--timesteps', '64', '--config', {str(cfg)!r},\n"
        f"             '--out', {str(out)!r}, '--no-progress']) == 0\n"
        "from agents.evaluate import load_agent\n"
        f"model, meta, _ = load_agent({str(out)!r})\n"
        "print(json.dumps({'algo': meta['algo'], 'cls': type(model).__name__, 'steps': int(model.num_timesteps)}))\n")
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(tmp_path / "site"), str(ROOT)])}
    p = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, env=env, timeout=600)
    assert p.returncode == 0, p.stderr[-3000:]
    res = json.loads(p.stdout.strip().splitlines()[-1])
    assert res == {"algo": name, "cls": target.split(":")[1], "steps": 64}
    # the same command without the registration: refused by name, with the registered ones listed
    env["PYTHONPATH"] = str(ROOT)
    p = subprocess.run([sys.executable, "-m", "agents.train", "--algo", name, "--out", str(tmp_path / "x")],
                       capture_output=True, text=True, env=env, timeout=600)
    assert p.returncode != 0 and f"'{name}'" in p.stderr and "ppo" in p.stderr
