"""Safety-Gymnasium's step API for PlanarBLF: the cost as a return value of its own.

Safety-Gymnasium (and OmniSafe, which trains on it) returns six values from ``step``::

    obs, reward, cost, terminated, truncated, info = env.step(action)

Safety-Gymnasium 1.0.0 pins ``gymnasium==0.28.1`` and OmniSafe 0.5.0 requires it, so neither
installs beside the Gymnasium 1.x this package is built on; this wrapper follows that convention
without importing either. ``reset`` is unchanged, ``(obs, info)``.

>>> import gymnasium as gym
>>> import blf_gym
>>> env = blf_gym.SafetyGymnasiumWrapper(gym.make("PlanarBLF-v0", terminate_on_violation=False))  # doctest: +SKIP
>>> obs, info = env.reset(seed=0)                                                               # doctest: +SKIP
>>> obs, reward, cost, terminated, truncated, info = env.step(env.action_space.sample())         # doctest: +SKIP

A vector env (``gym.make_vec("PlanarBLF-v0", num_envs=N)``, PlanarBLF's own, or Gymnasium's sync
and async ones) is wrapped the same way: ``SafetyGymnasiumWrapper(venv)`` gives a vector wrapper
whose ``step`` returns the cost as a float64 array of shape (N,), 0 for an arm whose step was an
autoreset (Gymnasium's next-step mode), as Safety-Gymnasium's vector envs do.

The cost is PlanarBLF's ``info["cost"]``: 1.0 on a control step in which some integration step
broke a bound, else 0.0; summed over an episode it counts the violating control steps, the unit
of a cost limit. Safety-Gymnasium's episodes do not end on a cost, so the wrapper is meant for
``terminate_on_violation=False``; with the default (True) the episode ends on its first costly
step, which then has cost 1.0. The info is passed through with ``"cost"`` still in it.
"""

from __future__ import annotations

from typing import Any

import gymnasium as gym

import numpy as np

__all__ = ["SafetyGymnasiumWrapper", "SafetyGymnasiumVectorWrapper"]


def _missing(info: dict[str, Any]) -> ValueError:
    return ValueError("SafetyGymnasiumWrapper: the wrapped env's info has no 'cost' entry (keys: "
                      f"{sorted(info)}); it needs an env that reports a per-step cost, such as PlanarBLF-v0")


class SafetyGymnasiumWrapper(gym.Wrapper):
    """Wrap a Gymnasium env whose ``info`` carries a per-step ``"cost"`` so that ``step`` returns
    ``(obs, reward, cost, terminated, truncated, info)``, Safety-Gymnasium's API (module
    docstring). ``cost`` is a Python float; spaces, ``reset``, ``render`` and ``close`` are the
    wrapped env's. A step whose info has no ``"cost"`` raises ``ValueError``."""

    def __new__(cls, env: Any, *args: Any, **kwargs: Any) -> Any:
        if isinstance(env, gym.vector.VectorEnv):  # a vector env gets the vector wrapper
            return SafetyGymnasiumVectorWrapper(env)
        return super().__new__(cls)

    def step(self, action: Any) -> tuple[Any, float, float, bool, bool, dict[str, Any]]:
        obs, reward, terminated, truncated, info = self.env.step(action)
        if "cost" not in info:
            raise _missing(info)
        return obs, reward, float(info["cost"]), terminated, truncated, info


class SafetyGymnasiumVectorWrapper(gym.vector.VectorWrapper):
    """The six-value step of :class:`SafetyGymnasiumWrapper` for a vector env:
    ``(obs, rewards, costs, terminations, truncations, infos)``, ``costs`` a float64 array (N,) with 0
    where an arm's step was an autoreset (its ``info["_cost"]`` mask is False)."""

    def reset(self, **kwargs: Any) -> tuple[Any, dict[str, Any]]:
        self._resetting = np.zeros(self.num_envs, dtype=bool)
        return self.env.reset(**kwargs)

    def step(self, actions: Any) -> tuple[Any, Any, np.ndarray, Any, Any, dict[str, Any]]:
        obs, rewards, terminations, truncations, infos = self.env.step(actions)
        resetting = getattr(self, "_resetting", np.zeros(self.num_envs, dtype=bool))
        self._resetting = np.asarray(terminations, dtype=bool) | np.asarray(truncations, dtype=bool)
        if "cost" not in infos:
            if resetting.all():  # every arm autoreset: Gymnasium's sync env then has reset infos only
                return obs, rewards, np.zeros(self.num_envs), terminations, truncations, infos
            raise _missing(infos)
        costs = np.asarray(infos["cost"], dtype=np.float64).copy()
        mask = infos.get("_cost")
        if mask is not None:
            costs[~np.asarray(mask, dtype=bool)] = 0.0
        costs[resetting] = 0.0
        return obs, rewards, costs, terminations, truncations, infos
