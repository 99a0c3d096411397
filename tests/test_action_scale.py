"""Plain mode's per-joint action scale (issue 61, item 3): the torque at action 1 per joint,
separate from the actuator limit max_torque; an action under a scale s drives the arm exactly as the
action times s / max_torque does without it; bad scales are refused by name; scoring keeps it."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest

import blf_gym  # noqa: F401

SCALE = (25.0, 25.0, 8.0)


def _run(actions, **kw):
    env = gym.make("PlanarBLF-v0", scenario="paper-0.1hz", terminate_on_violation=False, duration=0.3, **kw)
    env.reset(seed=3)
    us, obs = [], []
    for a in actions:
        o, _, _, _, info = env.step(np.asarray(a, dtype=np.float32))
        us.append(info["u"])
        obs.append(o)
    env.close()
    return np.array(us), np.array(obs)


def test_an_action_under_a_scale_is_that_torque():
    rng = np.random.default_rng(0)
    acts = rng.uniform(-1, 1, size=(30, 3)).astype(np.float32)
    u_scaled, obs_scaled = _run(acts, action_scale=SCALE)
    # the same torques asked through the default scale (max_torque, 150 N m)
    u_plain, obs_plain = _run(acts.astype(np.float64) * np.array(SCALE) / 150.0)
    np.testing.assert_allclose(u_scaled, acts.astype(np.float64) * np.array(SCALE), rtol=1e-6, atol=1e-9)
    np.testing.assert_allclose(u_scaled, u_plain, rtol=1e-6, atol=1e-6)
    np.testing.assert_allclose(obs_scaled, obs_plain, rtol=1e-4, atol=1e-6)
    # one number is every joint's scale; None is max_torque's, as before
    u_one, _ = _run(acts[:3], action_scale=25.0)
    np.testing.assert_allclose(u_one, acts[:3].astype(np.float64) * 25.0, rtol=1e-6)
    u_none, _ = _run(acts[:3], action_scale=None)
    np.testing.assert_allclose(u_none, acts[:3].astype(np.float64) * 150.0, rtol=1e-6)


@pytest.mark.parametrize("bad", [0.0, -1.0, 151.0, float("nan"), float("inf"), [25.0, 25.0], [25.0, 25.0, 0.0],
                                 "25", True, [25.0, 25.0, 200.0]])
def test_a_bad_action_scale_is_refused_by_name(bad):
    with pytest.raises(ValueError, match="action_scale"):
        gym.make("PlanarBLF-v0", action_scale=bad)


def test_residual_mode_refuses_an_action_scale_and_a_larger_actuator_allows_a_larger_one():
    with pytest.raises(ValueError, match="residual_scale"):
        gym.make("PlanarBLF-v0", controller="proposed", action_scale=10.0)
    env = gym.make("PlanarBLF-v0", max_torque=300.0, action_scale=200.0)
    assert np.allclose(env.unwrapped.core.action_scale, 200.0)
    env.close()


def test_scoring_keeps_the_scale_an_agent_trained_with():
    from agents.loading import scoring_env_kwargs

    kw = scoring_env_kwargs({"controller": None, "action_scale": list(SCALE), "scenario": "randomized"})
    assert kw["action_scale"] == list(SCALE) and "scenario" not in kw


def test_the_law_reference_of_a_scaled_plain_agent_is_the_law_alone():
    """blf-eval scores a plain agent against the law run through the agent's env set-up with a zero
    residual: a plain agent's action scale has no meaning there, and the reference is the same with
    or without it (it was refused as a residual-mode action scale before)."""
    from dataclasses import replace

    from agents.evaluate import law_reference
    from blf_gym.model.params import preset

    sc = [replace(preset("paper-0.1hz"), sim=replace(preset("paper-0.1hz").sim, duration=0.5))]
    meta = {"mode": "plain", "env_kwargs": {"controller": None, "control_period": 0.01}}
    with_scale = {"mode": "plain", "env_kwargs": {**meta["env_kwargs"], "action_scale": list(SCALE)}}
    a, b = law_reference(sc, meta)[0], law_reference(sc, with_scale)[0]
    np.testing.assert_array_equal(a.sq, b.sq)
    assert a.rmse_deg == b.rmse_deg
