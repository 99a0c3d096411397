"""The env's arguments and info keys are declared once (blf_gym.envs.envcore.ARGUMENTS, INFO_KEYS); the
docstring and the documentation site's tables are made from them. These tests hold the
declarations to what the env really takes and returns, so the tables cannot drift."""

from __future__ import annotations

import inspect

import gymnasium as gym
import numpy as np

import blf_gym  # noqa: F401  (registers the ids)
from blf_gym.envs.env import PlanarBLFEnv, arguments_table, info_table, observation_table, reward_terms_table
from blf_gym.envs.envcore import ARGUMENTS, INFO_KEYS, EnvCore
from blf_gym.envs.observation import observation_layout
from blf_gym.kernel.reward import TERMS


def test_every_keyword_argument_of_the_env_is_declared_once_in_order():
    params = [p for p in inspect.signature(EnvCore.__init__).parameters if p not in ("self", "num_envs", "single")]
    assert [a.name for a in ARGUMENTS] == params


def _keys_seen(**kwargs) -> tuple[set, set, set]:
    """Keys at reset, keys on every step, keys on some step, over one short episode."""
    env = gym.make("PlanarBLF-v0", duration=0.05, **kwargs)
    _, info = env.reset(seed=0)
    at_reset = set(info)
    every, some = None, set()
    done = False
    while not done:
        _, _, term, trunc, info = env.step(np.full(3, 0.5, dtype=np.float32))
        every = set(info) if every is None else every & set(info)
        some |= set(info)
        done = term or trunc
    return at_reset, every, some


def test_the_info_keys_the_env_returns_are_the_declared_ones():
    declared = {k.name: k.when for k in INFO_KEYS}
    always = {k for k, w in declared.items() if w == "always"}
    step = {k for k, w in declared.items() if w == "step"}
    seen_any = set()
    for kwargs in ({}, {"controller": "proposed", "residual_filter": "barrier", "privileged": True}):
        at_reset, every, some = _keys_seen(**kwargs)
        assert always <= at_reset and always <= every
        assert at_reset - always == ({"scenario", "qd"} if kwargs else {"scenario"})
        assert step <= every, step - every
        seen_any |= at_reset | some
    # the optional keys each appear under their stated condition, and nothing undeclared appears
    assert {"filter_outputs", "qd", "episode_metrics"} <= seen_any
    assert seen_any <= set(declared), seen_any - set(declared)


def test_the_tables_are_made_from_the_declarations():
    args = arguments_table().splitlines()
    assert len(args) == 2 + len(ARGUMENTS)
    assert "| `control_period` | `0.01` | s |" in args[2 + [a.name for a in ARGUMENTS].index("control_period")]
    assert len(info_table().splitlines()) == 2 + len(INFO_KEYS)
    assert len(observation_table(False).splitlines()) == 2 + len(observation_layout(3, False)) == 2 + 31
    assert len(reward_terms_table().splitlines()) == 2 + len(TERMS)
    doc = PlanarBLFEnv.__doc__
    assert arguments_table("    ") in doc and info_table("    ") in doc and observation_table(True, "    ") in doc
