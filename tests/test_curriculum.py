"""The funnel-width curriculum: the env's ``bound_scale`` and blf-train's ``curriculum``.

A training aid only: every judgement (blf-eval, the learning curves, load_pretrained) runs at the
benchmark's own bounds."""

from __future__ import annotations

import json
import math

import gymnasium as gym
import numpy as np
import pytest

import blf_gym  # noqa: F401
from blf_gym.envs.envcore import MAX_BOUND_SCALE
from blf_gym.model.params import preset


def test_bound_scale_widens_every_drawn_funnel_by_exactly_its_factor_from_the_next_reset():
    plain = gym.make("PlanarBLF-v0", scenario="randomized")
    wide = gym.make("PlanarBLF-v0", scenario="randomized", bound_scale=4.0)
    plain.reset(seed=7)
    wide.reset(seed=7)
    b, w = plain.unwrapped.scenario.bounds, wide.unwrapped.scenario.bounds
    for f in ("upper_amplitude", "upper_floor", "lower_amplitude", "lower_floor"):
        assert getattr(w, f) == 4.0 * getattr(b, f)
    assert w.decay_rate == b.decay_rate
    # the rest of the draw is the same scenario
    assert wide.unwrapped.scenario.arm == plain.unwrapped.scenario.arm
    assert wide.unwrapped.scenario.reference == plain.unwrapped.scenario.reference
    # the observation's bound entries read the widened funnel, and stay inside their boxes at the widest
    widest = gym.make("PlanarBLF-v0", bound_scale=MAX_BOUND_SCALE)
    obs, _ = widest.reset(seed=0)
    assert widest.observation_space.contains(obs)
    # a new value applies at the next reset, not to the running episode
    wide.unwrapped.bound_scale = 1.0
    assert wide.unwrapped.scenario.bounds == w
    wide.reset()
    assert wide.unwrapped.scenario.bounds == preset("paper-0.1hz").bounds


def test_a_wider_funnel_lets_an_error_through_that_the_benchmark_counts():
    """The same torques on the same scenario: the benchmark's funnel is broken, the 15x one is not
    (violations are counted against the episode's own, widened, bounds)."""
    counts = []
    for scale in (1.0, MAX_BOUND_SCALE):
        env = gym.make("PlanarBLF-v0", bound_scale=scale, terminate_on_violation=False)
        env.reset(seed=0)
        n = 0
        for _ in range(20):
            _, _, term, trunc, info = env.step(np.full(3, 0.05, dtype=np.float32))
            n += int(info["cost"] > 0)
            assert not term
        counts.append(n)
    assert counts[0] > 0 and counts[1] == 0


@pytest.mark.parametrize("value", [0.5, 0.0, MAX_BOUND_SCALE * 1.01, math.nan, math.inf, True, "2"])
def test_a_bad_bound_scale_is_refused_by_name(value):
    with pytest.raises(ValueError, match="bound_scale"):
        gym.make("PlanarBLF-v0", bound_scale=value)
    env = gym.make("PlanarBLF-v0")
    with pytest.raises(ValueError, match="bound_scale"):
        env.unwrapped.bound_scale = value
    assert env.unwrapped.bound_scale == 1.0


def test_the_vector_env_takes_it_too():
    from blf_gym.envs.vector import PlanarBLFVectorEnv

    v = PlanarBLFVectorEnv(num_envs=2, scenario="paper-0.5hz", bound_scale=2.0)
    v.reset(seed=0)
    assert v.core.scenarios[1].bounds.upper_floor == 2.0 * preset("paper-0.5hz").bounds.upper_floor


def test_judging_always_drops_the_curriculum():
    from agents.loading import scoring_env_kwargs

    kw = scoring_env_kwargs({"scenario": "randomized", "control_period": 0.01, "bound_scale": 5.0})
    assert "bound_scale" not in kw and kw["control_period"] == 0.01


def test_the_schedule_on_known_numbers_and_bad_curricula_refused():
    from agents.config import TrainConfig, curriculum_scale

    cur = {"bound_scale": 9.0, "until": 1000}
    # S ** (1 - t / T): 9 at the start, 3 half-way, 1 from T on
    assert curriculum_scale(cur, 0) == 9.0
    assert curriculum_scale(cur, 500) == pytest.approx(3.0, rel=1e-12)
    assert curriculum_scale(cur, 1000) == 1.0 and curriculum_scale(cur, 10**9) == 1.0
    assert curriculum_scale({}, 0) == 1.0
    for bad in ({"bound_scale": 1.0, "until": 10}, {"bound_scale": 16.0, "until": 10},
                {"bound_scale": 4.0, "until": 0}, {"bound_scale": 4.0}, {"bound_scale": 4.0, "until": 10, "x": 1}):
        with pytest.raises(ValueError, match="curriculum"):
            TrainConfig.of({"curriculum": bad}, "cfg.yaml")


def test_a_run_with_a_curriculum_trains_wide_and_ends_at_the_benchmarks_bounds(tmp_path, monkeypatch):
    from agents.train import train
    from agents.vec_env import BLFVecEnv

    seen: list[float] = []
    original = BLFVecEnv.set_attr

    def spy(self, name, value, indices=None):
        if name == "bound_scale":
            seen.append(float(value))
        return original(self, name, value, indices)

    monkeypatch.setattr(BLFVecEnv, "set_attr", spy)
    cfg = tmp_path / "cfg.yaml"
    cfg.write_text("n_envs: 2\nenv: {control_period: 0.01, duration: 0.2}\n"
                   "hyperparams: {n_steps: 32, batch_size: 32, n_epochs: 1}\npolicy_kwargs: {net_arch: [8]}\n"
                   "curriculum: {bound_scale: 4.0, until: 96}\neval_freq: 1000\ncheckpoint_freq: 1000\n")
    out = train(algo="ppo", mode="plain", timesteps=192, config=cfg, out=tmp_path / "run", progress=False)
    meta = json.loads((out / "metadata.json").read_text())
    assert meta["config"]["curriculum"] == {"bound_scale": 4.0, "until": 96}
    assert "bound_scale" not in meta["env_kwargs"]
    assert seen[0] == 4.0 and seen[-1] == 1.0 and all(a > b for a, b in zip(seen, seen[1:]))
    # every step before `until` asked for the schedule's value: 4 ** (1 - t/96) at t = 2, 4, ...
    assert seen[1] == pytest.approx(4.0 ** (1 - 2 / 96), rel=1e-12)
    curve = json.loads((out / "eval" / "curve.json").read_text())
    assert "bound_scale" not in curve["env_kwargs"]
