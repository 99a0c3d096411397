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

The cost is PlanarBLF's ``info["cost"]``: 1.0 on a control step in which some integration step
broke a bound, else 0.0; summed over an episode it counts the violating control steps, the unit
of a cost limit. Safety-Gymnasium's episodes do not end on a cost, so the wrapper is meant for
``terminate_on_violation=False``; with the default (True) the episode ends on its first costly
step, which then has cost 1.0. The info is passed through with ``"cost"`` still in it.
"""

from __future__ import annotations

from typing import Any

import gymnasium as gym

__all__ = ["SafetyGymnasiumWrapper"]


class SafetyGymnasiumWrapper(gym.Wrapper):
    """Wrap a Gymnasium env whose ``info`` carries a per-step ``"cost"`` so that ``step`` returns
    ``(obs, reward, cost, terminated, truncated, info)``, Safety-Gymnasium's API (module
    docstring). ``cost`` is a Python float; spaces, ``reset``, ``render`` and ``close`` are the
    wrapped env's. A step whose info has no ``"cost"`` raises ``ValueError``."""

    def step(self, action: Any) -> tuple[Any, float, float, bool, bool, dict[str, Any]]:
        obs, reward, terminated, truncated, info = self.env.step(action)
        if "cost" not in info:
            raise ValueError("SafetyGymnasiumWrapper: the wrapped env's info has no 'cost' entry (keys: "
                             f"{sorted(info)}); it needs an env that reports a per-step cost, such as "
                             "PlanarBLF-v0")
        return obs, reward, float(info["cost"]), terminated, truncated, info
