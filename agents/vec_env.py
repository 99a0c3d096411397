"""An SB3 ``VecEnv`` over blf_gym's native vector env: N arms in one compiled call.

SB3 expects same-step resets with the last observation of an ended episode in
``infos[i]["terminal_observation"]`` and ``infos[i]["TimeLimit.truncated"]`` for truncations;
this adapter provides exactly that on top of :class:`blf_gym.envs.vector.PlanarBLFVectorEnv`.

>>> from agents.vec_env import BLFVecEnv
>>> venv = BLFVecEnv(8, controller="proposed", seed=0)   # doctest: +SKIP
>>> model = stable_baselines3.SAC("MlpPolicy", venv)     # doctest: +SKIP
"""

from __future__ import annotations

from collections.abc import MutableMapping
from typing import Any, Iterable, Sequence

import numpy as np
from gymnasium.vector import AutoresetMode
from stable_baselines3.common.vec_env.base_vec_env import VecEnv

from blf_gym.envs.vector import PlanarBLFVectorEnv

__all__ = ["ArmInfo", "BLFVecEnv"]


def _value(v: Any, i: int) -> Any:
    """Arm i's entry of a batched info value, as a single env gives it (a Python scalar, an array
    row, or a dict of them)."""
    if isinstance(v, dict):
        return _row(v, i)
    x = v[i]
    return x.item() if isinstance(x, np.generic) else x


def _skip(k: str) -> bool:
    return k.startswith("_") or k in ("final_obs", "final_info")


def _row(info: dict[str, Any], i: int) -> dict[str, Any]:
    return {k: _value(v, i) for k, v in info.items() if not _skip(k)}


class ArmInfo(MutableMapping):
    """One arm's ``info`` in the list SB3 receives, read from the batched info on demand.

    SB3 reads a few keys per step (``terminal_observation``, ``TimeLimit.truncated``, ``episode``,
    a callback's ``cost``); building every arm's whole dict at every step took a third of the
    adapter's time. Each value is converted once, when first read, exactly as a plain dict row
    would hold it; keys written (VecMonitor's ``episode``, VecNormalize's normalized terminal
    observation) are kept beside. ``copy()`` and ``dict(info)`` give a plain dict."""

    __slots__ = ("_batch", "_i", "_own")

    def __init__(self, batch: dict[str, Any], i: int, own: dict[str, Any] | None = None) -> None:
        self._batch = batch
        self._i = i
        self._own: dict[str, Any] = {} if own is None else own

    def __getitem__(self, key: str) -> Any:
        own = self._own
        if key in own:
            return own[key]
        if _skip(key) or key not in self._batch:
            raise KeyError(key)
        v = own[key] = _value(self._batch[key], self._i)
        return v

    def __setitem__(self, key: str, value: Any) -> None:
        self._own[key] = value

    def __delitem__(self, key: str) -> None:
        if key not in self:
            raise KeyError(key)
        self._materialize()
        del self._own[key]
        self._batch = {}

    def _materialize(self) -> None:
        for k in self:
            self[k]

    def __iter__(self):
        seen = set()
        for k in self._batch:
            if not _skip(k):
                seen.add(k)
                yield k
        for k in list(self._own):
            if k not in seen:
                yield k

    def __len__(self) -> int:
        return sum(1 for _ in self)

    def __contains__(self, key: object) -> bool:
        return key in self._own or (isinstance(key, str) and not _skip(key) and key in self._batch)

    def copy(self) -> dict[str, Any]:
        return dict(self)

    def __repr__(self) -> str:
        return repr(dict(self))


_REQUIRED = object()


class BLFVecEnv(VecEnv):
    """SB3 vectorized env of ``num_envs`` PlanarBLF arms; kwargs are PlanarBLFEnv's.

    ``controller`` is required, so the mode is always explicit: ``None`` for plain mode (the
    action is the whole torque, as ``PlanarBLF-v0``), or a law (``"proposed"``, ``"lesobc"``,
    ``"bc"``, a registered plug-in) for residual mode (as ``PlanarBLFResidual-v0``). Before, leaving
    it out silently built the plain env."""

    def __init__(self, num_envs: int, seed: int | None = None, *, controller: Any = _REQUIRED,
                 **env_kwargs: Any) -> None:
        if controller is _REQUIRED:
            raise ValueError("BLFVecEnv: give controller= explicitly: None for plain mode (the action is the "
                             "whole torque) or a law such as 'proposed' for residual mode (the action is a "
                             "residual over it)")
        env_kwargs["controller"] = controller
        self.venv = PlanarBLFVectorEnv(num_envs=num_envs, autoreset_mode=AutoresetMode.SAME_STEP, **env_kwargs)
        super().__init__(num_envs, self.venv.single_observation_space, self.venv.single_action_space)
        self._seed = seed
        self._actions: np.ndarray | None = None
        self.render_mode = None

    # --- core API
    def reset(self) -> np.ndarray:
        obs, _ = self.venv.reset(seed=self._seed)
        self._seed = None  # later resets continue the streams
        self.reset_infos = [{} for _ in range(self.num_envs)]
        return obs

    def step_async(self, actions: np.ndarray) -> None:
        self._actions = np.asarray(actions)

    def step_wait(self):
        obs, rew, term, trunc, info = self.venv.step(self._actions)
        dones = term | trunc
        infos: list[ArmInfo] = []
        for i in range(self.num_envs):
            if dones[i]:
                row = ArmInfo(info["final_info"], i, {"terminal_observation": info["final_obs"][i],
                                                      "TimeLimit.truncated": bool(trunc[i] and not term[i])})
            else:
                row = ArmInfo(info, i)
            infos.append(row)
        return obs, rew.astype(np.float32), dones, infos

    def seed(self, seed: int | None = None) -> Sequence[None | int]:
        self._seed = seed
        return [None if seed is None else seed + i for i in range(self.num_envs)]

    def close(self) -> None:
        self.venv.close()

    # --- attribute access (there are no per-arm env objects)
    def get_attr(self, attr_name: str, indices: Any = None) -> list[Any]:
        return [getattr(self.venv, attr_name) for _ in self._get_indices(indices)]

    def set_attr(self, attr_name: str, value: Any, indices: Any = None) -> None:
        setattr(self.venv, attr_name, value)

    def env_method(self, method_name: str, *method_args: Any, indices: Any = None, **method_kwargs: Any) -> list[Any]:
        fn = getattr(self.venv, method_name)
        return [fn(*method_args, **method_kwargs) for _ in self._get_indices(indices)]

    def env_is_wrapped(self, wrapper_class: type, indices: Any = None) -> list[bool]:
        return [False for _ in self._get_indices(indices)]

    def get_images(self) -> Sequence[np.ndarray | None]:
        return [None for _ in range(self.num_envs)]

    def _get_indices(self, indices: Any) -> Iterable[int]:
        if indices is None:
            return range(self.num_envs)
        if isinstance(indices, int):
            return [indices]
        return indices
