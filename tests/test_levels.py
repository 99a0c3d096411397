"""Difficulty levels (blf_gym.envs.levels): each a fixed bundle of scenario knobs applied after the draw,
so a level's episode k is the full benchmark's episode k with parts taken away; level 3, the
default, is the benchmark itself; every path (single env, vector env, blf-eval) applies the same
map and blf-eval's records name their level."""

from __future__ import annotations

import json
from dataclasses import replace

import gymnasium as gym
import numpy as np
import pytest

import blf_gym  # noqa: F401
from blf_gym.envs.levels import DEFAULT_LEVEL, LEVELS, WIDE_BOUNDS, apply_level
from blf_gym.model.params import ArmParams, preset
from blf_gym.envs.vector import PlanarBLFVectorEnv
from blf_gym.envs.scenarios import sample_suite


def _draw(seed: int):
    return sample_suite(np.random.default_rng(seed), preset("paper-0.1hz"), "randomized")


@pytest.mark.parametrize("seed", [10_000, 10_001, 20_003])
def test_each_level_changes_only_what_its_row_says(seed):
    sc = _draw(seed)
    full, l0, l1, l2 = (apply_level(sc, k) for k in (3, 0, 1, 2))
    assert full is sc  # the benchmark itself, untouched
    wide = sc.bounds.upper_floor * WIDE_BOUNDS, sc.bounds.lower_floor * WIDE_BOUNDS
    # level 1: the draw's plant, disturbances and reference; only the funnel is wider
    assert replace(l1, bounds=sc.bounds, name=sc.name) == sc
    assert (l1.bounds.upper_floor, l1.bounds.lower_floor) == pytest.approx(wide)
    assert l1.bounds.upper_amplitude == pytest.approx(sc.bounds.upper_amplitude * WIDE_BOUNDS)
    assert l1.bounds.decay_rate == sc.bounds.decay_rate
    # level 2: the draw without its force
    assert replace(l2, force=sc.force, name=sc.name) == sc and l2.force.wrench == (0.0, 0.0, 0.0)
    # level 0: the nominal plant (the paper's masses, no friction, identity dead zone, no force or
    # noise, on the reference at t = 0) in the wide funnel; reference and simulation kept
    assert l0.arm.masses == ArmParams().masses and l0.friction.viscous == 0.0 and l0.friction.coulomb == 0.0
    dz = l0.dead_zone
    assert (dz.slope_right, dz.slope_left, dz.break_right, dz.break_left) == (1.0, 1.0, 0.0, 0.0)
    assert l0.force.wrench == (0.0, 0.0, 0.0) and l0.angle_noise_std == 0.0 and l0.initial_error == (0.0, 0.0, 0.0)
    assert l0.bounds == l1.bounds and l0.reference == sc.reference and l0.sim == sc.sim
    assert [x.name for x in (l0, l1, l2)] == [f"{sc.name}@L{k}" for k in range(3)]


def test_the_nominal_level_has_no_model_mismatch_for_the_law():
    """An independent check of level 0's plant: the LESO estimates the lumped disturbance x3, the
    gap between the plant and the law's nominal model; with the nominal plant (and no force) it is
    orders of magnitude smaller than on the full benchmark, where friction, dead zone and the
    force enter it."""
    sizes = []
    for level in (0, 3):
        env = gym.make("PlanarBLF-v0", scenario="paper-0.1hz", controller="proposed", level=level, duration=25.0)
        env.reset(seed=0)
        x3 = []
        for _ in range(2500):
            obs, _, term, trunc, _ = env.step(np.zeros(3, dtype=np.float32))
            x3.append(obs[28:31])
            if term or trunc:
                break
        sizes.append(np.sqrt(np.mean(np.square(x3[200:]))))  # after the observer's transient
        env.close()
    assert sizes[0] < 0.1 * sizes[1], sizes


@pytest.mark.parametrize("level", [0, 1, 2, 3])
def test_single_and_vector_envs_draw_the_same_episode_and_take_it_to_the_level(level):
    env = gym.make("PlanarBLF-v0", scenario="randomized", level=level)
    full = gym.make("PlanarBLF-v0", scenario="randomized")
    venv = PlanarBLFVectorEnv(num_envs=2, scenario="randomized", level=level)
    env.reset(seed=5)
    full.reset(seed=5)
    venv.reset(seed=[5, 6])
    got, base = env.unwrapped.core.scenarios[0], full.unwrapped.core.scenarios[0]
    assert got == apply_level(base, level) and venv.core.scenarios[0] == got
    # the observation's bounds follow the level
    obs, _ = env.reset(seed=7)
    obs_full, _ = full.reset(seed=7)
    factor = WIDE_BOUNDS if level in (0, 1) else 1.0
    assert obs[15] == pytest.approx(obs_full[15] * factor, rel=1e-6)
    for e in (env, full, venv):
        e.close()


def test_the_default_level_is_the_benchmark_to_the_bit():
    """Level 3, named or not, runs the same episode as before the levels existed: the same
    scenario object from the same draw, and the same observations and rewards to the bit."""
    runs = []
    for kw in ({}, {"level": DEFAULT_LEVEL}):
        env = gym.make("PlanarBLF-v0", scenario="randomized", controller="proposed", **kw)
        obs, _ = env.reset(seed=11)
        assert env.unwrapped.core.scenarios[0] == _draw_env(11)
        rows = [obs]
        for k in range(200):
            obs, r, *_ = env.step(np.full(3, 0.01 * (k % 7 - 3), dtype=np.float32))
            rows.append(np.append(obs, r))
        runs.append(rows)
        env.close()
    for a, b in zip(*runs):
        assert np.array_equal(a, b)


def _draw_env(seed: int):
    """The scenario the env draws at reset(seed) on "randomized", made with a second env."""
    env = gym.make("PlanarBLF-v0", scenario="randomized")
    env.reset(seed=seed)
    sc = env.unwrapped.core.scenarios[0]
    env.close()
    return sc


@pytest.mark.parametrize("bad", [-1, 4, 1.0, True, "2", None])
def test_a_bad_level_is_refused_by_name(bad):
    with pytest.raises(ValueError, match=r"level must be an integer in \[0, 3\]"):
        gym.make("PlanarBLF-v0", level=bad)


def test_blf_eval_scores_a_level_and_every_record_names_it(tmp_path):
    from agents.evaluate import main

    args = ["--controllers", "proposed", "--agents", "--scenarios", "paper-0.1hz", "--suite", "randomized",
            "--suite-seeds", "2", "--duration", "2", "--no-progress", "--no-plots", "--reference", "none"]
    assert main([*args, "--level", "1", "--out", str(tmp_path / "l1")]) == 0
    assert main([*args, "--out", str(tmp_path / "l3")]) == 0
    l1 = json.loads((tmp_path / "l1" / "results.json").read_text())["records"]
    l3 = json.loads((tmp_path / "l3" / "results.json").read_text())["records"]
    assert {r["level"] for r in l1} == {1} and {r["level"] for r in l3} == {3}
    assert [r["scenario"] for r in l1] == ["paper-0.1hz@L1", "randomized@L1"]
    assert [r["scenario"] for r in l3] == ["paper-0.1hz", "randomized"]
    assert [r["suite"] for r in l1] == [None, "randomized"]
    # the same draws: the wide funnel's margins are larger, the tracking the same law's
    for a, b in zip(l1, l3):
        assert min(a["min_margin_deg"]) > min(b["min_margin_deg"])
    assert main([*args, "--level", "7", "--out", str(tmp_path / "bad")]) == 2


def test_the_levels_table_lists_every_level():
    assert [lv.number for lv in LEVELS] == list(range(len(LEVELS))) and LEVELS[DEFAULT_LEVEL].name == "full"
