"""The score reward's reference law, simulated lazily as the episode reaches it.

The score term compares the policy's running squared error with the reference law's on the same
scenario. That reference used to be simulated whole at every reset of a new scenario (0.3-0.6 s,
so a plain agent whose episodes end after a step or two ran at about 4 steps/s); now a reset
simulates nothing and the reference is extended chunk by chunk. These tests pin that the rewards
are the same to the bit whatever the chunking, equal to the whole reference computed in one go,
and that a reset no longer pays for the episode.
"""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest

import blf_gym  # noqa: F401
import blf_gym.envs.envcore as core_module


def _episode_rewards(env_id, scenario, seed, scale, term=False, duration=2.5):
    env = gym.make(env_id, scenario=scenario, duration=duration, terminate_on_violation=term)
    env.reset(seed=seed)
    rng = np.random.default_rng(seed)
    rewards, done = [], False
    while not done:
        _, r, te, tr, info = env.step((rng.uniform(-1, 1, 3) * scale).astype(np.float32))
        rewards.append(r)
        done = te or tr
    return np.array(rewards), env.unwrapped.core


@pytest.mark.parametrize("chunk", [7, 1000])
@pytest.mark.parametrize("env_id,scale", [("PlanarBLFResidual-v0", 0.5), ("PlanarBLF-v0", 0.02)])
def test_the_rewards_do_not_depend_on_the_chunking(monkeypatch, chunk, env_id, scale):
    # 2.5 s episodes cross two 1000-sample blocks of the running sum; chunks of 7 samples straddle
    # them, and chunks of 1000 are the old one-go grouping
    base, _ = _episode_rewards(env_id, "randomized", 3, scale)
    monkeypatch.setattr(core_module, "LAW_CHUNK", chunk)
    other, _ = _episode_rewards(env_id, "randomized", 3, scale)
    np.testing.assert_array_equal(base, other)


def test_the_lazy_reference_is_the_whole_one_computed_in_one_go():
    rewards, core = _episode_rewards("PlanarBLFResidual-v0", "paper-0.5hz", 0, 0.5)
    whole = core.law_cumulative([core.scenarios[0]])[0]
    # the env's lazily filled reference, after the episode reached its end, is the whole one
    np.testing.assert_array_equal(core._law_cum[0], whole)
    # and it is the law's own running error: an independent run of the law alone on the inner path
    from dataclasses import replace

    from blf_gym.kernel.simulate import simulate

    tr = simulate(replace(core.scenarios[0], angle_noise_std=0.0), "proposed")
    np.testing.assert_allclose(whole[-1], np.sum(tr.e1 ** 2, axis=0), rtol=1e-12)


def test_a_reset_simulates_nothing_and_a_step_only_what_it_needs():
    env = gym.make("PlanarBLF-v0", scenario="randomized")
    core = env.unwrapped.core
    for seed in range(5):
        env.reset(seed=seed)
        assert core._law_h[0] == 0  # before: the whole 30 s (30,000 samples) at every new scenario
        env.step(np.zeros(3, dtype=np.float32))
        # one agent step of 10 ms has 10 samples: the reference covers that step, not the episode
        assert core.samples_per_period <= core._law_h[0] <= 2 * core.samples_per_period


def test_a_repeated_scenario_reuses_its_whole_reference():
    env = gym.make("PlanarBLFResidual-v0", scenario="paper-0.1hz", duration=0.5)
    core = env.unwrapped.core
    first, _ = None, None
    for k in range(2):
        env.reset(seed=0)
        rewards, done = [], False
        while not done:
            _, r, te, tr, _ = env.step(np.full(3, 0.1, dtype=np.float32))
            rewards.append(r)
            done = te or tr
        if k == 0:
            first = rewards
            assert len(core._cum_cache) == 1  # the finished run is kept
        else:
            assert rewards == first
    env.reset(seed=0)
    assert core._law_h[0] == core._law_cum.shape[1]  # served whole from the cache
    # a fixed scenario's reference is simulated whole at its first reset (once; the steps then carry
    # none of it), a suite's comes with the episode
    fresh = gym.make("PlanarBLFResidual-v0", scenario="paper-0.5hz", duration=0.5).unwrapped
    fresh.reset(seed=0)
    assert fresh.core._law_h[0] == fresh.core._law_cum.shape[1]
