"""The Safety-Gymnasium six-value step for the native vector env and Gymnasium's sync vector env:
each arm's cost is the cost its single env gives (the vector env matches single envs with seeds
s + i), and 0 on an autoreset step."""

from __future__ import annotations

import gymnasium as gym
import numpy as np

import blf_gym
from blf_gym.envs.safety import SafetyGymnasiumVectorWrapper

KW = dict(duration=0.05, terminate_on_violation=False)


def _single_costs(seed: int, steps: int, action: np.ndarray) -> list[float]:
    env = blf_gym.SafetyGymnasiumWrapper(gym.make("PlanarBLF-v0", **KW))
    env.reset(seed=seed)
    out = []
    for _ in range(steps):
        _, _, cost, term, trunc, _ = env.step(action)
        out.append(cost)
        if term or trunc:
            break
    return out


def _vector_costs(venv, steps: int, action: np.ndarray) -> np.ndarray:
    env = blf_gym.SafetyGymnasiumWrapper(venv)
    assert isinstance(env, SafetyGymnasiumVectorWrapper)
    env.reset(seed=0)
    rows = []
    for _ in range(steps):
        obs, rew, costs, term, trunc, info = env.step(np.tile(action, (2, 1)))
        assert costs.dtype == np.float64 and costs.shape == (2,)
        rows.append(costs)
    return np.array(rows)


def test_the_vector_wrapper_gives_each_arm_its_single_envs_cost_and_zero_on_autoreset():
    action = np.full(3, -0.2, dtype=np.float32)  # a constant torque: the arm leaves its funnel in 20 ms
    singles = [_single_costs(s, 5, action) for s in (0, 1)]
    assert all(len(c) == 5 for c in singles) and sum(map(sum, singles)) > 0  # there is a cost to carry
    for venv in (gym.make_vec("PlanarBLF-v0", num_envs=2, **KW),
                 gym.make_vec("PlanarBLF-v0", num_envs=2, vectorization_mode="sync", **KW)):
        got = _vector_costs(venv, 8, action)
        np.testing.assert_array_equal(got[:5].T, np.array(singles))
        np.testing.assert_array_equal(got[5], 0.0)  # the step after truncation is an autoreset
        np.testing.assert_array_equal(got[6:].T, np.array(singles)[:, :2])  # the new episode counts again


def test_a_vector_env_without_a_cost_is_refused_by_name():
    env = blf_gym.SafetyGymnasiumWrapper(gym.make_vec("Pendulum-v1", num_envs=2, vectorization_mode="sync"))
    env.reset(seed=0)
    try:
        env.step(np.zeros((2, 1), dtype=np.float32))
    except ValueError as e:
        assert "no 'cost' entry" in str(e)
    else:  # pragma: no cover
        raise AssertionError("a vector env without info['cost'] was accepted")
