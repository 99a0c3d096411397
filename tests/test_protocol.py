"""A comparison you can trust: what the agent sees, what the counters mean, the one agent loader,
the episode's totals, the held-out stress suite and the provenance of every result."""

from __future__ import annotations

import json
import pickle
from dataclasses import replace

import gymnasium as gym
import numpy as np
import pytest

import blf_gym  # noqa: F401
from blf_gym.envs.envcore import observation_index
from blf_gym.results.metrics import summarize
from blf_gym.model.params import preset
from blf_gym.envs.scenarios import (
    STRESS_RANGES,
    STRESS_SEED_OFFSET,
    SUITE_RANGES,
    outside_training,
    sample_suite,
)
from blf_gym.kernel.simulate import simulate

IDX = observation_index(3)


def _episode(env, action=None):
    a = np.zeros(3, dtype=np.float32) if action is None else action
    obs, info = env.reset(seed=0)
    while True:
        obs, _, term, trunc, info = env.step(a)
        if term or trunc:
            return obs, info


# ---- 2. the observation's error is the measured one ------------------------------------------

def test_the_normalized_error_in_the_observation_uses_the_measured_angles():
    env = gym.make("PlanarBLFResidual-v0", angle_noise_std=2e-4, duration=0.2, terminate_on_violation=False)
    env.reset(seed=1)
    for _ in range(10):
        obs, _, _, _, info = env.step(np.zeros(3, dtype=np.float32))
        y, qd_ref = obs[IDX["y"]].astype(float), obs[IDX["q_d"]].astype(float)
        ka, kb = float(obs[IDX["k_a"]][0]), float(obs[IDX["k_b"]][0])
        e_meas = y - qd_ref
        expected = np.where(e_meas >= 0, e_meas / ka, e_meas / kb)
        # float32 rounding of angles near 1 rad, over bounds of about 0.3 rad
        np.testing.assert_allclose(obs[IDX["e1_normalized"]], expected, atol=2e-6)
        e_true = np.where(info["e1"] >= 0, info["e1"] / ka, info["e1"] / kb)
        assert np.max(np.abs(obs[IDX["e1_normalized"]] - e_true)) > 1e-5  # the noise shows


# ---- 3. counters mean the same on both paths --------------------------------------------------

def test_env_trajectories_count_like_the_inner_path():
    env = gym.make("PlanarBLFResidual-v0", controller="lesobc", scenario="paper-0.5hz", duration=6.0,
                   terminate_on_violation=False, record=True)
    _episode(env)
    tr_env = env.unwrapped.trajectory()
    tr_in = simulate(preset("paper-0.5hz", duration=6.0), "lesobc")
    assert tr_in.step_violations > 0  # LESOBC breaks the bounds at 0.5 Hz (docs/model.md section 7)
    for k in ("step_violations", "first_violation_step_time", "saturated_steps", "diverged", "divergence_code"):
        assert getattr(tr_env, k) == getattr(tr_in, k), k
    np.testing.assert_array_equal(tr_env.e1, tr_in.e1)


# ---- 5. the episode's totals ------------------------------------------------------------------

def test_episode_metrics_on_the_last_step_equal_blf_eval_s():
    env = gym.make("PlanarBLFResidual-v0", controller="lesobc", scenario="paper-0.5hz", duration=6.0,
                   terminate_on_violation=False, record=True)
    _, info = _episode(env)
    em = info["episode_metrics"]
    rec = summarize([env.unwrapped.trajectory()], "x", "residual", "s", 1e-4)
    np.testing.assert_allclose(em["rmse_deg"], rec["rmse_deg"], rtol=1e-12)
    assert em["violating_samples"] == rec["per_episode_violations"][0] > 0
    assert em["first_violation_s"] == pytest.approx(rec["first_violation_s"])
    assert em["truncation_reason"] == "time_limit" and em["termination_reason"] is None
    assert "episode" not in info  # Gymnasium's RecordEpisodeStatistics owns that key
    # an episode ended by a violation says so
    env = gym.make("PlanarBLFResidual-v0", controller="lesobc", scenario="paper-0.5hz")
    _, info = _episode(env)
    assert info["episode_metrics"]["termination_reason"] == "violation"
    assert info["episode_metrics"]["violating_steps"] >= 1


def test_the_vector_env_reports_episode_metrics_per_arm():
    venv = gym.make_vec("PlanarBLFResidual-v0", num_envs=2, duration=0.05, vectorization_mode="vector_entry_point")
    venv.reset(seed=0)
    for _ in range(5):
        _, _, term, trunc, info = venv.step(np.zeros((2, 3), dtype=np.float32))
    assert (term | trunc).all()
    assert all(isinstance(m, dict) and m["samples"] == 50 for m in info["episode_metrics"])


# ---- 4. one loader that refuses what cannot be scored -----------------------------------------

@pytest.fixture(scope="module")
def tiny_run(tmp_path_factory):
    from agents.train import main as train_main

    d = tmp_path_factory.mktemp("run")
    cfg = d / "c.yaml"
    cfg.write_text("n_envs: 2\nnormalize: true\nenv: {duration: 0.1}\nhyperparams: {n_steps: 16, batch_size: 32, "
                   "n_epochs: 1}\npolicy_kwargs: {net_arch: [8]}\neval_freq: 1000\ncurve_suite_seeds: 1\n")
    assert train_main(["--timesteps", "32", "--config", str(cfg), "--out", str(d / "run"), "--no-progress"]) == 0
    return d / "run"


def test_the_agent_loader_refuses_a_missing_or_corrupt_normalization_or_metadata(tiny_run, tmp_path):
    import shutil

    from agents import load_agent

    model, meta, norm = load_agent(tiny_run)
    assert norm is not None and meta["env_kwargs"]["controller"] == "proposed"
    bad = tmp_path / "bad"
    shutil.copytree(tiny_run, bad)
    (bad / "vecnormalize.pkl").unlink()
    with pytest.raises(ValueError, match=r"vecnormalize\.pkl: missing.*normalization"):
        load_agent(bad)
    (bad / "vecnormalize.pkl").write_bytes(b"not a pickle")
    with pytest.raises(ValueError, match=r"vecnormalize\.pkl: not readable"):
        load_agent(bad)
    with open(bad / "vecnormalize.pkl", "wb") as f:
        pickle.dump({"some": "thing"}, f)
    with pytest.raises(ValueError, match=r"vecnormalize\.pkl"):
        load_agent(bad)
    shutil.copy(tiny_run / "vecnormalize.pkl", bad / "vecnormalize.pkl")
    (bad / "metadata.json").write_text("")
    with pytest.raises(ValueError, match=r"metadata\.json: not readable as JSON"):
        load_agent(bad)


def test_blf_eval_exits_2_naming_the_missing_statistics(tiny_run, tmp_path, capsys):
    import shutil

    from agents.evaluate import main as eval_main

    bad = tmp_path / "bad"
    shutil.copytree(tiny_run, bad)
    (bad / "vecnormalize.pkl").unlink()
    assert eval_main(["--controllers", "--agents", str(bad), "--suite-seeds", "0", "--no-progress"]) == 2
    assert "vecnormalize.pkl: missing" in capsys.readouterr().err


# ---- 6. the law scores exactly 1 against itself, under noise, on the env path ----------------

def test_a_zero_residual_scores_exactly_one_on_the_same_noise():
    from agents.episodes import _ZeroResidual, evaluate_agent, law_reference

    scs = [replace(sample_suite(np.random.default_rng(10_000 + k)), sim=replace(preset("paper-0.1hz").sim,
                                                                                 duration=1.0))
           for k in range(3)]
    assert all(sc.angle_noise_std > 0 for sc in scs)
    meta = {"mode": "residual", "env_kwargs": {"controller": "proposed", "control_period": 0.01}}
    trajs = evaluate_agent(_ZeroResidual(), meta, None, scs)
    rec = summarize(trajs, "zero", "residual", "randomized", 1e-4, law=law_reference(scs, meta))
    assert rec["per_episode_score"] == [1.0, 1.0, 1.0] and rec["certificate_broken"] == 0.0


# ---- 7. the stress suite ----------------------------------------------------------------------

def test_every_stress_episode_leaves_the_training_ranges_and_stays_in_the_stress_ranges():
    pushed = {}
    edge = {"onset_at_0_or_a_fold": 0, "fast": 0, "light": 0, "heavy": 0}
    for k in range(300):
        sc = sample_suite(np.random.default_rng(STRESS_SEED_OFFSET + k), name="stress")
        out = outside_training(sc)
        assert out, k  # at least one knob outside the training suite's ranges
        for knob in out:
            pushed[knob] = pushed.get(knob, 0) + 1
        f = sc.reference.frequency
        assert STRESS_RANGES["frequency"][0] <= f <= STRESS_RANGES["frequency"][1]
        assert STRESS_RANGES["payload"][0] <= sc.arm.masses[-1] <= STRESS_RANGES["payload"][1]
        assert sc.angle_noise_std <= STRESS_RANGES["angle_noise_std"][1]
        assert max(abs(e) for e in sc.initial_error) <= STRESS_RANGES["initial_error"][1]
        on = sc.force.onset
        if "force_onset" in out:
            folds = [(2 * i + 1) / (2 * f) for i in range(40)]
            assert on == 0.0 or min(abs(on - t) for t in folds) < 1e-9
            edge["onset_at_0_or_a_fold"] += 1
        edge["fast"] += f > SUITE_RANGES["frequency"][1]
        edge["light"] += sc.arm.masses[-1] < SUITE_RANGES["payload"][0]
        edge["heavy"] += sc.arm.masses[-1] > SUITE_RANGES["payload"][1]
    assert set(pushed) == set(SUITE_RANGES)  # every knob gets pushed
    assert all(v > 0 for v in edge.values()), edge
    # reproducible from its seed, and apart from the training suite's draws
    a = sample_suite(np.random.default_rng(STRESS_SEED_OFFSET), name="stress")
    assert a == sample_suite(np.random.default_rng(STRESS_SEED_OFFSET), name="stress")
    assert not outside_training(sample_suite(np.random.default_rng(STRESS_SEED_OFFSET)))


def test_the_stress_suite_is_an_env_scenario_but_never_a_training_one(tmp_path, capsys):
    from agents.train import main as train_main

    env = gym.make("PlanarBLFResidual-v0", scenario="stress")
    env.reset(seed=5)
    assert outside_training(env.unwrapped.scenario)
    assert train_main(["--scenario", "stress", "--timesteps", "10", "--out", str(tmp_path / "x"),
                       "--no-progress"]) == 2
    assert "held out" in capsys.readouterr().err
    assert not (tmp_path / "x").exists()


# ---- 8. provenance ----------------------------------------------------------------------------

def test_a_varied_label_names_its_variation_or_says_custom():
    from agents.evaluate import build_scenarios, variation_label

    groups = build_scenarios(["paper-0.1hz"], 0, {"frequency": 0.5}, 1.0)
    assert groups[0][0] == "paper-0.1hz+frequency=0.5"
    assert groups[0][1][0].reference.frequency == 0.5  # what the label says is what runs
    assert variation_label({}) == ""
    assert variation_label({"force": 20, "frequency": 0.5}) == "+force=20,frequency=0.5"
    assert variation_label({"payload": 0.1, "force": 55, "frequency": 0.3, "angle_noise_std": 0.001}) == "+custom"


def test_results_record_what_produced_them(tiny_run, tmp_path):
    from agents.evaluate import main as eval_main

    out = tmp_path / "ev"
    assert eval_main(["--controllers", "proposed", "--agents", str(tiny_run), "--duration", "0.1",
                      "--scenarios", "paper-0.1hz", "--suite", "stress", "--suite-seeds", "2",
                      "--scenario-kwargs", '{"payload": 0.12}', "--out", str(out), "--no-plots",
                      "--no-progress"]) == 0
    data = json.loads((out / "results.json").read_text())
    labels = {r["scenario"] for r in data["records"]}
    # a varied group is never unlabelled, and its label names the variation
    assert labels == {"paper-0.1hz+payload=0.12", "stress+payload=0.12"}
    for r in data["records"]:
        assert r["scenario_kwargs"] == {"payload": 0.12}
        if r["scenario"].startswith("stress"):
            assert r["suite"] == "stress" and r["suite_seeds"] == [STRESS_SEED_OFFSET, STRESS_SEED_OFFSET + 1]
        if r["kind"] == "residual":
            assert r["train_seed"] == 0 and r["env_kwargs"]["duration"] == 0.1
    prov = data["provenance"]
    assert prov["versions"]["blf-gym"] and "--scenario-kwargs" in prov["command"]
    csv_text = (out / "results.csv").read_text()
    assert "scenario_kwargs" in csv_text.splitlines()[0] and "payload" in csv_text


def test_the_suites_seed_ranges_never_meet():
    # each suite's episode k uses seed offset + k: the ranges stay apart for every count a command
    # scores (blf-eval's protocol, the certificate suite's 120 cases, a falsifier's replays use
    # their own seeds), and every training seed an agent uses lies below the first of them
    from blf_gym.envs import protocol as p

    starts = sorted(p.suite_seed_offset(s) for s in p.SUITES)
    assert starts == [p.EVAL_SEED_OFFSET, p.STRESS_SEED_OFFSET, p.CERTIFICATE_SEED_OFFSET]
    assert all(b - a >= p.SUITE_SEED_SPAN for a, b in zip(starts, starts[1:]))
    assert max(p.PROTOCOL_SEEDS.values()) < p.SUITE_SEED_SPAN
    assert set(p.HELD_OUT_SUITES) < set(p.SUITES) and "randomized" not in p.HELD_OUT_SUITES
    assert "stress" not in p.CURVE_GROUPS and "certificate" not in p.CURVE_GROUPS
    with pytest.raises(ValueError, match="unknown suite 'nope'"):
        p.suite_seed_offset("nope")
    # the scenario module and blf-eval read the same objects, not copies
    import agents.evaluate as ev
    from blf_gym.envs import scenarios as sc

    assert sc.STRESS_SEED_OFFSET is p.STRESS_SEED_OFFSET and ev.EVAL_SEED_OFFSET is p.EVAL_SEED_OFFSET
    assert ev.suite_seed_offset is p.suite_seed_offset
