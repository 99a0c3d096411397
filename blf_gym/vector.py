"""``PlanarBLFVectorEnv``: N arms in one compiled kernel call (``gym.make_vec``'s vector entry point).

The arms are independent episodes of :class:`~blf_gym.env.PlanarBLFEnv`, computed by the same
:class:`~blf_gym.core.EnvCore` and the same kernel, split over threads. Arm i reset with seed
``s + i`` is bit-identical to a single env reset with that seed. Autoreset is same-step: when an
arm ends, ``infos["final_obs"]`` and ``infos["final_info"]`` hold its last observation and info,
and the returned observation is already the first of its next episode.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from gymnasium import spaces
from gymnasium.utils import seeding
from gymnasium.vector import AutoresetMode, VectorEnv
from gymnasium.vector.utils import batch_space

from .core import EnvCore, check_env_kwargs
from .params import check_int, is_integer

__all__ = ["PlanarBLFVectorEnv"]


def _with_masks(info: dict[str, Any], mask: np.ndarray) -> dict[str, Any]:
    """Gymnasium's vector-info convention: each key's per-arm array plus a ``_key`` mask."""
    out: dict[str, Any] = {}
    for k, v in info.items():
        out[k] = _with_masks(v, mask) if isinstance(v, dict) else v
        out[f"_{k}"] = mask.copy()
    return out


class PlanarBLFVectorEnv(VectorEnv):
    """Batched ``PlanarBLF-v0``; keyword arguments are those of :class:`~blf_gym.env.PlanarBLFEnv`
    plus ``num_envs`` and ``threads`` (default: the number of CPUs)."""

    metadata = {"autoreset_mode": AutoresetMode.SAME_STEP, "render_modes": []}

    def __init__(self, num_envs: int = 1, render_mode: str | None = None, **kwargs: Any) -> None:
        if render_mode is not None:
            raise ValueError("PlanarBLFVectorEnv: render_mode must be None (the vector env does not "
                             f"render; use the single env for pictures), got {render_mode!r}")
        check_env_kwargs(kwargs)
        self.core = EnvCore(num_envs, **kwargs)
        self.num_envs = self.core.num_envs
        n = self.core.n
        self.single_action_space = spaces.Box(-1.0, 1.0, (n,), dtype=np.float32)
        self.single_observation_space = spaces.Box(self.core.obs_low, self.core.obs_high, dtype=np.float32)
        self.action_space = batch_space(self.single_action_space, self.num_envs)
        self.observation_space = batch_space(self.single_observation_space, self.num_envs)
        self.render_mode = None
        self._started = False

    def reset(self, *, seed: int | list[int | None] | None = None, options: dict[str, Any] | None = None):
        """Reset every arm. ``seed`` s (an int or numpy integer >= 0) seeds arm i with s + i; or
        give a list of one seed per arm (each an integer >= 0, or None to continue its stream).
        Anything else, and bad ``options``, raise ValueError before any arm changes."""
        N = self.num_envs
        o = "PlanarBLFVectorEnv.reset:"
        accepted = (f"None, an integer >= 0 (arm i gets seed + i) or a list of {N} seeds (one per arm, "
                    "each an integer >= 0 or None)")
        if seed is None:
            seeds: list[int | None] = [None] * N
        elif is_integer(seed):  # int or numpy integer, never a bool
            s0 = check_int(o, "seed", seed, lo=0, hint=f" ({accepted})")
            seeds = [s0 + i for i in range(N)]
        elif isinstance(seed, (list, tuple)) or (isinstance(seed, np.ndarray) and seed.ndim == 1):
            if len(seed) != N:
                raise ValueError(f"{o} seed must be {accepted}, got {len(seed)} seeds: {seed!r}")
            seeds = [check_int(o, f"seed[{i}]", s, lo=0, none_ok=True) for i, s in enumerate(seed)]
        else:
            raise ValueError(f"{o} seed must be {accepted}, got {seed!r}")
        options = self.core.check_options(options)
        for i, s in enumerate(seeds):
            if s is not None or not self._started:
                self.core.rngs[i], _ = seeding.np_random(s)
        self._started = True
        self.core.reset_envs(range(N), options)
        info: dict[str, Any] = {}
        obs = self.core.observe(info)
        return obs, _with_masks(info, np.ones(N, dtype=bool))

    def step(self, actions):
        if not self._started:
            raise RuntimeError("call reset() before step()")
        obs, rew, term, trunc, info = self.core.step(actions)
        N = self.num_envs
        done_mask = term | trunc
        out = _with_masks(info, np.ones(N, dtype=bool))
        if done_mask.any():
            done = [int(i) for i in np.flatnonzero(done_mask)]
            final_obs = np.empty(N, dtype=object)
            for i in done:
                final_obs[i] = obs[i].copy()
            out["final_obs"] = final_obs
            out["_final_obs"] = done_mask.copy()
            out["final_info"] = _with_masks(info, done_mask)
            out["_final_info"] = done_mask.copy()
            self.core.reset_envs(done)
            new_obs = self.core.observe(None, which=done)
            obs[done_mask] = new_obs[done_mask]
        return obs, rew, term, trunc, out
