"""The one loader of a trained agent: model, observation normalization, metadata and env kwargs.

Everything that scores or runs a ``blf-train`` agent (``blf-eval``, the learning-curve callback's
consumers, the notebooks, ``agents.report``) loads it here, so every check is made once:

* ``metadata.json`` must be readable JSON with the algorithm, mode and env kwargs;
* an agent trained with observation normalization (``config.normalize`` in its metadata) must
  have its ``vecnormalize.pkl``: scored without it, its RMSE is several times worse, silently;
* the statistics must be readable and match the model's observation size.

Each problem raises ``ValueError`` naming the file.
"""

from __future__ import annotations

import json
import pickle
from pathlib import Path
from typing import Any

__all__ = ["algorithm_class", "available_algorithms", "load_agent", "load_pretrained", "pretrained_agents"]

PRETRAINED = Path(__file__).resolve().parent / "pretrained"


def available_algorithms() -> list[str]:
    """Training algorithms registered in the ``blf_gym.algorithms`` entry-point group."""
    from importlib.metadata import entry_points

    return sorted(ep.name for ep in entry_points(group="blf_gym.algorithms"))


def algorithm_class(name: str):
    """The class (SB3-style: learn, save, load, predict) registered as ``name`` in the
    ``blf_gym.algorithms`` entry-point group. A new algorithm is one registration there."""
    from importlib.metadata import entry_points

    eps = {ep.name: ep for ep in entry_points(group="blf_gym.algorithms")}
    if name not in eps:
        raise ValueError(f"unknown algorithm {name!r}; accepted values: {sorted(eps)} (registered in the "
                         "blf_gym.algorithms entry-point group; reinstall the project if this list is empty)")
    try:
        return eps[name].load()
    except ImportError as exc:
        raise ValueError(f"algorithm {name!r} is registered as {eps[name].value} but cannot be imported ({exc}); "
                         f"install the package that provides it (tqc: pip install sb3-contrib)") from exc


def read_json_object(path: Path, what: str, hint: str = "") -> dict[str, Any]:
    """A JSON object from ``path``; ValueError naming the file if it is unreadable or not an object."""
    try:
        obj = json.loads(Path(path).read_text())
    except (OSError, ValueError) as exc:
        raise ValueError(f"{path}: not readable as JSON ({exc}); it should hold {what}{hint}") from None
    if not isinstance(obj, dict):
        raise ValueError(f"{path}: not a JSON object; it should hold {what}{hint}")
    return obj


def _metadata(meta_path: Path, model_path: Path) -> dict[str, Any]:
    if not meta_path.is_file():
        raise ValueError(f"{model_path}: no metadata.json beside the model; was it written by blf-train?")
    meta = read_json_object(meta_path, "the run's metadata")
    for key in ("algo", "mode", "env_kwargs"):
        if key not in meta:
            raise ValueError(f"{meta_path}: the metadata lacks {key!r}")
    return meta


def load_agent(path: str | Path) -> tuple[Any, dict[str, Any], Any]:
    """(SB3 model, metadata, VecNormalize statistics or None) from a ``blf-train`` run folder or its
    model zip. The env kwargs the agent was trained with are ``metadata["env_kwargs"]``."""
    path = Path(path)
    if path.is_dir():
        if not (path / "model.zip").is_file():
            raise ValueError(f"{path}: no model.zip in this folder; give a blf-train run folder or its model zip")
        path = path / "model.zip"
    if not path.is_file():
        raise ValueError(f"agent model not found: {path}")
    meta = _metadata(path.with_name("metadata.json"), path)
    cls = algorithm_class(meta["algo"])
    try:
        model = cls.load(path, device="cpu")
    except Exception as exc:  # SB3 raises several types for a corrupt or foreign zip
        raise ValueError(f"{path}: cannot be loaded as a {meta['algo'].upper()} model ({exc})") from exc
    stats = path.with_name("vecnormalize.pkl")
    config = meta.get("config") if isinstance(meta.get("config"), dict) else None
    normalized = bool(config.get("normalize")) if config is not None else stats.is_file()
    norm = None
    if normalized:
        if not stats.is_file():
            raise ValueError(f"{stats}: missing. The agent was trained with observation normalization "
                             f"(metadata config.normalize), and scored without its statistics its numbers "
                             "mean nothing; restore the file or retrain")
        try:
            with open(stats, "rb") as f:
                norm = pickle.load(f)
            obs_shape = tuple(norm.obs_rms.mean.shape)
        except Exception as exc:  # a truncated or foreign pickle
            raise ValueError(f"{stats}: not readable as the agent's normalization statistics "
                             f"({type(exc).__name__}: {exc})") from None
        if obs_shape != tuple(model.observation_space.shape):
            raise ValueError(f"{stats}: statistics for observations of shape {obs_shape}, but the model in {path} "
                             f"takes {tuple(model.observation_space.shape)}")
    return model, meta, norm


def pretrained_agents() -> list[str]:
    """Names of the agents shipped in ``agents/pretrained/``."""
    return sorted(p.name for p in PRETRAINED.iterdir() if (p / "model.zip").is_file())


def load_pretrained(name: str | Path, scenario: str | None = None, reward: str = "score", **env_kwargs: Any):
    """A shipped agent (or any blf-train run folder) and an env it can act in, as SB3 expects them.

    Returns ``(model, env)``: the model loaded by :func:`load_agent`, and a one-arm SB3 ``VecEnv``
    (``DummyVecEnv`` of ``gym.make`` with a ``Monitor``) built with the env kwargs the agent was
    trained with (its residual scale, control period, observation and filter included), wrapped in
    the agent's ``VecNormalize`` statistics (frozen: ``training=False``, rewards not normalized) when
    it has them. So ``stable_baselines3.common.evaluation.evaluate_policy(model, env)`` runs the agent
    exactly as ``blf-eval`` does.

    ``scenario`` replaces the training scenario (e.g. ``"paper-0.1hz"``); ``env_kwargs`` replace
    others. Episodes run their whole duration (``terminate_on_violation=False``), as in blf-eval.
    ``reward="score"`` (default) gives the env's default reward, whose episode return is the
    episode's log score_vs_law; ``reward="training"`` the reward the agent was trained with (an
    agent whose metadata names none was trained before the default changed, with the shaped reward
    of ``RewardWeights()``).
    """
    import gymnasium as gym
    from stable_baselines3.common.monitor import Monitor
    from stable_baselines3.common.vec_env import DummyVecEnv

    import blf_gym  # noqa: F401 - registers the ids

    path = Path(name)
    if not path.is_dir():
        path = PRETRAINED / str(name)
    if not path.is_dir():
        raise ValueError(f"unknown pretrained agent {str(name)!r}; shipped: {pretrained_agents()} (or give a "
                         "blf-train run folder)")
    if reward not in ("score", "training"):
        raise ValueError(f"reward must be 'score' or 'training', got {reward!r}")
    model, meta, norm = load_agent(path)
    kw = dict(meta["env_kwargs"])
    kw.pop("threads", None)
    if reward == "score":
        kw.pop("reward_weights", None)
    else:
        kw.setdefault("reward_weights", {})
    kw["terminate_on_violation"] = False
    if scenario is not None:
        kw["scenario"] = scenario
    kw.update(env_kwargs)
    from .train import ENV_IDS

    env_id = meta.get("env_id") or ENV_IDS[meta["mode"]]
    venv = DummyVecEnv([lambda: Monitor(gym.make(env_id, **kw))])
    if norm is None:
        return model, venv
    norm.set_venv(venv)
    norm.training = False
    norm.norm_reward = False
    return model, norm
