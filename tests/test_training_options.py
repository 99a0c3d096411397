"""Training options of issue 61, item 3: episodes that start along the reference (``start_time``),
a violation cost that works without termination (``RewardWeights.violation_rate``) and the action
scale read from the law's torques (``action_scale="law"``). Scoring ignores the first two and keeps
the third as numbers."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest

import blf_gym  # noqa: F401
from blf_gym.model.bounds import error_bounds
from blf_gym.model.reference import joint_reference

SHAPED = {"tracking": 1.0, "torque": 0.01}


def _core(env):
    return env.unwrapped.core


def test_an_episode_starts_on_the_reference_at_the_drawn_time():
    env = gym.make("PlanarBLF-v0", scenario="paper-0.1hz", reward_weights=SHAPED, start_time=(5.0, 25.0))
    starts = []
    for seed in range(6):
        env.reset(seed=seed)
        core = _core(env)
        t0 = float(core.loop.time[0])
        starts.append(t0)
        # a whole number of control periods inside the range
        assert 5.0 - 0.005 <= t0 <= 25.0 + 0.005
        assert abs(t0 / 0.01 - round(t0 / 0.01)) < 1e-9
        sc = core.scenarios[0]
        q_d, qd_d, _ = joint_reference(t0, sc)
        x = core.loop.X[0]
        np.testing.assert_allclose(x[:3], q_d, rtol=0, atol=1e-12)  # the paper presets start without error
        np.testing.assert_allclose(x[3:6], qd_d, rtol=0, atol=1e-12)
        # the LESO's states are x1_hat, x2_hat, x3_hat per joint: at the angles and the reference's velocities
        obs_x = x[6:15]
        np.testing.assert_allclose(obs_x[0:3], q_d, atol=1e-12)
        np.testing.assert_allclose(obs_x[3:6], qd_d, atol=1e-12)
        np.testing.assert_array_equal(obs_x[6:9], 0.0)
    assert len(set(starts)) > 3  # the seeds draw different times
    # the same seed draws the same start and the same episode, to the bit
    env.close()
    env = gym.make("PlanarBLF-v0", scenario="randomized", reward_weights=SHAPED, start_time=(5.0, 25.0),
                   terminate_on_violation=False, angle_noise_std=1e-4)
    runs = []
    for _ in range(2):
        env.reset(seed=2)
        runs.append(np.array([env.step(np.full(3, 0.01, np.float32))[0] for _ in range(5)]))
    np.testing.assert_array_equal(runs[0], runs[1])
    env.close()


def test_the_bounds_and_the_law_at_a_late_start_are_those_of_that_time():
    # the proposed law (residual mode, zero residual) started on the reference at 14.5 s, just before
    # the fastest segment: it keeps the bounds of that time, whose width the info reports
    t0 = 14.5
    env = gym.make("PlanarBLFResidual-v0", scenario="paper-0.1hz", reward_weights=SHAPED, start_time=t0,
                   record=True)
    env.reset(seed=0)
    for _ in range(100):
        _, _, term, trunc, _ = env.step(np.zeros(3, np.float32))
        assert not term
    tr = env.unwrapped.trajectory()
    assert abs(tr.t[0] - t0) < 1e-9  # the record starts with the reset's own sample
    k_a, k_b = error_bounds(tr.t, env.unwrapped.scenario.bounds)
    np.testing.assert_allclose(np.broadcast_to(tr.k_a.T, (3, len(tr.t))), np.broadcast_to(k_a, (3, len(tr.t))),
                               rtol=1e-12)
    np.testing.assert_allclose(np.broadcast_to(tr.k_b.T, (3, len(tr.t))), np.broadcast_to(k_b, (3, len(tr.t))),
                               rtol=1e-12)
    assert np.all((tr.e1 < tr.k_a) & (-tr.e1 < tr.k_b))
    env.close()


def test_a_start_near_the_end_is_truncated_at_the_duration():
    env = gym.make("PlanarBLFResidual-v0", scenario="paper-0.1hz", reward_weights=SHAPED, start_time=29.9)
    env.reset(seed=0)
    steps, trunc = 0, False
    while not trunc:
        _, _, term, trunc, _ = env.step(np.zeros(3, np.float32))
        assert not term
        steps += 1
    assert steps == 10
    env.close()


def test_start_time_zero_is_the_usual_episode_to_the_bit():
    def run(**kw):
        env = gym.make("PlanarBLF-v0", scenario="randomized", reward_weights=SHAPED, angle_noise_std=1e-4,
                       terminate_on_violation=False, **kw)
        env.reset(seed=7)
        obs = [env.step(np.full(3, 0.02, np.float32))[0] for _ in range(20)]
        env.close()
        return np.array(obs)

    np.testing.assert_array_equal(run(), run(start_time=0.0))


@pytest.mark.parametrize("bad, match", [(-1.0, "start_time"), (30.0, "start_time"), ((10.0, 5.0), "low <= high"),
                                        ((1.0, 2.0, 3.0), "start_time"), (float("nan"), "start_time"),
                                        ("5", "start_time")])
def test_a_bad_start_time_is_refused_by_name(bad, match):
    with pytest.raises(ValueError, match=match):
        gym.make("PlanarBLF-v0", reward_weights=SHAPED, start_time=bad)


def test_start_time_refuses_a_reward_that_needs_the_law_from_t0():
    with pytest.raises(ValueError, match="start_time needs a reward"):
        gym.make("PlanarBLF-v0", start_time=10.0)  # the default score reward
    with pytest.raises(ValueError, match="start_time needs a reward"):
        gym.make("PlanarBLF-v0", reward_weights={"relative": True}, start_time=10.0)


def test_scoring_drops_the_training_options():
    from agents.loading import scoring_env_kwargs

    kw = scoring_env_kwargs({"controller": None, "start_time": [0.0, 20.0], "action_scale": [20.0, 25.0, 7.0],
                             "terminate_on_violation": False})
    assert "start_time" not in kw and kw["action_scale"] == [20.0, 25.0, 7.0]


def _violating_run(rate):
    # a constant torque drives the arm out of its bounds within a few steps; termination off
    env = gym.make("PlanarBLF-v0", scenario="paper-0.1hz", terminate_on_violation=False,
                   reward_weights={**SHAPED, "violation_rate": rate}, duration=1.0)
    env.reset(seed=0)
    out = []
    for _ in range(30):
        _, r, term, _, info = env.step(np.array([0.1, -0.1, 0.05], np.float32))
        assert not term, info["termination_reason"]
        out.append((r, info["reward_info"]["violation"], int(info["violating_samples"]), info["cost"]))
    env.close()
    return out


def test_the_violation_rate_charges_the_share_of_violating_samples_without_termination():
    free, charged = _violating_run(0.0), _violating_run(3.0)
    seen = 0
    for (r0, p0, _, c0), (r1, p1, n1, c1) in zip(free, charged):
        assert p0 == 0.0
        # 10 ms steps hold 10 samples: the penalty is the rate times the violating share
        assert p1 == pytest.approx(-3.0 * float(n1) / 10.0, abs=1e-12)
        assert r1 == pytest.approx(r0 + p1, abs=1e-9)
        seen += c1 > 0
    assert seen > 10  # the test drove the arm out of its bounds


def test_a_bad_violation_rate_is_refused_by_name():
    with pytest.raises(ValueError, match="violation_rate"):
        gym.make("PlanarBLF-v0", reward_weights={"violation_rate": -1.0})


def test_the_law_scale_covers_the_law_and_is_an_agent_action_that_reproduces_it():
    """action_scale="law" is twice the largest torque the law applies after its start-up on the
    env's own draws; checked against the law's torques read from simulate_batch's trajectories."""
    from dataclasses import replace

    from blf_gym.envs.envcore import LAW_SCALE_MARGIN, LAW_SCALE_SKIP, law_action_scale
    from blf_gym.kernel.simulate import simulate

    scale = law_action_scale("paper-0.1hz")
    tr = simulate(replace(blf_gym.preset("paper-0.1hz"), angle_noise_std=0.0))
    top = np.abs(tr.u[tr.t >= LAW_SCALE_SKIP - 1e-12]).max(axis=0)
    np.testing.assert_allclose(scale, LAW_SCALE_MARGIN * top, rtol=1e-12)
    env = gym.make("PlanarBLF-v0", scenario="paper-0.1hz", action_scale="law")
    np.testing.assert_allclose(_core(env).action_scale, scale)
    env.close()
    # per arm and per level: the nominal plant of level 0 needs less torque than the full task
    assert all(a < b for a, b in zip(law_action_scale("randomized", level=0), law_action_scale("randomized")))


def test_a_run_trains_with_the_options_and_is_scored_without_them(tmp_path, monkeypatch):
    import json

    from agents.loading import scoring_env_kwargs
    from agents.train import train
    from blf_gym.envs.envcore import EnvCore

    starts: list[int] = []
    original = EnvCore._start_steps

    def spy(self, idx, scenarios):
        out = original(self, idx, scenarios)
        starts.extend(out or [])
        return out

    monkeypatch.setattr(EnvCore, "_start_steps", spy)
    cfg = tmp_path / "cfg.yaml"
    cfg.write_text("n_envs: 2\nenv: {control_period: 0.01, duration: 2.0, start_time: [0.5, 1.5], action_scale: law, "
                   "terminate_on_violation: false, reward_weights: {tracking: 1.0, torque: 0.01, violation_rate: 2.0}}\n"
                   "hyperparams: {n_steps: 32, batch_size: 32, n_epochs: 1}\npolicy_kwargs: {net_arch: [8]}\n"
                   "eval_freq: 1000\ncheckpoint_freq: 1000\n")
    out = train(algo="ppo", mode="plain", scenario="paper-0.1hz", timesteps=128, config=cfg, out=tmp_path / "run",
                progress=False)
    meta = json.loads((out / "metadata.json").read_text())
    kw = meta["env_kwargs"]
    # the training episodes started along the reference, between 0.5 and 1.5 s (50 to 150 periods)
    assert starts and all(5000 <= k <= 15000 and k % 100 == 0 for k in starts)
    # "law" is recorded as the numbers it stood for on this run's own env
    probe = gym.make("PlanarBLF-v0", scenario="paper-0.1hz", duration=2.0, action_scale="law")
    assert kw["action_scale"] == [float(v) for v in _core(probe).action_scale]
    probe.close()
    # scoring starts at t = 0 with the scale the agent trained with
    scored = gym.make("PlanarBLF-v0", scenario="paper-0.1hz", **scoring_env_kwargs(kw))
    assert _core(scored).start_time is None
    np.testing.assert_array_equal(_core(scored).action_scale, kw["action_scale"])
    scored.reset(seed=0)
    assert _core(scored).loop.time[0] == 0.0
    scored.close()


@pytest.mark.parametrize("bad", [{"episodes": 0}, {"episodes": "x"}, {"margin": 0.5}, {"seed": -1}, {"level": 7},
                                 {"max_torque": -1.0}])
def test_law_action_scale_refuses_bad_arguments_by_name(bad):
    from blf_gym.envs.envcore import law_action_scale

    with pytest.raises(ValueError, match=f"law_action_scale.{next(iter(bad))}"):
        law_action_scale("paper-0.1hz", **bad)
