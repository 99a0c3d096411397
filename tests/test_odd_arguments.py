"""Odd arguments that used to run silently in the wrong mode, or fail far from their cause.

Each case was found by trying the env as an RL user would; each assertion fails on the code
before the fix (noted per test)."""

from __future__ import annotations

import subprocess
import sys

import gymnasium as gym
import numpy as np
import pytest

import blf_gym  # noqa: F401
from blf_gym.envs.envcore import MAX_ARMS, EnvCore
from blf_gym.envs.env import PlanarBLFEnv
from blf_gym.model.params import MAX_DURATION, SimParams


@pytest.mark.parametrize("controller", ["none", None])
def test_the_residual_id_refuses_a_controller_that_makes_it_plain(controller):
    # before: controller="none" silently ran plain mode, each action the whole torque (150 N m)
    with pytest.raises(ValueError, match="would run plain mode"):
        gym.make("blf_gym:PlanarBLFResidual-v0", controller=controller)
    with pytest.raises(ValueError, match="would run plain mode"):
        gym.make_vec("PlanarBLFResidual-v0", num_envs=2, controller=controller)
    # the plain id takes it, and is plain
    assert not gym.make("PlanarBLF-v0", controller=controller).unwrapped.core.residual
    assert gym.make("PlanarBLFResidual-v0").unwrapped.core.residual


@pytest.mark.parametrize("mode", [True, False, 1, 2.5, b"rgb_array", ["rgb_array"], ("human",), {"a": 1},
                                  "rgb", "rgb_array_lists", object()])
def test_a_junk_render_mode_gets_the_envs_own_error(mode):
    # before: gym.make read it first and failed with AttributeError: 'bool' object has no attribute 'endswith'
    for env_id in ("PlanarBLF-v0", "PlanarBLFResidual-v0"):
        with pytest.raises(ValueError, match="PlanarBLFEnv: render_mode must be one of"):
            gym.make(env_id, render_mode=mode)


def test_the_render_modes_still_work_through_make():
    env = gym.make("PlanarBLF-v0", render_mode="rgb_array_list", duration=0.02)
    env.reset(seed=0)
    env.step(np.zeros(3, dtype=np.float32))
    frames = env.render()
    assert len(frames) == 2 and frames[0].ndim == 3


@pytest.mark.parametrize("mode", [np.array([1.0, 2.0]), np.array(["NextStep"]), 1, None, 2.5])
def test_a_junk_autoreset_mode_is_a_clear_error(mode):
    # before: np.array([1., 2.]) raised "truth value of an array ... is ambiguous" inside vector.py
    with pytest.raises(ValueError, match="autoreset_mode must be"):
        gym.make_vec("PlanarBLF-v0", num_envs=2, autoreset_mode=mode)


def test_a_huge_num_envs_is_refused_before_any_allocation():
    # before: OverflowError from numpy inside core.py
    with pytest.raises(ValueError, match=r"num_envs must be an integer in \[1, 65536\]") as exc:
        gym.make_vec("PlanarBLF-v0", num_envs=10 ** 400)
    assert len(str(exc.value)) < 400  # the 401 digits are not repeated back
    with pytest.raises(ValueError, match="num_envs"):
        EnvCore(MAX_ARMS + 1)
    # within MAX_ARMS, the reward's reference may still be too large: said in GiB, with the way out
    with pytest.raises(ValueError, match=r"GiB for the reward's reference.*reward_weights=\{\}"):
        EnvCore(60_000)


@pytest.mark.parametrize("duration", [1e6, MAX_DURATION * 1.001])
def test_a_very_long_episode_is_refused_with_its_reason(duration):
    # before: duration=1e6 failed at construction with MemoryError: Unable to allocate 22.4 GiB
    with pytest.raises(ValueError, match=r"duration must be .* 3600\] s \(blf_gym.model.params.MAX_DURATION"):
        gym.make("PlanarBLF-v0", duration=duration)
    with pytest.raises(ValueError, match="SimParams.duration"):
        SimParams(duration=duration)
    assert SimParams(duration=MAX_DURATION).n_samples == 3_600_000


@pytest.mark.parametrize("period", [0.01, 0.002, 0.005, 0.0005])
def test_a_float32_control_period_is_the_number_it_prints_as(period):
    # before: np.float32(0.01) read as 0.009999999776, no whole multiple of 1 ms, and was refused
    a = PlanarBLFEnv(control_period=np.float32(period), dt=np.float32(1e-4), duration=0.02)
    b = PlanarBLFEnv(control_period=period, dt=1e-4, duration=0.02)
    assert a.core.control_period == period and a.core.sim.dt == 1e-4
    oa, _ = a.reset(seed=3)
    ob, _ = b.reset(seed=3)
    np.testing.assert_array_equal(oa, ob)
    act = np.full(3, 0.01, dtype=np.float32)
    for _ in range(2):
        ra = a.step(act)
        rb = b.step(act)
        np.testing.assert_array_equal(ra[0], rb[0])
        assert ra[1:4] == rb[1:4]
        if ra[2] or ra[3]:
            break
    # float32 rounding of something that is no multiple stays refused
    with pytest.raises(ValueError, match="control_period"):
        PlanarBLFEnv(control_period=np.float32(0.0105))


def test_the_sb3_adapter_needs_the_mode_said():
    # before: BLFVecEnv(8, scenario=...) without controller= silently built the plain env
    from agents.vec_env import BLFVecEnv

    with pytest.raises(ValueError, match="give controller= explicitly"):
        BLFVecEnv(2, scenario="paper-0.1hz", duration=0.02)
    assert not BLFVecEnv(2, controller=None, duration=0.02).venv.core.residual
    assert BLFVecEnv(2, controller="proposed", duration=0.02).venv.core.residual


def test_gym_make_warns_when_torch_competes_with_the_env():
    # before: only the native vector env warned; through gym.make, SB3's PPO fell from 1,255-1,619
    # to 43-280 steps/s under load with torch's default threads, without a word. A fresh process,
    # since the warning is given once per process.
    code = ("import os, warnings, torch; torch.set_num_threads(os.cpu_count() or 1)\n"
            "import gymnasium as gym, blf_gym\n"
            "with warnings.catch_warnings(record=True) as w:\n"
            "    warnings.simplefilter('always')\n"
            "    gym.make('PlanarBLFResidual-v0', duration=0.02)\n"
            "print('|'.join(str(x.message) for x in w))\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr
    assert "PlanarBLFEnv: torch uses" in out.stdout and "torch.set_num_threads(" in out.stdout
    # torch on one thread is quiet, whatever the env's threads (nothing more to give up)
    code_quiet = code.replace("torch.set_num_threads(os.cpu_count() or 1)", "torch.set_num_threads(1)").replace(
        "duration=0.02)", "duration=0.02, threads=os.cpu_count() or 1)")
    out = subprocess.run([sys.executable, "-c", code_quiet], capture_output=True, text=True, timeout=300)
    assert out.returncode == 0 and "torch uses" not in out.stdout


def test_the_env_docstring_states_the_defaults_the_code_has():
    # before: it said the default reward was the shaped one and that there was no max_episode_steps
    from dataclasses import fields

    from blf_gym.kernel.reward import SCORE_REWARD

    doc = PlanarBLFEnv.__doc__
    for f in fields(SCORE_REWARD):
        assert f"``{f.name}={getattr(SCORE_REWARD, f.name)!r}``" in doc
    assert "no\n      ``max_episode_steps``" not in doc and "no ``max_episode_steps``" not in doc
    env = gym.make("PlanarBLF-v0")
    assert f"({env.spec.max_episode_steps} with the defaults)" in " ".join(doc.split())
    assert env.unwrapped.core.weights == SCORE_REWARD
