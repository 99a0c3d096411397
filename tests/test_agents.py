"""agents: blf-train (every algorithm x mode, resume), the SB3 VecEnv adapter, and blf-eval."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("stable_baselines3")

from agents.evaluate import load_agent, main as eval_main  # noqa: E402
from agents.train import load_config, main as train_main  # noqa: E402
from agents.vec_env import BLFVecEnv  # noqa: E402

TINY = """
n_envs: 2
normalize: {normalize}
env:
  control_period: 0.01
  residual_scale: 2.0
  duration: 0.2
hyperparams: {hyper}
policy_kwargs:
  net_arch: [16, 16]
eval_freq: 100
checkpoint_freq: 100
"""
HYPER = {
    "ppo": "{n_steps: 32, batch_size: 32, n_epochs: 1}",
    "sac": "{learning_starts: 0, batch_size: 32, buffer_size: 2000}",
    "td3": "{learning_starts: 0, batch_size: 32, buffer_size: 2000}",
    "tqc": "{learning_starts: 0, batch_size: 32, buffer_size: 2000}",
}


def _tiny(tmp_path: Path, algo: str, normalize: bool = True) -> Path:
    p = tmp_path / f"{algo}.yaml"
    p.write_text(TINY.format(normalize=str(normalize).lower(), hyper=HYPER[algo]))
    return p


@pytest.mark.parametrize("mode", ["plain", "residual"])
@pytest.mark.parametrize("algo", ["ppo", "sac", "td3", "tqc"])
def test_tiny_training_through_the_cli(tmp_path, algo, mode):
    if algo == "tqc":
        pytest.importorskip("sb3_contrib")
    out = tmp_path / "run"
    rc = train_main(["--algo", algo, "--mode", mode, "--timesteps", "128", "--config",
                     str(_tiny(tmp_path, algo)), "--out", str(out), "--no-progress"])
    assert rc == 0
    meta = json.loads((out / "metadata.json").read_text())
    assert meta["algo"] == algo and meta["mode"] == mode and meta["timesteps"] >= 128
    assert meta["seed"] == 0 and "torch" in meta["versions"] and meta["wall_s"] > 0
    assert (meta["env_kwargs"].get("controller") == "proposed") == (mode == "residual")
    assert (out / "model.zip").is_file() and (out / "vecnormalize.pkl").is_file()
    assert any((out / "tb").rglob("events.out.tfevents*"))
    assert any((out / "checkpoints").glob("step_*/model.zip"))


@pytest.mark.parametrize("algo", ["ppo", "td3"])
def test_action_noise_goes_to_any_algorithm_that_takes_it_and_is_refused_by_others(tmp_path, algo, capsys):
    # no list of algorithm names: the constructor's own signature decides (SB3's off-policy
    # algorithms take action_noise, PPO does not)
    cfg = tmp_path / "noisy.yaml"
    cfg.write_text(_tiny(tmp_path, algo).read_text() + "action_noise_std: 0.3\n")
    out = tmp_path / "run"
    args = ["--algo", algo, "--timesteps", "64", "--config", str(cfg), "--out", str(out), "--no-progress"]
    if algo == "ppo":
        assert train_main(args) == 2
        assert ("noisy.yaml: action_noise_std needs an algorithm that takes SB3's action_noise (an off-policy "
                "one); ppo does not") in capsys.readouterr().err
        return
    assert train_main(args) == 0
    from stable_baselines3 import TD3

    model = TD3.load(out / "model.zip", device="cpu")
    noise = model.action_noise  # SB3 wraps it per env (VectorizedActionNoise) when n_envs > 1
    np.testing.assert_allclose(getattr(noise, "base_noise", noise)._sigma, 0.3 * np.ones(3))


def test_resume_continues_the_step_count_with_the_replay_buffer(tmp_path):
    out = tmp_path / "run"
    cfg = str(_tiny(tmp_path, "sac"))
    assert train_main(["--algo", "sac", "--timesteps", "200", "--config", cfg, "--out", str(out),
                       "--no-progress"]) == 0
    # as if the run had been interrupted after an evaluation past its last checkpoint
    cpath = out / "eval" / "curve.json"
    c = json.loads(cpath.read_text())
    c["points"].append(dict(c["points"][-1], timesteps=250))
    cpath.write_text(json.dumps(c))
    # the latest checkpoint is at 200 steps; resume to 400
    assert train_main(["--algo", "sac", "--timesteps", "400", "--config", cfg, "--out", str(out),
                       "--resume", "--no-progress"]) == 0
    meta = json.loads((out / "metadata.json").read_text())
    assert meta["timesteps"] == 400 and meta["completed"]
    steps = sorted(int(f.name.split("_")[1]) for f in (out / "checkpoints").glob("step_*"))
    assert steps[-1] == 400 and 300 in steps  # saved after the resume point, not from zero
    # the learning curve continues from the checkpoint (the stretch past it is dropped): one point
    # per step count, in order
    curve = [p["timesteps"] for p in json.loads(cpath.read_text())["points"]]
    assert curve == sorted(set(curve)) and curve[0] == 0 and curve[-1] == 400 and 250 not in curve
    model, meta, norm = load_agent(out / "model.zip")
    model.load_replay_buffer(out / "checkpoints" / "step_400" / "replay_buffer.pkl")
    # a row per vector step of the 2 envs: 400 steps = 200 rows if the resumed run kept the first
    # 100 rows, 100 if it had started from an empty buffer. SB3 stores a step's transition after
    # the checkpoint callback has run, so each checkpoint is one row short (198).
    assert model.replay_buffer.size() == 198


def test_save_load_round_trip_gives_identical_deterministic_actions(tmp_path):
    out = tmp_path / "run"
    assert train_main(["--algo", "sac", "--timesteps", "64", "--config", str(_tiny(tmp_path, "sac")),
                       "--out", str(out), "--no-progress"]) == 0
    model, meta, norm = load_agent(out / "model.zip")
    model2, _, _ = load_agent(out / "model.zip")
    obs = np.random.default_rng(0).normal(size=(5, 31)).astype(np.float32)
    a1, _ = model.predict(obs, deterministic=True)
    a2, _ = model2.predict(obs, deterministic=True)
    np.testing.assert_array_equal(a1, a2)


def test_bad_training_input_is_named(tmp_path, capsys):
    assert train_main(["--algo", "sac", "--mode", "residual", "--controller", "pid", "--timesteps", "10",
                       "--out", str(tmp_path / "x")]) == 2
    assert "pid" in capsys.readouterr().err
    bad = tmp_path / "bad.yaml"
    bad.write_text("n_envs: 1\nlearning_rat: 0.1\n")
    with pytest.raises(ValueError, match="learning_rat"):
        load_config(bad)
    bad.write_text("env:\n  controll_period: 0.01\n")
    with pytest.raises(ValueError, match="controll_period"):
        load_config(bad)
    for key, value in (("curve_suite_seeds", 0), ("eval_freq", -5), ("n_envs", 1.5)):
        bad.write_text(f"{key}: {value}\n")
        with pytest.raises(ValueError, match=f"{key} must be an integer >= 1"):
            load_config(bad)
    assert train_main(["--algo", "sac", "--timesteps", "10", "--resume", "--out", str(tmp_path / "none")]) == 2


@pytest.mark.parametrize("text, message", [
    ("normalize: 'yes'\n", "normalize must be true or false, got 'yes'"),
    ("policy: 3\n", "policy must be a string, got 3"),
    ("hyperparams: [1, 2]\n", "hyperparams must be a mapping with string keys, got [1, 2]"),
    ("action_noise_std: -0.1\n", "action_noise_std must be a finite number >= 0, got -0.1"),
    ("checkpoint_freq: true\n", "checkpoint_freq must be an integer >= 1, got True"),
    ("env:\n  num_envs: 4\n", "unknown env key(s) ['num_envs']"),
    ("- 1\n", "a config is a mapping of"),
])
def test_a_config_s_wrong_type_is_refused_naming_the_file_and_the_key(tmp_path, text, message):
    bad = tmp_path / "bad.yaml"
    bad.write_text(text)
    with pytest.raises(ValueError) as err:
        load_config(bad)
    assert str(err.value).startswith(f"{bad}: ") and message in str(err.value)


def test_a_config_s_env_keys_are_the_env_s_own_arguments():
    import inspect

    from agents.config import RUN_SET_ENV_KEYS, TrainConfig, env_keys
    from agents.config import CONFIG_DIR
    from blf_gym.envs.envcore import EnvCore

    params = set(inspect.signature(EnvCore.__init__).parameters) - {"self"}
    assert set(env_keys()) == params - set(RUN_SET_ENV_KEYS) and set(RUN_SET_ENV_KEYS) <= params
    assert {"control_period", "residual_filter", "reward_weights", "dt"} <= set(env_keys())
    # every shipped config (the budget runs' too) passes, and its defaults are TrainConfig's
    for path in sorted([*CONFIG_DIR.glob("*.yaml"), *(CONFIG_DIR / "budget").glob("*.yaml")]):
        load_config(path)
    assert TrainConfig().n_envs == 1 and TrainConfig().eval_freq == 20_000


def test_an_algorithm_registered_without_configs_trains_by_name_on_the_typed_defaults(tmp_path, capsys,
                                                                                       monkeypatch):
    # a package that registers an algorithm in blf_gym.algorithms ships no config here: blf-train
    # and a sweep take TrainConfig's defaults (stood in for by SB3's A2C, which ships no config)
    import agents.loading as loading
    from agents.config import TrainConfig, shipped_config
    from agents.sweep import load_sweep
    from stable_baselines3 import A2C

    registered, load = loading.available_algorithms(), loading.algorithm_class
    monkeypatch.setattr(loading, "available_algorithms", lambda: sorted([*registered, "a2c"]))
    monkeypatch.setattr(loading, "algorithm_class", lambda name: A2C if name == "a2c" else load(name))
    assert shipped_config("a2c", "residual") is None and shipped_config("ppo", "residual") is not None
    assert load_sweep({"algo": "a2c", "timesteps": 64}, tmp_path)["base"] == {}
    out = tmp_path / "run"
    assert train_main(["--algo", "a2c", "--timesteps", "16", "--scenario", "paper-0.5hz", "--out", str(out),
                       "--no-progress"]) == 0
    assert "no config ships for a2c in residual mode; training with TrainConfig's defaults" in capsys.readouterr().err
    meta = json.loads((out / "metadata.json").read_text())
    assert meta["algo"] == "a2c" and meta["config"] == {"normalize": False} and meta["config_file"] == ""
    assert meta["timesteps"] >= 16 and TrainConfig().n_envs == 1
    assert A2C.load(out / "model.zip", device="cpu").n_envs == TrainConfig().n_envs


def test_blf_train_and_a_sweep_check_a_run_the_same_way(tmp_path, capsys):
    from agents.sweep import load_sweep

    assert train_main(["--mode", "plain", "--controller", "bc", "--timesteps", "10", "--out",
                       str(tmp_path / "x")]) == 2
    said = capsys.readouterr().err
    with pytest.raises(ValueError) as err:
        load_sweep({"mode": "plain", "controller": "bc"}, tmp_path)
    reason = "controller applies to mode: residual only (plain mode has no inner law)"
    assert reason in said and str(err.value) == f"sweep: {reason}"


def test_vecenv_adapter_hands_back_terminal_observation():
    venv = BLFVecEnv(3, seed=0, controller="proposed", duration=0.03)
    obs = venv.reset()
    assert obs.shape == (3, 31)
    for k in range(3):
        obs, rew, dones, infos = venv.step(np.zeros((3, 3), dtype=np.float32))
    assert dones.all()
    for info in infos:
        assert info["TimeLimit.truncated"] is True
        assert info["terminal_observation"].shape == (31,)
        assert info["time"] == pytest.approx(0.03)  # the ended episode's info, not the new one's
    assert not np.array_equal(obs[0], infos[0]["terminal_observation"])  # obs is the new episode


def test_vecenv_infos_read_on_demand_equal_the_whole_rows():
    """The adapter's per-arm infos (ArmInfo, read on demand) hold what a plain dict row built at
    the step holds, key for key, even when read after later steps; written keys are kept, and
    copy() and dict() give plain dicts. The rows are built here from the batched info with a
    comprehension of our own, at the step, as the adapter used to."""
    from gymnasium.vector import AutoresetMode

    from blf_gym.envs.vector import PlanarBLFVectorEnv

    def plain(v, i):
        if isinstance(v, dict):
            return {k: plain(x, i) for k, x in v.items() if not k.startswith("_") and k not in ("final_obs", "final_info")}
        x = v[i]
        return x.item() if isinstance(x, np.generic) else x

    kw = dict(controller="proposed", duration=0.05, scenario="randomized", privileged=True)
    venv = BLFVecEnv(3, seed=4, **kw)
    ref = PlanarBLFVectorEnv(num_envs=3, autoreset_mode=AutoresetMode.SAME_STEP, **kw)
    venv.reset()
    ref.reset(seed=4)
    rng = np.random.default_rng(0)
    kept = []
    for _ in range(12):  # two episode ends of every arm
        a = rng.uniform(-1, 1, (3, 3)).astype(np.float32)
        _, _, dones, infos = venv.step(a)
        _, _, term, trunc, info = ref.step(a)
        want = [plain(info["final_info"], i) if dones[i] else plain(info, i) for i in range(3)]
        kept.append((infos, want, dones.copy()))
    ends = 0
    for infos, want, dones in kept:  # read after every later step
        for i in range(3):
            got = dict(infos[i])
            ends += bool(dones[i])
            if dones[i]:
                assert got.pop("TimeLimit.truncated") is True and got.pop("terminal_observation").shape == (37,)
            assert got.keys() == want[i].keys()
            for k in want[i]:
                np.testing.assert_equal(got[k], want[i][k])
    assert ends == 6
    info = kept[-1][0][0]
    info["episode"] = {"r": 1.0}
    assert info["episode"] == {"r": 1.0} and "episode" in info and isinstance(info.copy(), dict)
    assert info.copy()["episode"] == {"r": 1.0} and info.get("nonexistent") is None and "final_info" not in info


def test_eval_cli_end_to_end_with_an_agent(tmp_path, capsys):
    run = tmp_path / "run"
    assert train_main(["--algo", "td3", "--mode", "residual", "--timesteps", "64", "--config",
                       str(_tiny(tmp_path, "td3")), "--out", str(run), "--no-progress"]) == 0
    out = tmp_path / "eval"
    rc = eval_main(["--controllers", "proposed", "lesobc", "--agents", str(run / "model.zip"),
                    "--duration", "0.5", "--suite", "randomized", "--suite-seeds", "2", "--out", str(out),
                    "--no-progress"])
    assert rc == 0
    data = json.loads((out / "results.json").read_text())
    assert data["schema_version"] == 2
    assert data["provenance"]["versions"]["numpy"] and "command" in data["provenance"]
    recs = data["records"]
    # 3 policies x (2 presets + the suite)
    assert len(recs) == 9
    kinds = {r["policy"]: r["kind"] for r in recs}
    assert kinds["proposed"] == "baseline" and kinds["run"] == "residual"
    suite = [r for r in recs if r["scenario"] == "randomized"]
    assert all(r["episodes"] == 2 for r in suite)
    assert all(r["suite"] == "randomized" and r["suite_seeds"] == [10000, 10001] for r in suite)
    for r in recs:
        # the law against itself scores exactly 1; everyone has a score per episode
        assert len(r["per_episode_score"]) == r["episodes"] and r["score_vs_law"] > 0
        if r["policy"] == "proposed":
            assert r["per_episode_score"] == [1.0] * r["episodes"] and r["certificate_broken"] == 0.0
    agent = [r for r in recs if r["policy"] == "run"]
    assert all(r["train_seed"] == 0 and r["env_kwargs"]["controller"] == "proposed" for r in agent)
    with open(out / "results.csv") as f:
        rows = list(csv.DictReader(f))
    assert len(rows) == 9 and "rmse_deg_3" in rows[0]
    for png in out.glob("*.png"):
        assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert len(list(out.glob("*.png"))) == 6  # error and torque per scenario
    printed = capsys.readouterr().out
    assert "proposed" in printed and "run" in printed


def test_eval_bad_input_is_named(tmp_path, capsys):
    assert eval_main(["--agents", str(tmp_path / "missing.zip"), "--no-progress"]) == 2
    assert "missing.zip" in capsys.readouterr().err
    junk = tmp_path / "junk" / "model.zip"
    junk.parent.mkdir()
    junk.write_bytes(b"not a zip")
    (junk.parent / "metadata.json").write_text(json.dumps({"algo": "sac", "mode": "plain", "env_kwargs": {}}))
    assert eval_main(["--agents", str(junk), "--no-progress"]) == 2
    assert "cannot be loaded" in capsys.readouterr().err
    assert eval_main(["--controllers", "pid", "--agents", "--no-progress"]) == 2
    assert "pid" in capsys.readouterr().err
    assert eval_main(["--scenarios", "moon", "--agents", "--no-progress"]) == 2
    assert "moon" in capsys.readouterr().err
    assert eval_main(["--scenario-kwargs", '{"colour": 1}', "--agents", "--no-progress"]) == 2
    assert "colour" in capsys.readouterr().err


def test_an_interrupted_run_resumes_from_its_last_checkpoint(tmp_path):
    import signal
    import subprocess
    import sys
    import time

    out = tmp_path / "run"
    cfg = str(_tiny(tmp_path, "sac"))
    # the run's output goes to a file, not a pipe nobody reads while it trains (a full pipe would
    # block the run before its first checkpoint)
    log = tmp_path / "stderr.txt"
    with open(log, "w") as errf:
        # SIGINT at its default in the child: a shell running the suite in the background ignores it,
        # and a Python started with SIGINT ignored never raises KeyboardInterrupt (a user's Ctrl-C does)
        proc = subprocess.Popen([sys.executable, "-m", "agents.train", "--algo", "sac", "--timesteps", "1000000",
                                 "--config", cfg, "--out", str(out), "--no-progress"],
                                stdout=subprocess.DEVNULL, stderr=errf, text=True,
                                preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
        try:
            deadline = time.time() + 300  # generous: a cold cache compiles the kernels first
            while time.time() < deadline and proc.poll() is None and not list((out / "checkpoints").glob("step_*")):
                time.sleep(0.5)
            assert list((out / "checkpoints").glob("step_*")), f"no checkpoint within 300 s:\n{log.read_text()[-2000:]}"
            time.sleep(1.0)
            proc.send_signal(signal.SIGINT)
            proc.wait(timeout=300)  # generous: CI machines can be heavily loaded
        finally:
            if proc.poll() is None:
                proc.kill()
    err = log.read_text()
    assert "interrupted" in err
    meta = json.loads((out / "metadata.json").read_text())
    assert not meta["completed"]  # the model and metadata of an interrupted run are still written
    assert meta["status"] == "interrupted" and proc.returncode == 130
    ckpts = sorted(int(f.name.split("_")[1]) for f in (out / "checkpoints").glob("step_*"))
    assert ckpts[-1] == meta["timesteps"]  # the run ended on a checkpoint of where it stopped
    target = ckpts[-1] + 200
    assert train_main(["--algo", "sac", "--timesteps", str(target), "--config", cfg, "--out", str(out),
                       "--resume", "--no-progress"]) == 0
    meta = json.loads((out / "metadata.json").read_text())
    assert meta["timesteps"] == target and meta["completed"]


def test_cli_guards_against_silent_mistakes(tmp_path, capsys):
    run = tmp_path / "run"
    cfg = str(_tiny(tmp_path, "sac"))
    assert train_main(["--algo", "sac", "--timesteps", "32", "--config", cfg, "--out", str(run),
                       "--no-progress"]) == 0
    # a second run into the same folder would silently overwrite it
    assert train_main(["--algo", "sac", "--timesteps", "32", "--config", cfg, "--out", str(run),
                       "--no-progress"]) == 2
    assert "--resume" in capsys.readouterr().err
    # --controller means nothing in plain mode
    assert train_main(["--algo", "sac", "--mode", "plain", "--controller", "lesobc", "--timesteps", "32",
                       "--config", cfg, "--out", str(tmp_path / "p"), "--no-progress"]) == 2
    assert "residual only" in capsys.readouterr().err
    # nothing to evaluate, and malformed JSON, are named
    assert eval_main(["--controllers", "--agents", "--no-progress"]) == 2
    assert "nothing to evaluate" in capsys.readouterr().err
    assert eval_main(["--scenario-kwargs", "{payload: 5}", "--agents", "--no-progress"]) == 2
    assert "--scenario-kwargs" in capsys.readouterr().err


def test_learning_curve_points_match_an_evaluation_of_the_saved_model(tmp_path):
    """eval/curve.json scores the live policy with its live normalization; its last point must equal
    blf-eval's metrics of the saved model.zip + vecnormalize.pkl on the same scenarios."""
    from agents.evaluate import build_scenarios, evaluate_agent
    from blf_gym.results.metrics import summarize

    out = tmp_path / "run"
    cfg = tmp_path / "ppo.yaml"
    cfg.write_text(TINY.format(normalize="true", hyper=HYPER["ppo"]) + "curve_suite_seeds: 2\n")
    assert train_main(["--algo", "ppo", "--timesteps", "256", "--config", str(cfg), "--out", str(out),
                       "--scenario", "randomized", "--no-progress"]) == 0
    curve = json.loads((out / "eval" / "curve.json").read_text())
    steps = [p["timesteps"] for p in curve["points"]]
    assert steps[0] == 0 and steps == sorted(steps) and steps[-1] == 256  # eval_freq 100 on 64-step rollouts
    model, meta, norm = load_agent(out / "model.zip")
    for label, scs in build_scenarios(["paper-0.1hz", "paper-0.5hz"], 2, {}, 0.2):
        rec = summarize(evaluate_agent(model, meta, norm, scs), "x", "residual", label, scs[0].sim.dt)
        np.testing.assert_allclose(curve["points"][-1][label]["rmse_deg"], rec["rmse_deg"], rtol=1e-12)
        assert curve["points"][-1][label]["violations"] == rec["violations"]
    # the plot is written and is a PNG
    from agents.curves import main as curves_main

    assert curves_main([str(out), "--out", str(tmp_path / "c.png")]) == 0
    assert (tmp_path / "c.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    # on logarithmic axes the untrained point (step 0) is drawn at half the first evaluated step
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from agents.curves import plot_curves

    captured = {}
    real_close = plt.close
    try:
        plt.close = lambda fig=None: captured.setdefault("fig", fig)
        plot_curves([out], tmp_path / "log.png", log_steps=True, log_rmse=True)
    finally:
        plt.close = real_close
    ax = captured["fig"].axes[0]
    assert ax.get_xscale() == "log" and ax.get_yscale() == "log"
    xs = ax.lines[0].get_xdata()
    assert xs[0] == 0.5 * xs[1] == 0.5 * steps[1]
    real_close(captured["fig"])
    assert curves_main([str(out), "--log-steps", "--out", str(tmp_path / "l.png")]) == 0
    kept = tmp_path / "kept"  # a run as docs/ keeps it: curve.json at the top
    kept.mkdir()
    (kept / "curve.json").write_text((out / "eval" / "curve.json").read_text())
    assert curves_main([str(kept), "--out", str(tmp_path / "k.png")]) == 0
    assert curves_main([str(tmp_path / "nothing"), "--out", str(tmp_path / "d.png")]) == 2
    # runs scored on different scenarios cannot share one law line
    other = tmp_path / "other" / "eval"
    other.mkdir(parents=True)
    (other / "curve.json").write_text(json.dumps(dict(curve, suite_seeds=3)))
    assert curves_main([str(out), str(other.parent), "--out", str(tmp_path / "e.png")]) == 2
    assert not (tmp_path / "e.png").exists()


def test_report_pools_seeds_and_counts_wins_against_the_law(tmp_path, capsys):
    from agents.report import main as report_main, pool_seeds
    from blf_gym.results.metrics import write_results

    def rec(policy, kind, rmse, viol=(0, 0, 0), fail=0.0):
        return {"policy": policy, "kind": kind, "scenario": "paper-0.1hz", "episodes": 1, "dt": 1e-4,
                "rmse_deg": list(rmse), "violations": list(viol), "violation_fraction": [0.0] * 3,
                "max_excursion_deg": [0.0] * 3, "min_margin_deg": [1.0] * 3, "first_violation_s": None,
                "failure_rate": fail, "rmse_cvar_deg": list(rmse), "torque_rms": [1.0] * 3,
                "torque_peak": [1.0] * 3, "saturated_fraction": [0.0] * 3, "diverged": 0, "wall_s": 0.1,
                "score_vs_law": None, "certificate_broken": None, "law_failure_rate": None,
                "per_episode_rmse_deg": [list(rmse)], "per_episode_score": None,
                "per_episode_violations": [int(sum(viol))], "per_episode_failed": [fail > 0]}

    records = [rec("proposed", "baseline", (1.0, 2.0, 3.0)),
               rec("res_s0", "residual", (0.9, 1.9, 2.9)),            # beats the law in every joint
               rec("res_s1", "residual", (0.8, 2.1, 2.5), (0, 4, 0), 1.0),  # loses on joint 2
               rec("res_s2", "residual", (1.0, 1.0, 1.0))]            # ties joint 1: not a win
    rows = {r["policy"]: r for r in pool_seeds(records)}
    r = rows["res"]
    assert r["seeds"] == 3 and r["seeds_beating_law"] == 1
    np.testing.assert_allclose(r["rmse_mean"], [0.9, 5.0 / 3.0, 6.4 / 3.0])
    np.testing.assert_allclose(r["rmse_min"], [0.8, 1.0, 1.0])
    np.testing.assert_allclose(r["rmse_max"], [1.0, 2.1, 2.9])
    np.testing.assert_allclose(r["ratio_mean"], [0.9, 5.0 / 6.0, 6.4 / 9.0])
    assert r["violations"] == 4 and r["failure_rate"] == 1.0
    assert rows["proposed"]["seeds"] == 1
    write_results(records, tmp_path)
    assert report_main([str(tmp_path / "results.json"), "--out", str(tmp_path / "t.md")]) == 0
    assert "| res | residual | paper-0.1hz | 3 | 0.9000 (0.8000-1.0000)" in (tmp_path / "t.md").read_text()
    assert report_main([str(tmp_path / "none.json")]) == 2


def test_report_statistics_are_rliable_s_iqm_and_probability_of_improvement(tmp_path):
    from scipy.stats import trim_mean

    from agents.report import main as report_main, seed_statistics
    from blf_gym.results.metrics import write_results

    rng = np.random.default_rng(0)
    scores = rng.uniform(0.6, 1.6, size=(5, 8))  # 5 seeds x 8 episodes
    base = {"kind": "residual", "scenario": "stress", "episodes": 8, "dt": 1e-4, "rmse_deg": [1.0] * 3,
            "violations": [0] * 3, "violation_fraction": [0.0] * 3, "max_excursion_deg": [0.0] * 3,
            "min_margin_deg": [1.0] * 3, "first_violation_s": None, "failure_rate": 0.0, "rmse_cvar_deg": 1.0,
            "torque_rms": [1.0] * 3, "torque_peak": [1.0] * 3, "saturated_fraction": [0.0] * 3,
            "diverged": False, "wall_s": 0.0, "score_vs_law": 1.0, "certificate_broken": 0.1,
            "law_failure_rate": 0.0, "per_episode_rmse_deg": [[1.0] * 3] * 8, "per_episode_violations": [0] * 8,
            "per_episode_failed": [False] * 8}
    records = [dict(base, policy=f"agent_s{s}", per_episode_score=scores[s].tolist(), train_seed=s) for s in range(5)]
    (stat,) = seed_statistics(records, reps=2000)
    # independent references: the 25 % trimmed mean of all scores, and P(score > 1) per episode
    assert stat["iqm"] == pytest.approx(trim_mean(scores.ravel(), 0.25))
    assert stat["prob_improvement"] == pytest.approx(np.mean((scores > 1).mean(axis=0)))
    lo, hi = stat["ci95"]
    assert lo < stat["iqm"] < hi and hi - lo < 0.5
    assert stat["seeds"] == [0, 1, 2, 3, 4] and stat["episodes"] == 8
    write_results(records, tmp_path)
    assert report_main([str(tmp_path / "results.json")]) == 0
    data = json.loads((tmp_path / "report.json").read_text())
    assert data["statistics"][0]["iqm"] == pytest.approx(stat["iqm"])
    assert {"iqm", "ci95", "prob_improvement"} <= set(data["statistics"][0])


def test_report_pools_the_seeds_of_agents_blf_eval_ran_through_a_filter():
    """blf-eval --residual-filter names each agent <name>_s<seed>+<filter>: its seeds pool into
    <name>+<filter>, apart from the same agents without it (they once stayed five groups of one)."""
    from agents.report import pool_seeds, seed_group

    assert seed_group("cert_s3+barrier:handback=0.0033") == ("cert+barrier:handback=0.0033", 3)
    assert seed_group("cert_s12") == ("cert", 12) and seed_group("proposed") == ("proposed", None)
    base = {"kind": "residual", "scenario": "randomized", "rmse_deg": [1.0] * 3, "violations": [0] * 3,
            "failure_rate": 0.0}
    recs = [dict(base, policy=f"cert_s{s}{f}") for s in range(3) for f in ("", "+barrier:handback=0.0033")]
    rows = {r["policy"]: r["seeds"] for r in pool_seeds(recs)}
    assert rows == {"cert": 3, "cert+barrier:handback=0.0033": 3}


def test_linear_schedules_in_configs(tmp_path):
    from agents.train import _schedule

    f = _schedule("lin_3e-4", "x")
    assert f(1.0) == pytest.approx(3e-4) and f(0.5) == pytest.approx(1.5e-4) and f(0.0) == 0.0
    with pytest.raises(ValueError, match="lin_<number>"):
        _schedule("cosine_1e-3", "x")
    # YAML 1.1 reads 3e-4 (no dot) as the string "3e-4": it is the constant 3e-4, not an error
    import yaml
    assert yaml.safe_load("lr: 3e-4")["lr"] == "3e-4" and _schedule("3e-4", "x") == 3e-4
    cfg = tmp_path / "ppo.yaml"
    cfg.write_text(TINY.format(normalize="true", hyper="{n_steps: 32, batch_size: 32, n_epochs: 1, "
                                                     "learning_rate: lin_0.001}"))
    out = tmp_path / "run"
    assert train_main(["--algo", "ppo", "--timesteps", "128", "--config", str(cfg), "--out", str(out),
                       "--no-progress"]) == 0
    model, _, _ = load_agent(out / "model.zip")
    # SB3 keeps the schedule; at the end of training the rate has decayed to ~0
    assert model.lr_schedule(1.0) == pytest.approx(1e-3) and model.lr_schedule(0.0) == pytest.approx(0.0)


def test_report_windows_finds_where_an_agent_loses(tmp_path):
    from agents.report import main as report_main, windows

    t = np.arange(0, 3.0, 1e-3)
    e_law = np.full((t.size, 3), np.radians(0.01))
    e_ag = e_law.copy()
    e_ag[(t >= 1.0) & (t < 1.5), 0] = np.radians(0.03)  # joint 1 worse in one window only
    e_ag[:, 2] = np.radians(0.005)  # joint 3 better everywhere
    traj = tmp_path / "traj"
    traj.mkdir()
    for name, e in (("proposed", e_law), ("agent_s0", e_ag)):
        np.savez(traj / f"paper-0.1hz__{name}__0.npz", t=t, e1=e)
    text = windows(traj, "paper-0.1hz", "agent_s0")
    # joint 1: the window adds (9 - 1) * 500 / 3000 = 1.333 of the law's MSE
    assert "joint 1: agent MSE / law MSE = 2.333" in text
    assert "worse: 1.0-1.5 s (+1.333)" in text
    assert "joint 2: agent MSE / law MSE = 1.000" in text
    assert "joint 3: agent MSE / law MSE = 0.250" in text
    (tmp_path / "results.json").write_text("{}")
    assert report_main([str(tmp_path / "results.json"), "--windows", "paper-0.1hz", "nobody"]) == 2


def test_set_overrides_config_keys_from_the_command_line(tmp_path, capsys):
    """--set KEY=VALUE changes the config's keys (nested ones by a dot), is checked like the file
    (the key named), is recorded in the metadata, and cannot change a run on --resume."""
    out = tmp_path / "run"
    cfg = _tiny(tmp_path, "ppo", normalize=False)  # n_envs: 2, control_period 0.01
    text = cfg.read_text()
    base = ["--algo", "ppo", "--timesteps", "64", "--config", str(cfg), "--out", str(out), "--no-progress"]
    for bad, msg in ((["bogus=1"], "unknown config key 'bogus'"), (["n_envs=0"], "n_envs must be an integer >= 1, got 0"),
                     (["env.bogus=1"], "unknown env key(s) ['bogus']"), (["n_envs"], "expected KEY=VALUE")):
        assert train_main([*base, "--set", *bad]) == 2
        assert msg in capsys.readouterr().err
    assert not out.exists()
    sets = ["--set", "n_envs=1", "--set", "env.control_period=0.02", "--set", "note=from the command line"]
    assert train_main([*base, *sets]) == 0
    meta = json.loads((out / "metadata.json").read_text())
    assert meta["config"]["n_envs"] == 1 and meta["config"]["note"] == "from the command line"
    assert meta["config"]["env"]["control_period"] == 0.02 and meta["config"]["env"]["duration"] == 0.2
    assert meta["env_kwargs"]["control_period"] == 0.02
    assert cfg.read_text() == text  # the file itself is untouched
    capsys.readouterr()
    assert train_main([*base, "--resume", "--timesteps", "128", "--set", "n_envs=3"]) == 2
    assert "--resume keeps the run's own config" in capsys.readouterr().err
    assert train_main([*base, "--resume", "--timesteps", "128", *sets]) == 0  # the same values: no change
    assert json.loads((out / "metadata.json").read_text())["timesteps"] >= 128


def test_train_config_of_a_mapping_is_typed_and_checked():
    """TrainConfig.of: the typed config blf-train and a sweep's trials use; left-out and null keys
    take the defaults, a bad key or type or an inconsistent pair is refused by name."""
    from agents.config import TrainConfig

    tc = TrainConfig.of({"n_envs": 4, "eval_freq": None, "env": {"duration": 2.0}}, "f.yaml")
    assert tc.n_envs == 4 and tc.eval_freq == TrainConfig().eval_freq and tc.env == {"duration": 2.0}
    for cfg, msg in (({"normalize_reward": True}, "f.yaml: normalize_reward needs normalize: true"),
                     ({"n_envs": 1.5}, "f.yaml: n_envs must be an integer >= 1"),
                     ({"normalise": True}, r"f.yaml: unknown config key\(s\) \['normalise'\]")):
        with pytest.raises(ValueError, match=msg):
            TrainConfig.of(cfg, "f.yaml")


def test_sbx_algorithms_train_resume_and_are_judged_by_name(tmp_path):
    """SB3's JAX port (the jax extra) registered as sbx_ppo, sbx_sac and sbx_crossq: each trains
    through blf-train by name, sbx_ppo resumes from its checkpoint, and blf-eval's loader acts with
    the model's own predict (a JAX policy holds no torch parameters, so the torch fast path must not
    take it)."""
    pytest.importorskip("sbx")
    import dataclasses

    from agents.evaluate import agent_episodes
    from agents.loading import load_agent
    from blf_gym.model.params import preset

    runs = {}
    for algo, mode, hyper in (("sbx_ppo", "residual", "ppo"), ("sbx_sac", "plain", "sac"),
                              ("sbx_crossq", "residual", "sac")):
        cfg = tmp_path / f"{algo}.yaml"
        cfg.write_text(TINY.format(normalize="true", hyper=HYPER[hyper]))
        out = runs[algo] = tmp_path / algo
        assert train_main(["--algo", algo, "--mode", mode, "--timesteps", "64", "--config", str(cfg),
                           "--out", str(out), "--no-progress"]) == 0
        meta = json.loads((out / "metadata.json").read_text())
        assert meta["algo"] == algo and meta["mode"] == mode and meta["timesteps"] >= 64
    cfg = tmp_path / "sbx_ppo.yaml"
    assert train_main(["--algo", "sbx_ppo", "--mode", "residual", "--timesteps", "192", "--config", str(cfg),
                       "--out", str(runs["sbx_ppo"]), "--resume", "--no-progress"]) == 0
    assert json.loads((runs["sbx_ppo"] / "metadata.json").read_text())["timesteps"] >= 192
    model, meta, norm = load_agent(runs["sbx_ppo"] / "model.zip")
    assert type(model).__module__.startswith("sbx.")
    sc = preset("paper-0.1hz")
    sc = dataclasses.replace(sc, sim=dataclasses.replace(sc.sim, duration=0.05))
    trajs = list(agent_episodes(model, meta, norm, [sc], threads=1))
    assert len(trajs) == 1 and trajs[0].q.shape[0] == 50 and np.isfinite(trajs[0].q).all()


def test_the_multi_job_recipe_starts_resumes_and_then_leaves_a_run_alone(tmp_path):
    """docs/budget/run.sh, the README's recipe for a run split over several jobs: the same command
    starts the run, then extends it from its newest checkpoint (a second segment), then sees it
    done and trains nothing. Between the two jobs the machine is lost: docs/budget/keep.sh kept the
    run's newest checkpoint, and restores it into an empty folder, from which the run goes on."""
    import os
    import shutil
    import subprocess
    import sys

    script = Path(__file__).resolve().parents[1] / "docs" / "budget" / "run.sh"
    keep = script.with_name("keep.sh")
    out, cfg = tmp_path / "run", str(_tiny(tmp_path, "ppo"))
    env = {**os.environ, "PATH": f"{Path(sys.executable).parent}{os.pathsep}{os.environ.get('PATH', '')}"}

    def job(steps: int) -> str:
        p = subprocess.run(["bash", str(script), str(out), str(steps), "--algo", "ppo", "--config", cfg],
                           capture_output=True, text=True, env=env, timeout=600)
        assert p.returncode == 0, p.stderr[-2000:]
        return p.stderr

    job(64)
    meta = json.loads((out / "metadata.json").read_text())
    assert meta["timesteps"] == 64 and len(meta["segments"]) == 1 and meta["completed"]
    kept = tmp_path / "kept"
    subprocess.run(["bash", str(keep), str(out), str(kept)], check=True, capture_output=True, timeout=60)
    assert [p.name for p in (kept / "checkpoints").iterdir()] == ["step_64"]
    shutil.rmtree(out)  # the job's machine is gone; only what was kept survives
    subprocess.run(["bash", str(keep), "--restore", str(kept), str(out)], check=True, capture_output=True, timeout=60)
    job(128)
    meta = json.loads((out / "metadata.json").read_text())
    assert meta["timesteps"] == 128 and meta["resumed"]
    assert [(s["start_timesteps"], s["end_timesteps"]) for s in meta["segments"]] == [(0, 64), (64, 128)]
    assert "this stage is done" in job(128)
    assert len(json.loads((out / "metadata.json").read_text())["segments"]) == 2
    # restoring the older kept checkpoint over a run that is further along changes nothing
    p = subprocess.run(["bash", str(keep), "--restore", str(kept), str(out)], capture_output=True, text=True, timeout=60)
    assert p.returncode == 0 and "nothing restored" in p.stdout
    assert json.loads((out / "metadata.json").read_text())["timesteps"] == 128
    # the finished run, kept, is an agent blf-eval loads as it is: its model beside the checkpoint
    subprocess.run(["bash", str(keep), str(out), str(kept)], check=True, capture_output=True, timeout=60)
    assert [p.name for p in (kept / "checkpoints").iterdir()] == ["step_128"]
    model, meta, _ = load_agent(kept)
    assert model.num_timesteps == 128 and meta["timesteps"] == 128


def test_an_off_policy_run_kept_without_its_replay_buffer_refills_it_before_updating(tmp_path):
    """keep.sh does not keep a replay buffer (too large to commit). The kept set is still complete,
    and the resumed run lets its policy act without gradient steps until the buffer again holds the
    run's learning_starts transitions (at least a batch), then updates at its configured rate."""
    import shutil
    import subprocess

    from stable_baselines3 import SAC

    keep = Path(__file__).resolve().parents[1] / "docs" / "budget" / "keep.sh"
    out, kept, cfg = tmp_path / "run", tmp_path / "kept", str(_tiny(tmp_path, "sac"))
    assert train_main(["--algo", "sac", "--timesteps", "200", "--config", cfg, "--out", str(out),
                       "--no-progress"]) == 0
    assert (out / "checkpoints" / "step_200" / "replay_buffer.pkl").is_file()
    subprocess.run(["bash", str(keep), str(out), str(kept)], check=True, capture_output=True, timeout=60)
    ck = kept / "checkpoints" / "step_200"
    assert not (ck / "replay_buffer.pkl").exists()
    assert "replay_buffer.pkl" not in json.loads((ck / "state.json").read_text())["files"]
    shutil.rmtree(out)
    subprocess.run(["bash", str(keep), "--restore", str(kept), str(out)], check=True, capture_output=True, timeout=60)
    # a job that ends in the middle of the refill: learning_starts is 0 in the tiny config, so the
    # refill is one batch (32) of transitions, to step 232
    assert train_main(["--resume", "--timesteps", "210", "--out", str(out), "--no-progress"]) == 0
    meta = json.loads((out / "metadata.json").read_text())
    assert meta["segments"][-1]["replay_buffer"] == {"resumed": False, "refilled_until": 232}
    mid = json.loads((out / "checkpoints" / "step_210" / "state.json").read_text())
    assert mid["refill_until"] == 232 and "replay_buffer.pkl" in mid["files"]
    assert SAC.load(out / "model.zip", device="cpu").gradient_steps == 1  # the run's setting, not the refill's 0
    # the next job finishes the refill from the part-filled buffer, then updates
    assert train_main(["--resume", "--timesteps", "400", "--out", str(out), "--no-progress"]) == 0
    meta = json.loads((out / "metadata.json").read_text())
    assert meta["segments"][-1]["replay_buffer"] == {"resumed": True, "refilled_until": 232}
    assert "refill_until" not in json.loads((out / "checkpoints" / "step_400" / "state.json").read_text())
    before = SAC.load(ck / "model.zip", device="cpu")
    after = SAC.load(out / "model.zip", device="cpu")
    # 2 envs, train_freq 1, one gradient step per vector step: steps 202..400 are 100 vector steps,
    # of which those at 232, 234, ..., 400 (85) update; all 100 would if the buffer had not been
    # refilled, 95 if the second job had not gone on with the refill, none if it never ended
    assert after._n_updates - before._n_updates == 85
    assert after.gradient_steps == 1


def test_init_from_starts_a_new_run_from_a_trained_agents_policy_and_statistics(tmp_path):
    """config key init_from: the new run's untrained model acts as the source agent does (same
    weights, log_std and observation statistics), whatever its own policy_kwargs' log_std_init; a
    source that does not fit the run is refused, naming init_from."""
    from agents.lagrangian import PPOLagrangian  # noqa: F401  (registered as ppo_lagrangian)

    src = tmp_path / "src"
    assert train_main(["--algo", "ppo", "--mode", "plain", "--timesteps", "64", "--config", str(_tiny(tmp_path, "ppo")),
                       "--out", str(src), "--no-progress"]) == 0
    model_src, _, norm_src = load_agent(src)
    out = tmp_path / "warm"
    # 0 steps after the start: the saved model is the warm-started one, untouched by an update
    cfg = _tiny(tmp_path, "ppo")
    assert train_main(["--algo", "ppo_lagrangian", "--mode", "plain", "--timesteps", "1", "--config", str(cfg),
                       "--set", f"init_from={src}", "--set", "policy_kwargs.log_std_init=-3.0",
                       "--set", "hyperparams.n_steps=1", "--set", "hyperparams.batch_size=2",
                       "--set", "hyperparams.learning_rate=0.0",
                       "--out", str(out), "--no-progress"]) == 0
    meta = json.loads((out / "metadata.json").read_text())
    assert meta["init_from"]["path"] == str(src) and meta["init_from"]["timesteps"] == 64
    model, _, norm = load_agent(out)
    # learning rate 0: the one update changes no weight, so the policies must be equal
    for k, v in model_src.policy.state_dict().items():
        np.testing.assert_array_equal(model.policy.state_dict()[k].numpy(), v.numpy(), err_msg=k)
    assert float(model.policy.log_std.detach()[0]) != -3.0
    # the statistics start as the source's, then count the run's own few observations (resets and
    # one step of 2 arms); fresh statistics would count only those few
    assert norm_src.obs_rms.count < norm.obs_rms.count < norm_src.obs_rms.count + 10
    # a plain agent cannot start a residual run, nor a policy of another shape this one
    from agents.train import train

    with pytest.raises(ValueError, match="init_from: .* is a plain agent; this run is residual"):
        train(algo="ppo_lagrangian", mode="residual", timesteps=1, config=str(cfg), overrides=[f"init_from={src}"],
              out=tmp_path / "bad", progress=False)
    with pytest.raises(ValueError, match="init_from: .*policy .* does not fit"):
        train(algo="ppo_lagrangian", mode="plain", timesteps=1, config=str(cfg), out=tmp_path / "bad2",
              overrides=[f"init_from={src}", "policy_kwargs.net_arch=[32, 32]"], progress=False)


def test_a_time_budget_ends_the_run_as_completed_and_a_larger_one_extends_it(tmp_path, capsys):
    """--time-budget: training stops, as completed, at the first step at which the wall time that
    produced the model reaches the budget, even short of --timesteps; a resume keeps the budget (and
    trains nothing once it is spent); a larger one extends the run, counting the earlier segment; a
    smaller one, or another --name, is refused."""
    out, cfg = tmp_path / "run", str(_tiny(tmp_path, "ppo"))
    base = ["--algo", "ppo", "--mode", "plain", "--config", cfg, "--out", str(out), "--no-progress"]
    assert train_main([*base, "--timesteps", "20000", "--time-budget", "1.5"]) == 0
    meta = json.loads((out / "metadata.json").read_text())
    # the tiny config trains a few hundred steps per second here: 20,000 steps take far longer than
    # 1.5 s, so the budget, not the step target, ended the run
    assert meta["completed"] and meta["time_budget_s"] == 1.5 and 0 < meta["timesteps"] < 20000
    assert meta["wall_s_to_model"] >= 1.5
    first = meta["timesteps"]
    assert train_main(["--resume", "--out", str(out), "--no-progress"]) == 0
    assert "spent its time budget" in capsys.readouterr().err
    assert len(json.loads((out / "metadata.json").read_text())["segments"]) == 1
    assert train_main(["--resume", "--out", str(out), "--no-progress", "--time-budget", "1"]) == 2
    assert "below the run's budget of 1.5 s" in capsys.readouterr().err
    assert train_main(["--resume", "--out", str(out), "--no-progress", "--name", "other"]) == 2
    err = capsys.readouterr().err
    assert "--name other differs from the run's 'run'" in err and "continues a run with its own settings" in err
    assert train_main(["--resume", "--out", str(out), "--no-progress", "--time-budget", "3"]) == 0
    meta = json.loads((out / "metadata.json").read_text())
    assert meta["completed"] and meta["time_budget_s"] == 3 and meta["timesteps"] > first
    # 3 s over both segments, not 3 s more: the second took the budget's rest (about 1.5 s)
    assert meta["wall_s_to_model"] >= 3 and meta["segments"][1]["wall_s"] < 3
    assert [s["start_timesteps"] for s in meta["segments"]] == [0, first]
    for bad in ("0", "-1", "nan", "inf"):
        assert train_main([*base, "--timesteps", "64", "--time-budget", bad]) == 2
        assert "--time-budget must be a number of seconds > 0" in capsys.readouterr().err


def test_a_run_whose_job_ended_after_its_budget_was_spent_trains_no_more(tmp_path, capsys):
    """A job that stopped after the budget ended training but before the run was recorded as
    finished (a kill during the final save; a kept run restored on another machine, without its
    model.zip): the resume trains no step, writes the final model and records the run completed."""
    out, cfg = tmp_path / "run", str(_tiny(tmp_path, "ppo"))
    assert train_main(["--algo", "ppo", "--mode", "plain", "--config", cfg, "--out", str(out), "--no-progress",
                       "--timesteps", "20000", "--time-budget", "1"]) == 0
    meta = json.loads((out / "metadata.json").read_text())
    steps = meta["timesteps"]
    meta.update(status="running", completed=False)
    meta["segments"][-1]["status"] = "running"
    (out / "metadata.json").write_text(json.dumps(meta))
    (out / "model.zip").unlink()
    capsys.readouterr()
    assert train_main(["--resume", "--out", str(out), "--no-progress"]) == 0
    assert "had spent its time budget" in capsys.readouterr().err
    meta = json.loads((out / "metadata.json").read_text())
    assert meta["completed"] and meta["timesteps"] == steps and (out / "model.zip").is_file()
    assert [s["status"] for s in meta["segments"]] == ["killed", "completed"]


def test_the_budget_plans_run_the_commands_docs_budget_md_states(tmp_path):
    """docs/budget/plan.sh's chains E and F (SAC's seeds, the warm-started runs' seeds) pass
    run.sh the options that docs/budget.md fixed before the runs: the page's seed-0 commands with
    the seed and name changed; a stub run.sh records the calls."""
    import shlex
    import shutil
    import subprocess

    root = Path(__file__).resolve().parents[1]
    shutil.copy(root / "docs" / "budget" / "plan.sh", tmp_path / "plan.sh")
    log = tmp_path / "calls"
    (tmp_path / "run.sh").write_text(f'#!/usr/bin/env bash\nprintf "%s\\0" "$@" >> {log}\nprintf "\\n" >> {log}\n')
    (tmp_path / "run.sh").chmod(0o755)

    def calls(*args: str) -> list[list[str]]:
        log.unlink(missing_ok=True)
        subprocess.run(["bash", str(tmp_path / "plan.sh"), *args], check=True, capture_output=True, timeout=60)
        return [c.rstrip("\0").split("\0") for c in log.read_text().split("\0\n") if c]

    page = (root / "docs" / "budget.md").read_text()

    def documented(name: str, seed: int) -> list[str]:
        line = next(x for x in page.splitlines() if x.startswith(f"docs/budget/run.sh RUNS_DIR/{name}_s0 "))
        words = shlex.split(line)[1:]
        words = [w.replace(f"{name}_s0", f"{name}_s{seed}") for w in words]
        i = words.index("--seed")
        words[i + 1] = str(seed)
        return [w.replace("RUNS_DIR", "R") for w in words]

    got = calls("F", "R", "2")
    assert got == [documented("ppo_lagrangian_warm", 2), documented("ppo_warm", 2)]
    assert calls("E", "R", "1") == [documented("sbx_sac", 1)]
    assert calls("E", "R") == [documented("sbx_sac", s) for s in (0, 1, 2)]


def test_a_fused_adam_step_reaches_the_optimizer_and_updates_as_the_default_does(tmp_path):
    """``--set "policy_kwargs.optimizer_kwargs={fused: true, eps: 1.0e-5}"`` (docs/training.md)
    reaches the saved model's optimizer, and changes the update only in the rounding: the same seed
    and data give the same weights to float32 precision as the default optimizer, while one update
    more moves them far beyond that. The eps matters: SB3 gives Adam eps 1e-5 only when no
    optimizer_kwargs are given, so ``{fused: true}`` alone would also change eps to torch's 1e-8."""
    import torch
    from stable_baselines3 import PPO

    cfg = str(_tiny(tmp_path, "ppo"))
    params = {}
    for label, steps, extra in (("default", 128, []), ("one update fewer", 64, []),
                                ("fused", 128, ["--set", "policy_kwargs.optimizer_kwargs={fused: true, eps: 1.0e-5}"])):
        out = tmp_path / label.replace(" ", "_")
        assert train_main(["--algo", "ppo", "--mode", "plain", "--config", cfg, "--out", str(out), "--seed", "3",
                           "--timesteps", str(steps), "--no-progress", *extra]) == 0
        model = PPO.load(out / "model.zip", device="cpu")
        assert bool(model.policy.optimizer.defaults.get("fused")) is (label == "fused")
        assert model.policy.optimizer.defaults["eps"] == 1e-5
        params[label] = torch.nn.utils.parameters_to_vector(model.policy.parameters()).detach().numpy()
    # the tiny config's rollout is 2 arms x 32 steps, two minibatches of 32: 128 steps are two
    # updates, 64 one; an Adam step moves a weight by up to about the learning rate (3e-4)
    assert np.max(np.abs(params["default"] - params["one update fewer"])) > 2e-4
    np.testing.assert_allclose(params["fused"], params["default"], rtol=1e-5, atol=1e-6)
