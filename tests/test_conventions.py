"""The conventions of the tools RL researchers use: Gymnasium's vector wrappers on ``gym.make_vec``,
``max_episode_steps`` for the time wrappers, video length, a default reward whose return ranks
policies like ``score_vs_law``, ``agents.load_pretrained`` against blf-eval, rl-zoo3, threads."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.vector import AutoresetMode

import blf_gym  # noqa: F401
from blf_gym.results.metrics import score_vs_law
from blf_gym.model.params import preset
from blf_gym.kernel.simulate import simulate

ROOT = Path(__file__).resolve().parents[1]
IDS = ("PlanarBLF-v0", "PlanarBLFResidual-v0")


# ---- vector envs --------------------------------------------------------------------------------


@pytest.mark.parametrize("env_id", IDS)
def test_make_vec_is_next_step_in_every_mode_and_takes_gymnasium_vector_wrappers(env_id):
    from gymnasium.wrappers.vector import NormalizeObservation, RecordEpisodeStatistics

    for mode in ("vector_entry_point", "sync"):
        v = gym.make_vec(env_id, num_envs=2, vectorization_mode=mode, duration=0.05)
        assert v.metadata["autoreset_mode"] is AutoresetMode.NEXT_STEP, mode
        v.close()
    envs = RecordEpisodeStatistics(NormalizeObservation(gym.make_vec(env_id, num_envs=3, duration=0.05)))
    obs, _ = envs.reset(seed=0)
    lengths = []
    for _ in range(12):  # 5 steps an episode, the 6th resets (next-step), twice over
        obs, r, term, trunc, info = envs.step(np.zeros((3, 3), dtype=np.float32))
        if "episode" in info:
            lengths += [int(x) for x, m in zip(info["episode"]["l"], info["_episode"]) if m]
    assert np.all(np.isfinite(obs))
    # plain mode: zero torque leaves the bounds (terminates); residual: the law runs the whole 5 steps
    assert lengths and all(1 <= n <= 5 for n in lengths)
    if env_id == "PlanarBLFResidual-v0":
        assert lengths == [5] * len(lengths) and len(lengths) == 6
    # same-step stays available, and Gymnasium's wrappers still refuse it (the semantics differ)
    same = gym.make_vec(env_id, num_envs=2, autoreset_mode=AutoresetMode.SAME_STEP)
    assert same.metadata["autoreset_mode"] is AutoresetMode.SAME_STEP
    with pytest.raises(ValueError, match="autoreset_mode"):
        NormalizeObservation(same)
    with pytest.raises(ValueError, match="autoreset_mode must be"):
        gym.make_vec(env_id, num_envs=2, autoreset_mode="disabled")


# ---- episode length -----------------------------------------------------------------------------


@pytest.mark.parametrize("control_period,duration", [(0.01, 0.3), (0.002, 0.1), (1e-4, 0.02)])
def test_spec_max_episode_steps_is_the_episode_and_the_time_wrappers_see_it(control_period, duration):
    from gymnasium.wrappers import TimeAwareObservation
    from sb3_contrib.common.wrappers import TimeFeatureWrapper

    steps = int(round(duration / control_period))
    env = gym.make("PlanarBLFResidual-v0", control_period=control_period, duration=duration)
    assert env.spec.max_episode_steps == steps
    assert gym.make_vec("PlanarBLFResidual-v0", num_envs=2, control_period=control_period,
                        duration=duration).spec.max_episode_steps == steps
    for wrapper in (TimeAwareObservation, TimeFeatureWrapper):
        w = wrapper(gym.make("PlanarBLFResidual-v0", control_period=control_period, duration=duration))
        obs, _ = w.reset(seed=0)
        k = 0
        while True:
            obs, _, term, trunc, _ = w.step(np.zeros(3, dtype=np.float32))
            k += 1
            assert w.observation_space.contains(obs), (wrapper.__name__, k, obs[-1])
            if term or trunc:
                break
        assert k == steps and trunc and not term
        if wrapper is TimeFeatureWrapper:
            assert obs[-1] == pytest.approx(0.0, abs=1e-6)  # 1 - t / max_steps at the end: the true length
        else:
            assert obs[-1] == steps


# ---- rendering ----------------------------------------------------------------------------------


@pytest.mark.parametrize("control_period,mode,fps,every", [(0.02, "rgb_array", 50.0, 1),
                                                             (0.01, "rgb_array", 100.0, 1),
                                                             (0.002, "rgb_array_list", 100.0, 5)])
def test_a_recorded_video_lasts_the_simulated_time(tmp_path, control_period, mode, fps, every):
    from gymnasium.wrappers import RecordVideo
    from moviepy import VideoFileClip

    duration = 0.4
    env = gym.make("PlanarBLFResidual-v0", control_period=control_period, duration=duration, render_mode=mode)
    assert env.metadata["render_fps"] == fps and env.unwrapped.frame_every == every
    env = RecordVideo(env, str(tmp_path), episode_trigger=lambda i: True, name_prefix="v")
    env.reset(seed=0)
    while True:
        _, _, term, trunc, _ = env.step(np.zeros(3, dtype=np.float32))
        if term or trunc:
            break
    n = len(env.recorded_frames)
    env.close()
    assert n == int(round(duration * fps)) + 1  # the reset's frame and one per 1/fps of simulated time
    clip = VideoFileClip(str(tmp_path / "v-episode-0.mp4"))
    try:
        assert clip.fps == pytest.approx(fps)
        assert abs(clip.duration - duration) <= 1.5 / fps  # simulated time, to a frame
    finally:
        clip.close()


# ---- the default reward -------------------------------------------------------------------------


def _oracle(env, info):
    """The law plus the true disturbance's cancellation (agents/oracle.py): better than the law."""
    from blf_gym.model.dynamics import mass_matrix

    core = env.unwrapped.core
    if info is None:
        return np.zeros(3)
    M = mass_matrix(core.loop.X[0, :3], core.scenarios[0].arm)
    return np.clip(-M @ (info["x3"] - info["x3_hat"]) / core.residual_scale, -1, 1)


def _episode(env_id, policy, control_period, duration, **kw):
    env = gym.make(env_id, control_period=control_period, duration=duration, record=True, **kw)
    env.reset(seed=0)
    ret, info, k = 0.0, None, 0
    while True:
        _, r, term, trunc, info = env.step(np.asarray(policy(env, info), dtype=np.float32))
        ret += r
        k += 1
        if term or trunc:
            break
    traj = env.unwrapped.trajectory()
    rmse = np.degrees(np.sqrt(np.mean(traj.e1 ** 2, axis=0)))
    return ret, rmse, term, k


def _law_rmse(duration):
    traj = simulate(preset("paper-0.1hz", duration=duration), "proposed")
    return np.degrees(np.sqrt(np.mean(traj.e1 ** 2, axis=0)))


def test_default_reward_returns_log_score_vs_law_and_ranks_like_it_at_any_period():
    duration = 2.0
    law = _law_rmse(duration)  # an independent run of the law, by simulate()
    # (policy, residual_scale): the law holds the bounds against a constant 60 N m, not against 1000
    policies = {"law": (lambda e, i: np.zeros(3), 20.0), "worse": (lambda e, i: np.full(3, 0.05), 20.0),
                "better": (_oracle, 20.0), "violating": (lambda e, i: np.ones(3), 1000.0)}
    returns = {}
    for cp in (0.01, 0.002):
        for name, (pol, scale) in policies.items():
            ret, rmse, term, _ = _episode("PlanarBLFResidual-v0", pol, cp, duration, residual_scale=scale)
            returns[name, cp] = ret
            if name == "violating":
                assert term and ret <= -50.0, ret  # PHI_CAP - violation: below every other episode
            else:
                assert not term
                # a full episode returns log score_vs_law, the benchmark's own score
                assert ret == pytest.approx(np.log(score_vs_law(rmse, law)), abs=1e-9), (name, cp)
        order = sorted(policies, key=lambda n: returns[n, cp])
        assert order == ["violating", "worse", "law", "better"], (cp, returns)
        assert abs(returns["law", cp]) < 1e-9
    # the same trajectory (a constant residual is the same at any period) returns the same
    assert returns["worse", 0.01] == pytest.approx(returns["worse", 0.002], rel=1e-9)


def test_plain_default_reward_is_the_log_score_and_a_violation_always_loses():
    duration = 1.0
    law = _law_rmse(duration)
    for cp in (0.01, 0.002):
        scores = []
        for torque in (0.0, 0.02, -0.02):
            # without termination every episode runs its whole duration: return = log score_vs_law
            ret, rmse, term, k = _episode("PlanarBLF-v0", lambda e, i, t=torque: np.full(3, t), cp, duration,
                                          terminate_on_violation=False)
            assert not term and k == int(round(duration / cp))
            assert ret == pytest.approx(np.log(score_vs_law(rmse, law)), abs=1e-9)
            scores.append(ret)
        # with termination (the default), the same policies violate and return at most -50
        for torque in (0.0, 0.02):
            ret, _, term, _ = _episode("PlanarBLF-v0", lambda e, i, t=torque: np.full(3, t), cp, duration)
            assert term and ret <= -50.0


@pytest.mark.slow
def test_plain_default_reward_at_0_1_ms_with_the_law_as_a_policy():
    """The README's plain-env call at control_period=1e-4: the proposed law as an SB3-style policy
    (baselines.policies) stays inside the bounds and returns log score_vs_law, near 0 (it is the
    law, sampled), far above a zero torque, which violates and returns at most -50."""
    from baselines.policies import BaselinePolicy

    duration = 0.5
    law = _law_rmse(duration)
    env = gym.make("PlanarBLF-v0", control_period=1e-4, duration=duration, record=True)
    assert env.spec.max_episode_steps == 5000
    pol = BaselinePolicy("proposed", env=env)
    obs, _ = env.reset(seed=0)
    ret = 0.0
    while True:
        a, _ = pol.predict(obs)
        obs, r, term, trunc, _ = env.step(a)
        ret += r
        if term or trunc:
            break
    assert trunc and not term
    rmse = np.degrees(np.sqrt(np.mean(env.unwrapped.trajectory().e1 ** 2, axis=0)))
    assert ret == pytest.approx(np.log(score_vs_law(rmse, law)), abs=1e-9)
    assert abs(ret) < 0.05  # the sampled law is within 3 % of the law's RMSE (tests/test_policies.py)
    zero, _, term, _ = _episode("PlanarBLF-v0", lambda e, i: np.zeros(3), 1e-4, duration)
    assert term and zero <= -50.0 < ret


@pytest.mark.slow
def test_the_readmes_evaluate_policy_snippet_runs_without_warnings():
    """The README's snippet, run as written: SB3's evaluate_policy on the law as a policy, wrapped
    in a Monitor, gives no warning and returns the log score_vs_law of the sampled law (near 0)."""
    import re
    import subprocess
    import sys
    from pathlib import Path

    root = Path(__file__).resolve().parents[1]
    text = (root / "README.md").read_text()
    m = re.search(r"<!-- snippet:evaluate-policy -->\s*```python\n(.*?)```", text, re.S)
    assert m, "README.md has no evaluate-policy snippet"
    site = re.search(r"<!-- snippet:evaluate-policy -->\s*```python\n(.*?)```",
                     (root / "docs" / "getting-started.md").read_text(), re.S)
    assert site and site.group(1) == m.group(1), "docs/getting-started.md's quick start differs from the README's"
    # in a fresh process, as a reader runs it: blf-gym's once-per-process warnings (torch's threads
    # beside the env's) cannot have been spent by another test; -W error makes any warning fail it
    p = subprocess.run([sys.executable, "-W", "error", "-c", m.group(1)], capture_output=True, text=True,
                       timeout=600, cwd=root)
    assert p.returncode == 0, p.stderr[-2000:]
    out = re.fullmatch(r"return (-?\d+\.\d+)\n", p.stdout)
    assert out and abs(float(out.group(1))) < 0.05, p.stdout


def test_a_score_weight_needs_a_violation_penalty_that_makes_violations_lose():
    from blf_gym.kernel.reward import PHI_CAP, SCORE_REWARD, RewardWeights

    assert SCORE_REWARD.violation == 2 * PHI_CAP and SCORE_REWARD.alive == 0.0
    with pytest.raises(ValueError, match="violation must be >= 2 \\* PHI_CAP \\* score"):
        gym.make("PlanarBLFResidual-v0", reward_weights=RewardWeights(score=1.0, tracking=0.0, torque=0.0,
                                                                       alive=0.0, violation=10.0))
    with pytest.raises(ValueError, match="score"):
        RewardWeights(score=-1.0)


# ---- shipped agents -----------------------------------------------------------------------------


def test_load_pretrained_gives_blf_evals_numbers():
    from stable_baselines3.common.evaluation import evaluate_policy

    from agents import load_pretrained
    from agents.evaluate import build_scenarios, evaluate_agent
    from agents.loading import load_agent
    from blf_gym.results.metrics import summarize

    model, env = load_pretrained("ppo_residual", scenario="paper-0.5hz")
    core = env.venv.envs[0].unwrapped.core
    assert core.residual_scale == 8.0 and core.control_period == 0.01  # as trained, not the env's default 2
    assert env.training is False and env.norm_reward is False
    rets, lens = evaluate_policy(model, env, n_eval_episodes=1, deterministic=True, return_episode_rewards=True)
    m, meta, norm = load_agent(ROOT / "agents" / "pretrained" / "ppo_residual")
    (label, scs), = build_scenarios(["paper-0.5hz"], 0, {}, None)
    rec = summarize(evaluate_agent(m, meta, norm, scs, threads=1), "ppo_residual", "residual", label,
                    scs[0].sim.dt, law=[simulate(scs[0], "proposed")])
    assert lens == [3000]
    # the return (float32 in SB3's VecEnv) is blf-eval's per-episode score, in log
    assert rets[0] == pytest.approx(np.log(rec["per_episode_score"][0]), rel=1e-5)
    with pytest.raises(ValueError, match="unknown pretrained agent 'nope'"):
        load_pretrained("nope")
    _, tenv = load_pretrained("ppo_plain", reward="training")
    assert tenv.venv.envs[0].unwrapped.core.weights.alive == pytest.approx(1.01)  # the shaped reward it had


@pytest.mark.parametrize("name", sorted(d.name for d in (ROOT / "agents" / "pretrained").iterdir()
                                       if (d / "model.zip").is_file()))
def test_every_shipped_agent_loads_by_name_and_records_how_it_was_chosen(name):
    """Each folder blf-eval picks up by default loads through load_pretrained with its trained
    kwargs (a plain agent through its filter too), acts finitely, and records its seed and how the
    seed and configuration were chosen, as the protocol asks."""
    from agents import load_pretrained

    meta = json.loads((ROOT / "agents" / "pretrained" / name / "metadata.json").read_text())
    assert isinstance(meta["seed"], int) and "chosen before" in meta["trained_as"]
    model, env = load_pretrained(name, scenario="paper-0.1hz")
    core = env.venv.envs[0].unwrapped.core
    assert core.control_period == pytest.approx(meta["env_kwargs"].get("control_period", 0.01))
    assert core.residual_filter == meta["env_kwargs"].get("residual_filter")  # ppo_plain_searched: barrier
    obs = env.reset()
    for _ in range(3):
        act, _ = model.predict(obs, deterministic=True)
        assert act.shape == (1, 3) and np.all(np.isfinite(act))
        obs, _, _, _ = env.step(act)
    assert np.all(np.isfinite(obs))


# ---- rl-zoo3 ------------------------------------------------------------------------------------


@pytest.mark.slow
def test_rl_zoo3_trains_the_zoo_config_and_evaluates_on_the_same_kwargs(tmp_path):
    pytest.importorskip("rl_zoo3", reason="rl-zoo3 is in the zoo extra (the README's test command installs it)")
    rw = ("dict(relative=True, law_baseline=True, relative_cap=100.0, tracking=1.0, torque=0.0, alive=0.0, "
          "violation=300000.0)")
    cmd = [sys.executable, "-m", "rl_zoo3.train", "--algo", "ppo", "--env", "PlanarBLFResidual-v0",
           "--gym-packages", "blf_gym", "--conf-file", str(ROOT / "agents/configs/zoo/ppo.yml"), "-n", "512",
           "--eval-freq", "256", "--eval-episodes", "1", "-f", str(tmp_path / "logs"), "--seed", "0",
           "--hyperparams", "n_envs:2", "n_steps:256", "--eval-env-kwargs", "scenario:'randomized'",
           "residual_scale:8.0", f"reward_weights:{rw}"]
    p = subprocess.run(cmd, capture_output=True, text=True, timeout=600, cwd=tmp_path)
    assert p.returncode == 0, (p.stdout[-2000:], p.stderr[-2000:])
    run = tmp_path / "logs" / "ppo" / "PlanarBLFResidual-v0_1"
    assert (run / "PlanarBLFResidual-v0.zip").is_file() and (run / "evaluations.npz").is_file()
    import yaml

    saved = dict(yaml.unsafe_load((run / "PlanarBLFResidual-v0" / "config.yml").read_text()))
    assert "env_kwargs" in str(saved) and "residual_scale" in str(saved)
    args = yaml.unsafe_load((run / "PlanarBLFResidual-v0" / "args.yml").read_text())
    ev = dict(args)["eval_env_kwargs"]
    assert ev["residual_scale"] == 8.0 and ev["scenario"] == "randomized" and ev["reward_weights"]["relative"]

    # the evaluation recipe: the run as a blf-eval agent, scored by score_vs_law on the presets
    conv = subprocess.run([sys.executable, "-m", "agents.zoo", str(run), "--out", str(tmp_path / "agent")],
                          capture_output=True, text=True, timeout=300, cwd=ROOT)
    assert conv.returncode == 0, conv.stderr[-2000:]
    meta = json.loads((tmp_path / "agent" / "metadata.json").read_text())
    assert meta["mode"] == "residual" and meta["env_kwargs"]["residual_scale"] == 8.0 and meta["config"]["normalize"]
    assert (tmp_path / "agent" / "vecnormalize.pkl").is_file()
    ev = subprocess.run(["blf-eval", "--agents", str(tmp_path / "agent"), "--suite-seeds", "0", "--jobs", "1",
                         "--no-plots", "--no-progress", "--out", str(tmp_path / "eval")],
                        capture_output=True, text=True, timeout=600, cwd=ROOT)
    assert ev.returncode == 0, ev.stderr[-2000:]
    recs = json.loads((tmp_path / "eval" / "results.json").read_text())["records"]
    mine = [r for r in recs if r["policy"] == meta["name"]]
    assert len(mine) == 2 and all(np.isfinite(r["score_vs_law"]) and r["score_vs_law"] > 0 for r in mine)
    # a folder that is not an rl-zoo3 run is one line, naming what is missing
    bad = subprocess.run([sys.executable, "-m", "agents.zoo", str(tmp_path), "--out", str(tmp_path / "x")],
                         capture_output=True, text=True, timeout=300, cwd=ROOT)
    assert bad.returncode == 2 and len(bad.stderr.strip().splitlines()) == 1 and "args.yml" in bad.stderr
    # an --out that is a file: one line naming it, not a traceback
    (tmp_path / "afile").write_text("x")
    clash = subprocess.run([sys.executable, "-m", "agents.zoo", str(run), "--out", str(tmp_path / "afile")],
                           capture_output=True, text=True, timeout=300, cwd=ROOT)
    assert clash.returncode == 2 and len(clash.stderr.strip().splitlines()) == 1 and "afile" in clash.stderr


# ---- threads ------------------------------------------------------------------------------------


def test_the_vector_env_leaves_cores_to_the_learner_and_says_when_torch_competes():
    from blf_gym.envs.vector import default_threads

    cpus = os.cpu_count() or 1
    assert default_threads(64) == max(1, cpus // 2) and default_threads(1) == 1
    code = ("import warnings, torch; torch.set_num_threads({t}); import gymnasium as gym, blf_gym\n"
            "with warnings.catch_warnings(record=True) as w:\n"
            "    warnings.simplefilter('always')\n"
            "    gym.make_vec('PlanarBLFResidual-v0', num_envs=2, threads={e})\n"
            "print(sum('torch uses' in str(x.message) for x in w))")
    loud = subprocess.run([sys.executable, "-c", code.format(t=cpus, e=1)], capture_output=True, text=True,
                          timeout=300)
    quiet = subprocess.run([sys.executable, "-c", code.format(t=1, e=max(1, cpus - 1))], capture_output=True,
                           text=True, timeout=300)
    assert loud.stdout.strip().endswith("1"), loud.stderr[-2000:]
    assert quiet.stdout.strip().endswith("0"), quiet.stderr[-2000:]
