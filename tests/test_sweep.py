"""blf-sweep: the sweep file's checks, the objective, the Ray Tune search space, and real sweeps on a
local Ray instance (the shipped smoke sweep, a resume after Ctrl-C, the blf-tune alias), with one
trial compared bit for bit against a direct blf-train run."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
import zipfile
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
SMOKE = ROOT / "agents" / "configs" / "sweeps" / "smoke.yaml"
GROUPS = ("paper-0.1hz", "paper-0.5hz", "randomized")

ray = pytest.importorskip("ray", reason="the sweep extra is not installed (the README's test command installs it)")


def _spec(**kw):
    base = {"name": "t", "base": str(ROOT / "agents/configs/ppo_PlanarBLFResidual-v0.yaml"), "timesteps": 100,
            "seeds": [0], "search": "random", "num_samples": 2,
            "space": {"hyperparams.learning_rate": {"loguniform": [1e-5, 1e-3]}}}
    base.update(kw)
    return {k: v for k, v in base.items() if v is not None}


def _load(**kw):
    from agents.sweep import load_sweep

    return load_sweep(_spec(**kw), ROOT)


# ---- the sweep file ---------------------------------------------------------------------------


@pytest.mark.parametrize("kw, match", [
    ({"scenario": "stress"}, "stress suite is held out"),
    ({"colour": 1}, r"unknown sweep key\(s\) \['colour'\]"),
    ({"search": "bayes"}, "unknown search 'bayes'"),
    ({"seeds": [0, 0]}, "distinct integers"),
    ({"seeds": [True]}, "seeds? must be"),
    ({"timesteps": 1.5}, "timesteps must be an integer"),
    ({"num_samples": 0}, "num_samples must be an integer >= 1"),
    ({"search": "grid", "num_samples": None}, "grid takes only grid"),
    ({"search": "grid", "num_samples": 3}, "num_samples applies to search: random or optuna"),
    ({"space": {"hyperparams.learning_rate": {"grid": [1e-4]}}}, "grid values need search: grid"),
    ({"space": {"curve_suite_seeds": {"choice": [1, 2]}}}, "cannot be searched"),
    ({"space": {"env.duration": {"choice": [1.0, 2.0]}}}, "cannot be searched"),
    ({"space": {"env.colour": {"choice": [1]}}}, "unknown env kwarg 'colour'"),
    ({"space": {"gamma": {"choice": [0.9]}}}, "unknown config key 'gamma'"),
    ({"space": {"hyperparams.learning_rate": {"loguniform": [0.0, 1e-3]}}}, "needs low > 0"),
    ({"space": {"hyperparams.learning_rate": {"uniform": [1e-3, 1e-4]}}}, "needs low < high"),
    ({"space": {"hyperparams.learning_rate": {"normal": [0, 1]}}}, "unknown distribution 'normal'"),
    ({"space": {"hyperparams.n_steps": {"int": {"low": 64, "high": 256, "log": "yes"}}}}, "log must be true or false"),
    ({"space": {"hyperparams.n_steps": {"randint": [64.0, 256]}}}, "takes integers"),
    ({"overrides": {"hyperparams.learning_rate": 1e-4}}, "both in overrides and in space"),
    ({"overrides": {"n_envs": 0}}, "n_envs must be an integer >= 1"),
    ({"scheduler": {"hyperband": {}}}, "scheduler must be"),
    ({"scheduler": {"asha": {"grace_period": 1000}}}, r"grace_period must be an integer in \[1, timesteps\]"),
    ({"base": "no_such.yaml"}, "config file not found"),
    ({"controller": "pid"}, r"unknown controller 'pid'; accepted: \[.*'proposed'"),
    ({"controller": "bc", "mode": "plain"}, "controller applies to mode: residual only"),
    ({"observer": "kalman"}, "unknown observer 'kalman'"),
    ({"time_budget_s": 0}, "time_budget_s must be a number of seconds > 0"),
    ({"time_budget_s": "1h"}, "time_budget_s must be a number of seconds > 0"),
    ({"time_budget_s": True}, "time_budget_s must be a number of seconds > 0"),
])
def test_a_bad_sweep_file_is_refused_by_name(kw, match):
    with pytest.raises(ValueError, match=match):
        _load(**kw)


def test_the_shipped_smoke_sweep_is_valid_and_small():
    from agents.sweep import load_sweep, n_trials

    spec = load_sweep(SMOKE)
    assert spec["timesteps"] == 2048 and spec["seeds"] == [0, 1] and spec["num_samples"] == 2
    assert n_trials(spec) == 4


def test_ray_space_keeps_optuna_bounds_and_encodes_lists():
    """Optuna's int high is included and Ray's randint high is excluded: the conversion must not
    lose the top value, and list-valued choices reach the config as lists."""
    from ray import tune

    from agents.sweep import _decode, _ray_space

    spec = _load(space={"hyperparams.n_epochs": {"int": {"low": 1, "high": 3}},
                        "policy_kwargs.net_arch": {"categorical": [[64, 64], [256, 256]]}})
    space = _ray_space(spec)
    draws = {space["hyperparams.n_epochs"].sample() for _ in range(300)}
    assert draws == {1, 2, 3}
    assert isinstance(space["policy_kwargs.net_arch"], tune.search.sample.Categorical)
    picked = {json.dumps(_decode({"policy_kwargs.net_arch": space["policy_kwargs.net_arch"].sample()}, spec)
                         ["policy_kwargs.net_arch"]) for _ in range(50)}
    assert picked == {"[64, 64]", "[256, 256]"}
    grid = _ray_space(_load(search="grid", num_samples=None, seeds=[3, 5], space={"env.residual_scale": {"grid": [4.0, 8.0]}}))
    assert grid["seed"] == {"grid_search": [3, 5]} and grid["env.residual_scale"] == {"grid_search": [4.0, 8.0]}


def test_a_registered_plug_in_reaches_the_trials_command_by_name(tmp_path):
    """The example plug-ins (the README's test command installs them) are usable in a sweep."""
    from agents.sweep import trial_command

    spec = _load(controller="proposed_integral", observer="eso4")
    cmd = trial_command(spec, 3, tmp_path / "c.yaml", tmp_path / "run")
    assert cmd[cmd.index("--controller") + 1] == "proposed_integral"
    assert cmd[cmd.index("--observer") + 1] == "eso4" and cmd[cmd.index("--seed") + 1] == "3"


def test_trial_config_applies_overrides_then_sampled_values():
    from agents.sweep import trial_config

    spec = _load(overrides={"n_envs": 2, "env.residual_scale": 3.0})
    cfg = trial_config(spec, {"hyperparams.learning_rate": 5e-4})
    assert cfg["n_envs"] == 2 and cfg["env"]["residual_scale"] == 3.0
    assert cfg["hyperparams"]["learning_rate"] == 5e-4 and cfg["hyperparams"]["n_steps"] == 512  # the base's
    assert spec["base"]["hyperparams"]["learning_rate"] == "lin_3e-4"  # the base is not modified


# ---- the objective ----------------------------------------------------------------------------


def _point(rmse_scale=1.0, failure=0.0):
    law = {"paper-0.1hz": [0.01, 0.02, 0.2], "paper-0.5hz": [0.04, 0.04, 0.4], "randomized": [0.1, 0.08, 0.3]}
    pt = {"timesteps": 10, "wall_s": 1.0}
    for g in GROUPS:
        pt[g] = {"rmse_deg": [v * rmse_scale for v in law[g]], "violations": [0, int(failure > 0), 0],
                 "failure_rate": failure if g == "randomized" else 0.0, "diverged": 0}
    return pt, law


def test_objective_is_score_vs_law_and_a_failure_always_loses():
    from agents.sweep import rank_key, score_point

    pt, law = _point(0.5)
    row = score_point(pt, law, suite_seeds=4)
    # half the law's RMSE on every joint of every group: score 2 per group and pooled
    assert row["score_vs_law"] == pytest.approx(2.0, rel=1e-12) and row["objective"] == row["score_vs_law"]
    bad, _ = _point(0.1, failure=0.25)  # ten times better, but one of the 4 suite episodes failed
    brow = score_point(bad, law, suite_seeds=4)
    assert brow["failed_episodes"] == 1 and brow["episodes"] == 6
    assert brow["objective"] == pytest.approx(-1 / 6) and brow["score_vs_law"] == pytest.approx(10.0)
    clean = {"objective": 0.2, "failed_episodes": 0}
    dirty = {"objective": 5.0, "failed_episodes": 1}
    assert sorted([dirty, clean, {}], key=rank_key) == [clean, dirty, {}]


# ---- real sweeps --------------------------------------------------------------------------------


def _run(*args, cwd=ROOT, timeout=600):
    return subprocess.run([sys.executable, "-m", *args], capture_output=True, text=True, timeout=timeout, cwd=cwd)


def _strip(points):
    return [{k: v for k, v in p.items() if k != "wall_s"} for p in points]


def _policy_bytes(run: Path) -> bytes:
    with zipfile.ZipFile(run / "model.zip") as z:
        return z.read("policy.pth")


@pytest.mark.slow
def test_an_interrupted_smoke_sweep_resumes_ranks_its_trials_and_a_trial_is_a_direct_blf_train_run(tmp_path):
    """The shipped smoke sweep, stopped by Ctrl-C once its first trial finished (one trial at a
    time), then resumed by the same command with trials in parallel: the finished trial is kept,
    the sweep completes and ranks its configurations, and the finished trial equals a direct
    blf-train run of its recorded command bit for bit."""
    from agents.sweep import law_levels

    out = tmp_path / "smoke"
    proc = subprocess.Popen([sys.executable, "-m", "agents.sweep", str(SMOKE), "--out", str(out),
                             "--concurrency", "1"], cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                            text=True, preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    try:
        deadline = time.time() + 300
        first = None
        while time.time() < deadline and first is None:
            time.sleep(1)
            for meta in (out / "runs").glob("*/metadata.json"):
                if json.loads(meta.read_text()).get("completed"):
                    first = meta.parent
        assert first is not None, "no trial finished in 300 s"
        time.sleep(2)
        proc.send_signal(signal.SIGINT)
        text, _ = proc.communicate(timeout=180)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 130, text[-3000:]
    assert "run the same command to resume" in text
    before = json.loads((first / "metadata.json").read_text())
    p = _run("agents.sweep", str(SMOKE), "--out", str(out), "--concurrency", "2")
    assert p.returncode == 0, p.stderr[-3000:]
    assert "resuming" in p.stderr
    assert "blf-sweep: finished" in p.stderr and "4 done" in p.stderr
    after = json.loads((first / "metadata.json").read_text())
    assert after["segments"] == before["segments"]  # the finished trial was not trained again
    res = json.loads((out / "sweep.json").read_text())
    assert res["counts"]["done"] == 4 and len(res["trials"]) == 4 and len(res["configs"]) == 2
    assert res["spec"]["name"] == "smoke" and res["versions"] and "git_commit" in res
    # the ranking: the higher mean objective first, every configuration with both seeds
    objs = [c["objective"] for c in res["configs"]]
    assert objs == sorted(objs, reverse=True)
    assert all(c["seeds"] == [0, 1] for c in res["configs"])
    # each trial's score recomputed from its curve and the law, independently of the sweep's code:
    # 1 / the geometric mean of the nine per-joint RMSE ratios
    law = law_levels(2, 2.0)
    assert res["law"] == law  # the same code path on the same machine: equal
    for t in res["trials"]:
        curve = json.loads((out / "runs" / t["run"] / "eval" / "curve.json").read_text())["points"]
        assert curve[-1]["timesteps"] == 2048
        ratios = np.concatenate([np.asarray(curve[-1][g]["rmse_deg"]) / law[g] for g in GROUPS])
        assert t["score"]["score_vs_law"] == pytest.approx(1 / np.exp(np.mean(np.log(ratios))), rel=1e-12)
    md = (out / "sweep.md").read_text()
    assert md.count("| smoke-") == 4 and "| 1 | " in md and "| 2 | " in md
    # the trial that ran in one go against a direct blf-train with its recorded config, seed and budget
    t = next(t for t in res["trials"] if out / "runs" / t["run"] == first)
    cmd = t["command"].split()
    assert cmd[0] == "blf-train" and cmd[cmd.index("--out") + 1] == str(first)
    cmd[cmd.index("--out") + 1] = str(tmp_path / "direct")
    d = _run("agents.train", *cmd[1:])
    assert d.returncode == 0, d.stderr[-3000:]
    direct = json.loads((tmp_path / "direct" / "eval" / "curve.json").read_text())["points"]
    trial = json.loads((first / "eval" / "curve.json").read_text())["points"]
    assert _strip(direct) == _strip(trial)  # bit-identical metrics (JSON floats round-trip exactly)
    assert _policy_bytes(tmp_path / "direct") == _policy_bytes(first)
    # a different sweep into the same folder is refused
    other = tmp_path / "other.yaml"
    other.write_text(SMOKE.read_text().replace("search_seed: 0", "search_seed: 1").replace(
        "base: ../", f"base: {SMOKE.parent.parent}/"))
    q = _run("agents.sweep", str(other), "--out", str(out))
    assert q.returncode == 2 and "holds another sweep" in q.stderr and "Traceback" not in q.stderr


def _smoke_variant(tmp_path: Path, name: str, num_samples: int, timesteps: int, extra: str) -> Path:
    """The shipped smoke sweep with one seed, its name, size and budget changed and ``extra`` keys
    appended (a key given again in ``extra`` replaces the smoke file's, e.g. ``search``)."""
    text = (SMOKE.read_text().replace("base: ../", f"base: {SMOKE.parent.parent}/")
            .replace("name: smoke", f"name: {name}").replace("seeds: [0, 1]", "seeds: [0]")
            .replace("num_samples: 2", f"num_samples: {num_samples}").replace("timesteps: 2048", f"timesteps: {timesteps}"))
    for line in extra.splitlines():
        key = line.split(":")[0] + ":"
        text = "\n".join(ln for ln in text.splitlines() if not ln.startswith(key)) + "\n"
    sweep = tmp_path / f"{name}.yaml"
    sweep.write_text(text + extra)
    return sweep


@pytest.mark.slow
def test_asha_prunes_through_blf_train_and_tpe_proposes(tmp_path):
    """ASHA on the learning-curve points, Optuna's TPE proposing: pruned trials stop early and
    their blf-train ends on its SIGTERM path (a final checkpoint, status 'interrupted')."""
    sweep = _smoke_variant(tmp_path, "asha", 4, 3072, "search: optuna\n"
                           "scheduler: {asha: {grace_period: 1024, reduction_factor: 2}}\nconcurrency: 1\n")
    out = tmp_path / "out"
    p = _run("agents.sweep", str(sweep), "--out", str(out))
    assert p.returncode == 0, p.stderr[-3000:]
    res = json.loads((out / "sweep.json").read_text())
    c = res["counts"]
    assert c.get("done", 0) + c.get("pruned", 0) == 4 and c.get("done", 0) >= 1
    # one at a time, trials reach the rungs in a fixed order with bit-reproducible scores, so the
    # outcome does not depend on timing; with 4 configurations and reduction factor 2, a trial
    # below the first rung's median is stopped
    assert c.get("pruned", 0) >= 1, c
    for t in res["trials"]:
        meta = json.loads((out / "runs" / t["run"] / "metadata.json").read_text())
        if t["status"] == "pruned":
            assert t["timesteps"] < 3072 and meta["status"] == "interrupted"
            assert (out / "runs" / t["run"] / "checkpoints").is_dir()
        else:
            assert t["timesteps"] == 3072 and meta["status"] == "completed"
    assert len({json.dumps(t["params"], sort_keys=True) for t in res["trials"]}) == 4


@pytest.mark.slow
def test_a_wall_clock_budget_stops_the_sweep_and_a_resume_does_not_renew_it(tmp_path):
    """A budget shorter than the trials: Ray Tune stops them when it runs out, the sweep ends
    normally (exit 0, not an interrupt) with the stopped trials marked 'budget' and the rest
    never started; the same command then finds the budget spent and starts nothing."""
    # 90 s: with both cores busy elsewhere, a budget of 25 s (and of 60 s under heavier load) ended
    # before any trial had trained: Ray's start, the trial's imports and its first curve point came later
    sweep = _smoke_variant(tmp_path, "budget", 3, 5_000_000, "concurrency: 1\ntime_budget_s: 90\n")
    out = tmp_path / "out"
    p = _run("agents.sweep", str(sweep), "--out", str(out))
    assert p.returncode == 0, p.stderr[-3000:]
    res = json.loads((out / "sweep.json").read_text())
    c = res["counts"]
    # 5M steps take half an hour here: no trial can finish in 90 s (200k steps could, on an idle
    # machine). At the budget's end the running one's blf-train gets SIGTERM and saves (Ray may
    # start the next one meanwhile; that one stops after its first curve point)
    assert c.get("budget", 0) >= 1 and c.get("budget", 0) + c.get("pending", 0) == 3 and c.get("done", 0) == 0, c
    used = json.loads((out / "budget.json").read_text())["used_s"]
    assert 90 <= used < 90 + 120
    stopped = [t for t in res["trials"] if t["status"] == "budget"]
    assert max(t["timesteps"] for t in stopped) > 0 and all(t["timesteps"] < 5_000_000 for t in stopped)
    for t in stopped:
        # blf-train was stopped by SIGTERM, not killed: its final save holds every step it took
        run = out / "runs" / t["run"]
        meta = json.loads((run / "metadata.json").read_text())
        assert meta["status"] == "interrupted" and (run / "model.zip").is_file()
        assert meta["timesteps"] >= t["timesteps"]
    assert "Wall-clock budget 90 s" in (out / "sweep.md").read_text()
    again = _run("agents.sweep", str(sweep), "--out", str(out))
    assert again.returncode == 0 and "budget (90 s) is spent" in again.stderr
    assert json.loads((out / "budget.json").read_text())["used_s"] == used


@pytest.mark.slow
def test_blf_tune_is_a_grid_sweep_over_config_files(tmp_path):
    cands = []
    for name, scale in (("small", 0.5), ("large", 4.0)):
        p = tmp_path / f"{name}.yaml"
        text = (ROOT / "agents/configs/ppo_PlanarBLFResidual-v0.yaml").read_text()
        text = text.replace("residual_scale: 8.0", f"residual_scale: {scale}").replace("n_envs: 8", "n_envs: 2")
        text = text.replace("n_steps: 512", "n_steps: 64").replace("batch_size: 256", "batch_size: 64")
        text = text.replace("curve_suite_seeds: 4", "curve_suite_seeds: 1")
        p.write_text(text.replace("  control_period: 0.01", "  control_period: 0.01\n  duration: 0.5"))
        cands.append(str(p))
    out = tmp_path / "tune"
    r = _run("agents.tune", *cands, "--timesteps", "128", "--out", str(out))
    assert r.returncode == 0, r.stderr[-3000:]
    res = json.loads((out / "sweep.json").read_text())
    assert {t["run"] for t in res["trials"]} == {"small_s0", "large_s0"}
    assert res["spec"]["search"] == "grid" and res["counts"]["done"] == 2
    assert "config=small" in (out / "sweep.md").read_text()


def test_without_ray_blf_sweep_says_which_extra_to_install(monkeypatch, capsys):
    from agents import sweep

    monkeypatch.setitem(sys.modules, "ray", None)
    monkeypatch.setitem(sys.modules, "ray.tune", None)
    assert sweep.main([str(SMOKE), "--out", "/nonexistent/never-written"]) == 2
    err = capsys.readouterr().err
    assert "blf-gym[sweep]" in err and "Traceback" not in err and err.count("\n") == 1


def test_blf_gym_and_the_env_never_import_ray():
    code = ("import sys, gymnasium as gym, blf_gym, agents.train, agents.tune, agents.sweep; "
            "env = gym.make('PlanarBLF-v0'); env.reset(seed=0); env.step(env.action_space.sample()); "
            "bad = sorted(m for m in sys.modules if m.split('.')[0] in ('ray', 'optuna')); "
            "assert not bad, bad")
    p = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300,
                       env={**os.environ, "PYTHONPATH": str(ROOT)})
    assert p.returncode == 0, p.stderr[-2000:]


def test_set_on_the_command_line_joins_the_sweep_files_overrides():
    """blf-sweep's and blf-tune's --set reach every trial's config, over the sweep file's own
    overrides, and are checked like them."""
    from agents.config import parse_overrides
    from agents.sweep import load_sweep, trial_config
    from agents.tune import sweep_file

    spec = load_sweep(_spec(overrides={"eval_freq": 1024, "n_envs": 4}), ROOT,
                      overrides=parse_overrides(["n_envs=2", "env.control_period=0.02"]))
    cfg = trial_config(spec, {"hyperparams.learning_rate": 1e-4})
    assert cfg["eval_freq"] == 1024 and cfg["n_envs"] == 2 and cfg["env"]["control_period"] == 0.02
    assert cfg["hyperparams"]["learning_rate"] == 1e-4
    with pytest.raises(ValueError, match="n_envs must be an integer >= 1"):
        load_sweep(_spec(), ROOT, overrides=parse_overrides(["n_envs=0"]))
    with pytest.raises(ValueError, match="both in overrides and in space"):
        load_sweep(_spec(), ROOT, overrides=parse_overrides(["hyperparams.learning_rate=1e-4"]))
    tuned = sweep_file([ROOT / "agents/configs/ppo_PlanarBLFResidual-v0.yaml"], "ppo", "residual", 100, [0],
                       "randomized", None, ["n_envs=2"])
    assert tuned["overrides"] == {"n_envs": 2}
    assert trial_config(load_sweep(tuned, ROOT), {})["n_envs"] == 2
