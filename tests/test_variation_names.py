"""A varied scenario carries its variations in its name everywhere, with one label: the env's
info["scenario"] and render title, and blf-eval's rows, from the one function in blf_gym.envs.scenarios."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest

import blf_gym  # noqa: F401 (registers the ids)
from blf_gym.model.params import preset
from blf_gym.envs.scenarios import apply_variations, sample_suite, variation_label, varied_name


def test_the_label_is_sorted_canonical_and_short():
    assert variation_label({}) == ""
    assert variation_label({"frequency": 0.5, "force": 20}) == "+force=20,frequency=0.5"
    # an int and the same float read alike, as a per-joint value equal on every joint reads as one
    assert variation_label({"force": 20.0}) == variation_label({"force": 20})
    assert variation_label({"initial_error": (0.1, 0.1, 0.1)}) == "+initial_error=0.1"
    assert variation_label({"initial_error": (0.1, -0.2, 0.0)}) == "+initial_error=[0.1,-0.2,0]"
    assert variation_label({k: 1.0 for k in ("force", "frequency", "payload", "friction_scale", "dead_zone_scale")}) \
        == "+custom"


def test_varying_twice_gives_one_label_and_the_later_value():
    sc = apply_variations(preset("paper-0.1hz"), {"force": 20})
    assert sc.name == "paper-0.1hz+force=20"
    again = apply_variations(sc, {"frequency": 0.5})
    assert again.name == "paper-0.1hz+force=20,frequency=0.5"
    assert apply_variations(again, {"force": 30}).name == "paper-0.1hz+force=30,frequency=0.5"
    assert varied_name("paper-0.1hz+custom", {"force": 1}) == "paper-0.1hz+custom"
    assert apply_variations(preset("paper-0.1hz"), {"force": 20}, name="mine").name == "mine"
    # what the knobs did is what the name says (the reference runs at the varied frequency)
    assert again.reference.frequency == pytest.approx(0.5)


def test_blf_eval_and_the_env_name_a_varied_preset_alike():
    from agents.evaluate import build_scenarios

    kwargs = {"frequency": 0.3, "force": 20.0}
    (label, [sc]), = build_scenarios(["paper-0.1hz"], 0, kwargs, None)
    assert label == sc.name == "paper-0.1hz+force=20,frequency=0.3"
    env = gym.make("PlanarBLFResidual-v0", variations=kwargs, duration=0.05, render_mode="rgb_array")
    _, info = env.reset(seed=0)
    assert info["scenario"].name == label
    # reset options vary it once more: still one label
    _, info = env.reset(seed=0, options={"payload": 0.15})
    assert info["scenario"].name == "paper-0.1hz+force=20,frequency=0.3,payload=0.15"
    env.step(np.zeros(3, dtype=np.float32))
    env.render()
    title = env.unwrapped._renderer.ax_arm.get_title()  # noqa: SLF001 (the frame's title, as drawn)
    assert title.startswith("paper-0.1hz+force=20,frequency=0.3,payload=0.15 |"), title
    env.close()


def test_suite_episodes_keep_their_name_and_gain_the_label():
    rng = np.random.default_rng(0)
    sc = sample_suite(rng, preset("paper-0.1hz"), "randomized")
    assert sc.name == "randomized"
    assert apply_variations(sc, {"force": 20}).name == "randomized+force=20"
