"""The one loader of a trained agent: model, observation normalization, metadata and env kwargs.

Everything that scores or runs a ``blf-train`` agent (``blf-eval``, the learning-curve callback's
consumers, the notebooks, ``agents.report``) loads it here, so the folder is checked once, as a
whole, before anything is scored:

* ``metadata.json`` must be readable JSON with the algorithm (a registered name), mode and env
  kwargs; ``name``, if given, a non-empty string;
* ``mode`` must be ``'plain'`` or ``'residual'`` and agree with ``env_kwargs.controller`` (absent,
  None or ``'none'``: plain; a law's name: residual) and with ``env_id`` when given
  (``PlanarBLF-v0`` plain, ``PlanarBLFResidual-v0`` residual);
* ``env_kwargs`` must be a JSON object whose keys the env accepts and whose values pass the env's
  own checks: the env blf-eval would score the agent in (:func:`scoring_env_kwargs`) is built, and
  anything it refuses is reported with the field it names;
* whether the agent was trained with observation normalization must be stated in the metadata
  (``config.normalize``, written by blf-train), and agree with ``vecnormalize.pkl``: stated true
  and the file missing, or stated false and the file present, is refused, and so is no statement
  at all (the file's presence alone is not evidence: scored without its statistics, an agent's
  RMSE is several times worse, silently);
* the model and the statistics must be the files the agent was saved with: ``metadata.json``'s
  ``files`` holds their sha256 (written by blf-train and agents.zoo), and a file that differs, is
  missing or is not listed is refused unless accepted knowingly (``accept_changed_files``); a folder
  written before the hashes existed loads with a one-line warning;
* the statistics must be readable, normalize observations, and match the model's observation size;
* the model's own observation and action spaces (saved in ``model.zip``) must be the env's: the
  same shape and the same Box bounds.

Each problem raises one ``ValueError`` of one line that starts with the file at fault
(``metadata.json``, ``model.zip`` or ``vecnormalize.pkl``) and names the field.
"""

from __future__ import annotations

import json
import pickle
import re
import warnings
from pathlib import Path
from typing import Any

__all__ = ["POLICY_PREFIX", "algorithm_class", "available_algorithms", "check_agent_folder", "load_agent",
           "load_policy", "load_pretrained", "pretrained_agents", "scoring_env_kwargs"]

PRETRAINED = Path(__file__).resolve().parent / "pretrained"

SCORING_REPLACES = ("scenario", "variations", "angle_noise_std", "duration", "threads", "reward_weights",
                    "terminate_on_violation", "bound_scale", "level", "start_time")
"""env kwargs that blf-eval's ``evaluate_agent`` replaces: the scenarios are given, the reward is
not needed, termination is off, the bounds are the benchmark's own (``bound_scale`` 1), the
level is blf-eval's ``--level`` (the scenarios come at it), not the one the agent trained at, and
every scored episode starts at t = 0 (``start_time`` is a training aid)."""


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
                         f"install the package that provides it (tqc: pip install sb3-contrib; sbx_ppo, sbx_sac, sbx_crossq: "
                         f"pip install -c constraints-cpu.txt -e '.[jax]')") from exc


def read_json_object(path: Path, what: str, hint: str = "") -> dict[str, Any]:
    """A JSON object from ``path``; ValueError naming the file if it is unreadable or not an object."""
    try:
        obj = json.loads(Path(path).read_text())
    except (OSError, ValueError) as exc:
        raise ValueError(f"{path}: not readable as JSON ({exc}); it should hold {what}{hint}") from None
    if not isinstance(obj, dict):
        raise ValueError(f"{path}: not a JSON object; it should hold {what}{hint}")
    return obj


def scoring_env_kwargs(env_kwargs: dict[str, Any]) -> dict[str, Any]:
    """The keyword arguments of the env blf-eval scores an agent in, from the metadata's
    ``env_kwargs``: those of :data:`SCORING_REPLACES` dropped, no reward terms (``reward_weights={}``)
    and termination off. ``blf_gym.envs.envcore.EnvCore(n, record=True, threads=..., **scoring_env_kwargs(kw))``
    is ``agents.evaluate.evaluate_agent``'s env."""
    kw = {k: v for k, v in env_kwargs.items() if k not in SCORING_REPLACES}
    kw.update(reward_weights={}, terminate_on_violation=False)
    return kw


def _one_line(text: Any) -> str:
    return " ".join(str(text).split())


def _short(value: Any, limit: int = 80) -> str:
    r = _one_line(repr(value))
    return r if len(r) <= limit else r[: limit - 3] + "..."


def _field_in(message: str, keys: list[str]) -> str | None:
    """The key of ``keys`` an env error message names first (``control_period`` also as "control
    period(s)"), or None."""
    best: tuple[int, str] | None = None
    for k in keys:
        m = re.search(r"(?<![\w.])" + re.escape(k).replace("_", "[_ ]") + r"s?(?!\w)", message)
        if m and (best is None or m.start() < best[0]):
            best = (m.start(), k)
    return None if best is None else best[1]


def _check_metadata(meta: dict[str, Any], meta_path: Path) -> None:
    """The checks that need the metadata alone: name, mode, env_kwargs' type and keys."""
    from blf_gym.envs.envcore import check_env_kwargs

    from blf_gym import ENV_IDS

    name = meta.get("name", "agent")
    if not isinstance(name, str) or not name:
        raise ValueError(f"{meta_path}: name: must be a non-empty string (the agent's label in blf-eval's "
                         f"results), got {_short(name)}")
    if not isinstance(meta["algo"], str):
        raise ValueError(f"{meta_path}: algo: must be the name of a registered algorithm, e.g. 'ppo' "
                         f"(accepted: {available_algorithms()}), got {_short(meta['algo'])}")
    mode = meta["mode"]
    if not isinstance(mode, str) or mode not in ENV_IDS:
        raise ValueError(f"{meta_path}: mode: must be one of {list(ENV_IDS)} (plain: the agent's action is the "
                         f"torque; residual: it is added to a law's), got {_short(mode)}")
    kw = meta["env_kwargs"]
    if not isinstance(kw, dict):
        raise ValueError(f"{meta_path}: env_kwargs: must be a JSON object of the env's keyword arguments "
                         f"(e.g. {{\"control_period\": 0.01}}), got {_short(kw)}")
    try:
        check_env_kwargs(kw)
    except ValueError as exc:
        unknown = []
        for k in kw:  # named one by one, so the message can start with the fields
            try:
                check_env_kwargs({k: kw[k]})
            except ValueError:
                unknown.append(k)
        raise ValueError(f"{meta_path}: {', '.join(f'env_kwargs.{k}' for k in unknown) or 'env_kwargs'}: "
                         f"{_one_line(exc)}") from None


def _normalization_stated(meta: dict[str, Any], meta_path: Path, stats: Path) -> bool:
    """config.normalize, which must be stated (true or false) and agree with the statistics file."""
    config = meta.get("config")
    present = stats.is_file()
    has = f"{stats.name} is {'present' if present else 'absent'}"
    if config is None:
        raise ValueError(f"{meta_path}: config.normalize: not stated, so whether the agent needs observation "
                         f"normalization is unknown ({has}); add \"config\": {{\"normalize\": true}} if it was "
                         "trained with normalize: true (blf-train writes it), false if it was not")
    if not isinstance(config, dict):
        raise ValueError(f"{meta_path}: config: must be a JSON object (blf-train writes the run's config there, "
                         f"with normalize: true or false), got {_short(config)}")
    if "normalize" not in config:
        raise ValueError(f"{meta_path}: config.normalize: not stated, so whether the agent needs observation "
                         f"normalization is unknown ({has}); add \"normalize\": true to its \"config\" if it was "
                         "trained with normalize: true (blf-train writes it), false if it was not")
    normalize = config["normalize"]
    if not isinstance(normalize, bool):
        raise ValueError(f"{meta_path}: config.normalize: must be true or false, got {_short(normalize)}")
    if normalize and not present:
        raise ValueError(f"{stats}: missing. The agent was trained with observation normalization "
                         f"(metadata config.normalize), and scored without its statistics its numbers "
                         "mean nothing; restore the file or retrain")
    if present and not normalize:
        raise ValueError(f"{meta_path}: config.normalize: false, but {stats} is present; one of them is wrong, "
                         "and the agent scored with or without these statistics may mean nothing: set "
                         "config.normalize to true if it was trained with normalization, or remove the file if not")
    return normalize


def _statistics(stats: Path, model_path: Path, model: Any) -> Any:
    try:
        with open(stats, "rb") as f:
            norm = pickle.load(f)
        obs_shape = tuple(norm.obs_rms.mean.shape)
    except Exception as exc:  # a truncated or foreign pickle
        raise ValueError(f"{stats}: not readable as the agent's normalization statistics "
                         f"({type(exc).__name__}: {_one_line(exc)})") from None
    if getattr(norm, "norm_obs", True) is not True:
        raise ValueError(f"{stats}: norm_obs: {_short(getattr(norm, 'norm_obs', None))}, so these statistics "
                         "would leave the observations as they are, but the metadata states config.normalize true")
    model_shape = tuple(getattr(model.observation_space, "shape", None) or ())
    if obs_shape != model_shape:
        raise ValueError(f"{stats}: obs_rms: statistics for observations of shape {obs_shape}, but the model in "
                         f"{model_path} takes {model_shape}; they are not this agent's")
    return norm


def _scoring_core(meta: dict[str, Any], meta_path: Path):
    """The env blf-eval would score the agent in, with two arms; the env's own refusal, as one line
    naming the env_kwargs field. Building it loads (or, on a first run, compiles) the closed-loop
    kernel of the agent's controller, observer and filter: the batch build (two arms or more step
    in blocks of four, blf_gym.kernel.simulate.ClosedLoop), which blf-eval's batches then step and a
    single arm takes when its own build is not compiled, kept in memory and in numba's disk cache,
    so no second compile follows. (Only an agent run through another filter, blf-eval
    --residual-filter, needs a kernel besides this one.)"""
    from blf_gym.envs.envcore import EnvCore

    kw = scoring_env_kwargs(meta["env_kwargs"])
    try:
        return EnvCore(2, record=True, threads=1, **kw)
    except (ValueError, TypeError) as exc:
        msg = _one_line(exc)
        field = _field_in(msg, [k for k in meta["env_kwargs"] if k not in SCORING_REPLACES])
        raise ValueError(f"{meta_path}: env_kwargs{'.' + field if field else ''}: the env blf-eval builds "
                         f"from it refuses it ({msg})") from None


def _check_spaces(model: Any, meta: dict[str, Any], meta_path: Path, model_path: Path, core: Any) -> None:
    """The model's saved observation and action spaces against the env the metadata builds."""
    import numpy as np
    from gymnasium import spaces

    from blf_gym.envs.envcore import observation_layout

    from blf_gym import ENV_IDS

    kw = meta["env_kwargs"]
    mode = meta["mode"]
    if core.residual != (mode == "residual"):
        raise ValueError(f"{meta_path}: mode: {mode!r} contradicts env_kwargs.controller "
                         f"{_short(kw.get('controller'))}, which builds a {'residual' if core.residual else 'plain'} "
                         "env (a plain agent has no controller, its action is the whole torque; a residual agent "
                         "names the law it acts over, e.g. 'proposed')")
    if "env_id" in meta and meta["env_id"] != ENV_IDS[mode]:
        raise ValueError(f"{meta_path}: env_id: {_short(meta['env_id'])} contradicts mode {mode!r} "
                         f"(a {mode} agent acts in {ENV_IDS[mode]!r}; accepted pairs: {ENV_IDS})")
    obs = model.observation_space
    if not isinstance(obs, spaces.Box):
        raise ValueError(f"{model_path}: observation_space: the model observes {_short(obs)}, not a Box; it is "
                         "not a blf-gym agent")
    if tuple(obs.shape) != (core.obs_dim,):
        # the env kwargs that shape the observation, as the metadata gives them
        given = [k for k in ("privileged", "observation_extras") if k in kw]
        fields = ", ".join(f"env_kwargs.{k}" for k in given) or "env_kwargs"
        values = (", ".join(f"{k}={_short(kw[k])}" for k in given)
                  or "privileged and observation_extras at their defaults")
        raise ValueError(f"{meta_path}: {fields}: the env they build ({values}) observes {core.obs_dim} entries, "
                         f"but the model in {model_path} was trained on observations of shape {tuple(obs.shape)}; "
                         "restore the env_kwargs it was trained with")
    bad = np.flatnonzero((np.asarray(obs.low, dtype=np.float32) != core.obs_low)
                         | (np.asarray(obs.high, dtype=np.float32) != core.obs_high))
    if bad.size:
        layout = observation_layout(core.n, core.privileged, core.observation_extras)
        names = ", ".join(f"{layout[i][0]}: [{core.obs_low[i]:g}, {core.obs_high[i]:g}] in the env, "
                          f"[{obs.low[i]:g}, {obs.high[i]:g}] in the model" for i in bad[:2])
        raise ValueError(f"{model_path}: observation_space: its Box bounds differ from those of the env "
                         f"{meta_path} builds at {len(bad)} entr{'y' if len(bad) == 1 else 'ies'} "
                         f"({names}{', ...' if len(bad) > 2 else ''}); it was trained on another observation")
    act = model.action_space
    want = spaces.Box(-1.0, 1.0, (core.n,), dtype=np.float32)
    if not (isinstance(act, spaces.Box) and act.shape == want.shape and np.array_equal(act.low, want.low)
            and np.array_equal(act.high, want.high)):
        raise ValueError(f"{model_path}: action_space: the model acts in {_short(act)}, but the env {meta_path} "
                         f"builds takes {want} (one normalized torque per joint)")


HASHED_FILES = ("model.zip", "vecnormalize.pkl")
"""The files of an agent folder whose sha256 the metadata records (``files``) and the loader checks."""


def _sha256(path: Path) -> str:
    import hashlib

    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def file_hashes(folder: str | Path) -> dict[str, str]:
    """``{name: sha256}`` of each of :data:`HASHED_FILES` present in ``folder``: what an agent's
    ``metadata.json`` records under ``files`` when the folder is written (blf-train, agents.zoo,
    :func:`record_file_hashes`)."""
    folder = Path(folder)
    return {name: _sha256(folder / name) for name in HASHED_FILES if (folder / name).is_file()}


def record_file_hashes(folder: str | Path) -> dict[str, str]:
    """Write the sha256 of the folder's model and statistics into its ``metadata.json`` (``files``),
    atomically, leaving every other field as it is; returns them. For a folder written before the
    hashes existed, or one whose files you replaced on purpose."""
    from blf_gym.results.io import atomic_write_json

    folder = Path(folder)
    meta_path = folder / "metadata.json"
    meta = read_json_object(meta_path, "the run's metadata")
    meta["files"] = file_hashes(folder)
    atomic_write_json(meta_path, meta)
    return meta["files"]


_UNHASHED_WARNED: set[Path] = set()


def _check_files(meta: dict[str, Any], meta_path: Path, accept_changed_files: bool) -> None:
    """The folder's model and statistics against the sha256 that ``metadata.json`` recorded when the
    folder was written: a file swapped in from another agent (a ``vecnormalize.pkl`` of the same
    observation size loads, and scores differently) is refused by name."""
    folder = meta_path.parent
    recorded = meta.get("files")
    if recorded is None:
        if meta_path not in _UNHASHED_WARNED:
            _UNHASHED_WARNED.add(meta_path)
            warnings.warn(f"{meta_path}: no 'files' field, so its model and statistics cannot be checked against "
                          "what was saved (written before blf-gym recorded them); record them with python -m "
                          f"agents.loading --record-hashes {folder}", stacklevel=3)
        return
    if not isinstance(recorded, dict) or not all(isinstance(k, str) and isinstance(v, str)
                                                 for k, v in recorded.items()):
        raise ValueError(f"{meta_path}: files: must map file names to sha256 hex digests, got {_short(recorded)}")
    if accept_changed_files:
        return
    hint = ("; if you replaced it on purpose, accept it knowingly with load_agent(..., accept_changed_files=True) "
            f"or blf-eval --accept-changed-files, or record the new hashes with python -m agents.loading "
            f"--record-hashes {folder}")
    present = file_hashes(folder)
    for name in HASHED_FILES:
        want, got = recorded.get(name), present.get(name)
        if want == got:
            continue
        if want is None:
            raise ValueError(f"{folder / name}: present, but metadata.json's files do not list it: it was not "
                             f"saved with this agent{hint}")
        if got is None:
            raise ValueError(f"{folder / name}: missing, but metadata.json's files list it (sha256 {want[:12]}...)"
                             f"{hint}")
        raise ValueError(f"{folder / name}: sha256 {got[:12]}... is not the {want[:12]}... that metadata.json "
                         f"recorded when the agent was saved: it is another file{hint}")


def _metadata(meta_path: Path, model_path: Path) -> dict[str, Any]:
    if not meta_path.is_file():
        raise ValueError(f"{model_path}: no metadata.json beside the model; was it written by blf-train?")
    meta = read_json_object(meta_path, "the run's metadata")
    for key in ("algo", "mode", "env_kwargs"):
        if key not in meta:
            raise ValueError(f"{meta_path}: the metadata lacks {key!r}")
    return meta


def load_agent(path: str | Path, accept_changed_files: bool = False) -> tuple[Any, dict[str, Any], Any]:
    """(SB3 model, metadata, VecNormalize statistics or None) from a ``blf-train`` run folder or its
    model zip, checked as a whole (the module docstring lists the checks; each problem is one
    ``ValueError`` naming the file and the field). The env kwargs the agent was trained with are
    ``metadata["env_kwargs"]``. ``accept_changed_files``: load a model or statistics file whose
    sha256 differs from the one the metadata recorded (you replaced it on purpose)."""
    path = Path(path)
    if path.is_dir():
        if not (path / "model.zip").is_file():
            raise ValueError(f"{path}: no model.zip in this folder; give a blf-train run folder or its model zip")
        path = path / "model.zip"
    if not path.is_file():
        raise ValueError(f"agent model not found: {path}")
    meta_path = path.with_name("metadata.json")
    meta = _metadata(meta_path, path)
    _check_metadata(meta, meta_path)
    try:
        cls = algorithm_class(meta["algo"])
    except (ValueError, TypeError) as exc:
        raise ValueError(f"{meta_path}: algo: {_one_line(exc)}") from None
    try:
        model = cls.load(path, device="cpu")
    except Exception as exc:  # SB3 raises several types for a corrupt or foreign zip
        raise ValueError(f"{path}: cannot be loaded as a {str(meta['algo']).upper()} model "
                         f"({_one_line(exc)})") from exc
    stats = path.with_name("vecnormalize.pkl")
    norm = _statistics(stats, path, model) if _normalization_stated(meta, meta_path, stats) else None
    _check_spaces(model, meta, meta_path, path, _scoring_core(meta, meta_path))
    # last: a damaged file is named by the checks above; what they cannot see is a whole file swapped
    # in from another agent of the same sizes
    _check_files(meta, meta_path, accept_changed_files)
    return model, meta, norm


POLICY_PREFIX = "policy:"
"""How blf-eval names a registered policy where it names an agent's folder (``policy:nmpc``)."""


def load_policy(name: str) -> tuple[Any, dict[str, Any], None]:
    """(policy, metadata, None) for a policy registered in the ``blf_gym.policies`` entry points
    (``blf_gym.plugins.registry.make_policy``), shaped as :func:`load_agent`'s answer so blf-eval scores it
    as it scores an agent: the metadata names it, says plain mode and holds the policy's own
    ``env_kwargs``; there are no normalization statistics. ``name`` may carry
    :data:`POLICY_PREFIX`, and parameters of the policy's factory as ``NAME:key=value,...``
    (``floor:control_period=0.001``), named so in the records. The env it asks for is checked as an
    agent's is."""
    from blf_gym.plugins.blocks import parse_filter_spec
    from blf_gym.plugins.registry import make_policy

    name = name[len(POLICY_PREFIX):] if name.startswith(POLICY_PREFIX) else name
    try:
        base, kwargs = parse_filter_spec(name)
    except ValueError:
        raise ValueError(f"policy {name!r}: the form is NAME or NAME:key=number,key=number") from None
    try:
        policy = make_policy(base, **kwargs)
    except ImportError as exc:  # an optional dependency (the NMPC's CasADi, from the mpc extra)
        raise ValueError(f"policy {name!r}: {_one_line(exc)}") from None
    if (policy.env_kwargs.get("controller") or "none") != "none":
        raise ValueError(f"policy {name!r}: its env_kwargs name the inner law "
                         f"{policy.env_kwargs['controller']!r}; a registered policy acts in the plain env")
    meta = {"name": name, "algo": POLICY_PREFIX + name, "mode": "plain",
            "env_kwargs": json.loads(json.dumps(policy.env_kwargs)), "policy": name}
    _scoring_core(meta, Path(f"{POLICY_PREFIX}{name}"))
    return policy, meta, None


def check_agent_folder(path: str | Path, accept_changed_files: bool = False) -> None:
    """Check a ``blf-train`` run folder (or its model zip) as :func:`load_agent` does, without
    keeping the model: returns None, or raises the one-line ``ValueError`` naming the file and the
    field at fault."""
    load_agent(path, accept_changed_files)


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
    kw.pop("bound_scale", None)  # a training curriculum's; the agent is judged at the benchmark's bounds
    kw.pop("level", None)  # the level it trained at; loaded for the benchmark, as blf-eval scores it
    if reward == "score":
        kw.pop("reward_weights", None)
    else:
        kw.setdefault("reward_weights", {})
    kw["terminate_on_violation"] = False
    if scenario is not None:
        kw["scenario"] = scenario
    kw.update(env_kwargs)
    from blf_gym import ENV_IDS

    env_id = meta.get("env_id") or ENV_IDS[meta["mode"]]
    venv = DummyVecEnv([lambda: Monitor(gym.make(env_id, **kw))])
    if norm is None:
        return model, venv
    norm.set_venv(venv)
    norm.training = False
    norm.norm_reward = False
    return model, norm


def main(argv: list[str] | None = None) -> int:
    """``python -m agents.loading --record-hashes DIR [DIR ...]``: record the sha256 of each folder's
    model and statistics in its metadata.json; ``python -m agents.loading DIR``: check a folder."""
    import argparse

    ap = argparse.ArgumentParser(prog="python -m agents.loading", description=main.__doc__)
    ap.add_argument("folders", nargs="+", type=Path, help="agent folders (blf-train run folders)")
    ap.add_argument("--record-hashes", action="store_true",
                    help="write the sha256 of model.zip and vecnormalize.pkl into metadata.json's files, then check")
    args = ap.parse_args(argv)
    for folder in args.folders:
        if args.record_hashes:
            for name, digest in record_file_hashes(folder).items():
                print(f"{folder / name}: sha256 {digest}")
        check_agent_folder(folder)
        print(f"{folder}: checked")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
