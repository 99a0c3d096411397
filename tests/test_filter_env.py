"""The barrier filter through the env, the commands and the agent metadata (docs/model.md section 11)."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest

import blf_gym  # noqa: F401
from agents.evaluate import with_filter
from agents.config import env_keys


def test_the_residual_env_filters_and_reports_it():
    env = gym.make("PlanarBLFResidual-v0", residual_filter="barrier", duration=0.5)
    env.reset(seed=0)
    for _ in range(50):
        obs, r, term, trunc, info = env.step(np.ones(3, dtype=np.float32))
    fo = info["filter_outputs"]
    assert set(fo) == {"r_f", "theta", "beta", "breach", "assumptions", "handed_back"}
    assert 0.0 <= fo["theta"][0] <= 1.0 and fo["breach"][0] == 0.0
    # the torque applied is the law's plus the filtered residual, never more than asked for
    assert np.all(np.abs(fo["r_f"]) <= 2.0 + 1e-12)
    np.testing.assert_allclose(info["u"], np.clip(info["u_law"] + fo["r_f"], -150, 150), rtol=0, atol=1e-12)
    assert trunc and info["episode_metrics"]["filter_breaches"] == 0
    assert isinstance(info["episode_metrics"]["assumption_failures"], int)


def test_a_law_without_a_filter_refuses_the_option():
    for controller in ("bc", "lesobc"):
        with pytest.raises(ValueError, match="ships no residual filter"):
            gym.make("PlanarBLFResidual-v0", controller=controller, residual_filter="barrier")
    with pytest.raises(ValueError, match="residual_filter"):
        gym.make("PlanarBLFResidual-v0", residual_filter="nonexistent")
    with pytest.raises(ValueError, match="residual_filter"):
        gym.make("PlanarBLFResidual-v0", residual_filter=3)


def test_a_filter_named_with_parameters_uses_them_and_bad_ones_are_refused():
    """'barrier:handback=1e-9' hands control back at any innovation (the noise makes one), so r_f is 0
    at every step and says so; a plain 'barrier' lets the same residual through. A parameter that is
    not key=number, or that the filter refuses, is a ValueError naming it."""
    outs = {}
    for spec in ("barrier", "barrier:handback=1e-9"):
        env = gym.make("PlanarBLFResidual-v0", residual_filter=spec, duration=0.2)
        env.reset(seed=0)
        for _ in range(20):
            *_, info = env.step(np.ones(3, dtype=np.float32))
        outs[spec] = info["filter_outputs"]
    assert outs["barrier"]["handed_back"][0] == 0.0 and np.any(outs["barrier"]["r_f"] != 0.0)
    assert outs["barrier:handback=1e-9"]["handed_back"][0] == 1.0
    np.testing.assert_array_equal(outs["barrier:handback=1e-9"]["r_f"], np.zeros(3))
    for spec, word in (("barrier:handback", "key=number"), ("barrier:handback=-1", "handback"),
                       ("barrier:bogus=1", "bogus")):
        with pytest.raises(ValueError, match=word):
            gym.make("PlanarBLFResidual-v0", residual_filter=spec)
    with pytest.raises(ValueError, match="residual-filter"):
        with_filter({"name": "a", "env_kwargs": {}}, "cbf:gamma1=0")


def test_in_plain_mode_it_is_a_safety_filter_around_any_policy():
    # a policy that commands no torque at all: the arm falls under gravity and leaves the bounds
    # within a few steps; through the filter the proposed law takes over as the margin shrinks
    kw = dict(duration=2.0, terminate_on_violation=False)
    raw = gym.make("PlanarBLF-v0", **kw)
    filt = gym.make("PlanarBLF-v0", residual_filter="barrier", **kw)
    costs = {}
    for name, env in (("raw", raw), ("filtered", filt)):
        env.reset(seed=0)
        total = 0.0
        for _ in range(200):
            _, _, _, _, info = env.step(np.zeros(3, dtype=np.float32))
            total += info["cost"]
        costs[name] = total
    assert costs["raw"] > 100 and costs["filtered"] == 0, costs


def test_the_agent_metadata_records_the_filter_and_blf_eval_can_replace_it():
    assert "residual_filter" in env_keys()  # a config's env key, recorded in metadata["env_kwargs"]
    meta = {"name": "ppo_residual", "mode": "residual", "env_kwargs": {"controller": "proposed"}}
    m = with_filter(meta, "barrier")
    assert m["env_kwargs"]["residual_filter"] == "barrier" and m["name"] == "ppo_residual+barrier"
    assert meta["env_kwargs"] == {"controller": "proposed"}  # the original is untouched
    m2 = with_filter(m, "none")
    assert m2["env_kwargs"]["residual_filter"] is None and m2["name"] == "ppo_residual+barrier-filter"
    with pytest.raises(ValueError, match="residual-filter"):
        with_filter(meta, "nope")


def test_the_adversarial_list_is_the_documented_one():
    from agents.adversarial import sequences

    seqs = sequences(3000)
    assert len(seqs) == 31
    sat = [k for k in seqs if k.startswith("sat")]
    assert len(sat) == 8 and len({tuple(seqs[k][0]) for k in sat}) == 8
    for k in sat:
        assert np.all(np.abs(seqs[k]) == 1.0) and np.all(seqs[k] == seqs[k][0])
    # bang-bang: all joints switch sign every 10, 20 and 50 ms (1, 2 and 5 agent steps of 10 ms)
    for period, steps in ((10, 1), (20, 2), (50, 5)):
        col = seqs[f"bang{period}"][:, 0]
        switches = np.flatnonzero(np.diff(col) != 0) + 1
        assert np.all(np.diff(switches) == steps) and switches[0] == steps
    rnd = [k for k in seqs if k.startswith("rand")]
    assert len(rnd) == 20 and all(np.all(np.abs(seqs[k]) <= 1.0) for k in rnd)
    np.testing.assert_array_equal(seqs["rand03"], sequences(3000)["rand03"])  # seeded
    assert not np.array_equal(seqs["rand03"], seqs["rand04"])
