"""``PlanarBLFVectorEnv``: N arms in one compiled kernel call (``gym.make_vec``'s vector entry point).

The arms are independent episodes of :class:`~blf_gym.envs.env.PlanarBLFEnv`, computed by the same
:class:`~blf_gym.envs.envcore.EnvCore` and the same kernel, split over threads. Arm i reset with seed
``s + i`` is bit-identical to a single env reset with that seed.

Autoreset follows Gymnasium's modes (``autoreset_mode``, default ``AutoresetMode.NEXT_STEP``, as
in Gymnasium's own sync and async vector envs, so its vector wrappers accept it):

* ``NEXT_STEP``: the step on which an arm ends returns its last observation and info; the next
  step resets that arm (its action is ignored) and returns the first observation of the new
  episode with reward 0, ``terminated`` and ``truncated`` False, and the reset's info entries.
* ``SAME_STEP`` (on request; the SB3 adapter uses it): an arm that ends is reset in the same step;
  ``infos["final_obs"]`` and ``infos["final_info"]`` hold its last observation and info, and the
  returned observation is already the first of its next episode.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from gymnasium import spaces
from gymnasium.utils import seeding
from gymnasium.vector import AutoresetMode, VectorEnv
from gymnasium.vector.utils import batch_space

from blf_gym.envs.envcore import CORE_BOUND_SCALE, EnvCore, check_env_kwargs, warn_if_oversubscribed
from blf_gym.model.params import check_int, is_integer

__all__ = ["PlanarBLFVectorEnv", "default_threads", "make_residual_vector_env"]


def _with_masks(info: dict[str, Any], mask: np.ndarray) -> dict[str, Any]:
    """Gymnasium's vector-info convention: each key's per-arm array plus a ``_key`` mask."""
    out: dict[str, Any] = {}
    for k, v in info.items():
        out[k] = _with_masks(v, mask) if isinstance(v, dict) else v
        out[f"_{k}"] = mask.copy()
    return out


def default_threads(num_envs: int) -> int:
    """The vector env's default numba threads: half the cores (at least 1, at most one per arm),
    so that the learner beside it (torch, which takes every core by default) keeps the rest."""
    from blf_gym.model.params import usable_cores

    return max(1, min(num_envs, usable_cores() // 2))


class PlanarBLFVectorEnv(VectorEnv):
    """Batched ``PlanarBLF-v0``; keyword arguments are those of :class:`~blf_gym.envs.env.PlanarBLFEnv`
    plus ``num_envs``, ``autoreset_mode`` (see the module doc) and ``threads`` (default
    :func:`default_threads`: half the cores, so a learner beside the env is not starved)."""

    metadata = {"autoreset_mode": AutoresetMode.NEXT_STEP, "render_modes": []}

    def __init__(self, num_envs: int = 1, render_mode: str | None = None,
                 autoreset_mode: AutoresetMode | str = AutoresetMode.NEXT_STEP, **kwargs: Any) -> None:
        if render_mode is not None:
            raise ValueError("PlanarBLFVectorEnv: render_mode must be None (the vector env does not "
                             f"render; use the single env for pictures), got {render_mode!r}")
        modes = (AutoresetMode.NEXT_STEP, AutoresetMode.SAME_STEP)
        mode = autoreset_mode
        if isinstance(mode, str) and not isinstance(mode, AutoresetMode):
            mode = next((m for m in modes if mode in (m.value, m.name)), mode)
        if not isinstance(mode, AutoresetMode) or mode not in modes:  # (an array has no truth value)
            raise ValueError("PlanarBLFVectorEnv: autoreset_mode must be AutoresetMode.NEXT_STEP or "
                             f"AutoresetMode.SAME_STEP (or 'NextStep', 'SameStep'), got {autoreset_mode!r}")
        self.autoreset_mode = mode
        self.metadata = {**self.metadata, "autoreset_mode": mode}
        check_env_kwargs(kwargs)
        if kwargs.get("threads") is None and is_integer(num_envs) and num_envs >= 1:
            kwargs["threads"] = default_threads(int(num_envs))
        self.core = EnvCore(num_envs, **kwargs)
        warn_if_oversubscribed(self.core.loop.threads, "PlanarBLFVectorEnv")
        self.num_envs = self.core.num_envs
        n = self.core.n
        self.single_action_space = spaces.Box(-1.0, 1.0, (n,), dtype=np.float32)
        self.single_observation_space = spaces.Box(self.core.obs_low, self.core.obs_high, dtype=np.float32)
        self.action_space = batch_space(self.single_action_space, self.num_envs)
        self.observation_space = batch_space(self.single_observation_space, self.num_envs)
        self.render_mode = None
        self._started = False
        self._autoreset = np.zeros(self.num_envs, dtype=bool)
        self._spec = None

    @property
    def spec(self):
        """The EnvSpec ``gym.make_vec`` sets, with ``max_episode_steps`` filled in: every arm's
        episode length in agent steps (``duration / control_period``)."""
        return self._spec

    @spec.setter
    def spec(self, value) -> None:
        self._spec = self.core.with_episode_length(value)

    bound_scale = CORE_BOUND_SCALE

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
        self._autoreset[:] = False
        self.core.reset_envs(range(N), options)
        info: dict[str, Any] = {}
        obs = self.core.observe(info)
        return obs, _with_masks(info, np.ones(N, dtype=bool))

    def step(self, actions):
        if not self._started:
            raise RuntimeError("call reset() before step()")
        if self.autoreset_mode is AutoresetMode.NEXT_STEP:
            return self._step_next(actions)
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

    def _step_next(self, actions):
        """Next-step autoreset: the arms that ended on the previous step are reset now instead of
        stepped (the kernel still advances them, drawing no noise, and their rows are replaced)."""
        pending = self._autoreset
        obs, rew, term, trunc, info = self.core.step(actions, skip=pending if pending.any() else None)
        live = ~pending
        out = _with_masks(info, live)
        if pending.any():
            idx = [int(i) for i in np.flatnonzero(pending)]
            self.core.reset_envs(idx)
            rinfo: dict[str, Any] = {}
            new_obs = self.core.observe(rinfo, which=idx)
            obs[pending] = new_obs[pending]
            rew = np.where(pending, 0.0, rew)
            term = term & live
            trunc = trunc & live
            for k, v in rinfo.items():  # the reset's entries for the reset arms
                if k in out:
                    out[k] = np.where(pending.reshape((-1,) + (1,) * (np.ndim(v) - 1)), v, out[k])
                else:
                    out[k] = v
                out[f"_{k}"] = out.get(f"_{k}", np.zeros(self.num_envs, dtype=bool)) | pending
        self._autoreset = term | trunc
        return obs, rew, term, trunc, out


def make_residual_vector_env(num_envs: int = 1, **kwargs: Any) -> PlanarBLFVectorEnv:
    """``PlanarBLFResidual-v0``'s vector entry point: :class:`PlanarBLFVectorEnv`, refusing a
    controller that would make it plain (:func:`blf_gym.envs.env.check_residual_controller`)."""
    from blf_gym.envs.env import check_residual_controller

    check_residual_controller("PlanarBLFResidual-v0", kwargs)
    return PlanarBLFVectorEnv(num_envs=num_envs, **kwargs)
