"""``blf-train`` (also ``python -m agents.train``): train an SB3 agent on PlanarBLF.

Examples::

    blf-train --mode residual --scenario randomized --timesteps 1000000 --out runs/ppo_residual
    blf-train --algo sac --mode residual --timesteps 200000 --out runs/sac_residual
    blf-train --algo ppo --mode plain --scenario randomized --seed 3 --out runs/ppo_plain
    blf-train --resume --out runs/ppo_residual          # continue an interrupted run
    blf-train --algo sbx_sac --mode plain --timesteps 1000000000 --time-budget 3600 --out runs/sac
                                                        # as many steps as one hour of wall clock allows

Hyperparameters come from a YAML file per algorithm and env id (``agents/configs``, rl-zoo3
style; ``--config`` picks another). Only ``ppo_PlanarBLFResidual-v0.yaml`` is tuned (see
docs/tuning.md); the others are reasonable starting points. A run folder holds ``model.zip``,
``vecnormalize.pkl`` (when observations are normalized), ``metadata.json`` (config, package versions, seed, wall time, git
commit), ``checkpoints/`` (model, replay buffer and normalization statistics, for ``--resume``),
``eval/curve.json`` (learning curves: every ``eval_freq`` steps, the deterministic policy's RMSE
and violations with blf-eval's metrics on both paper presets and ``curve_suite_seeds`` held-out
randomized-suite episodes) and ``tb/`` (TensorBoard logs). ``blf-curves`` plots them.

Residual exploration stays near the law: the residual is bounded by ``residual_scale``, the
configs start PPO and SAC with a negative log-std and SAC/TD3 with no uniform warm-up
(``learning_starts: 0``), and TD3's action noise is small. The env adds the residual to the law,
so the critic learns on the action actually applied.
"""

from __future__ import annotations

import argparse
import inspect
import json
import os
import signal
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Mapping, Sequence

import numpy as np

from blf_gym import ENV_IDS
from blf_gym.results.io import atomic_write_json, help_text
from blf_gym.envs.levels import DEFAULT_LEVEL

from .config import (RunSpec, TrainConfig, add_config_options, apply_overrides, check_config, curriculum_scale,
                     parse_overrides, shipped_config)

__all__ = ["TrainRequest", "load_config", "main", "run_training", "train"]

MODES = tuple(ENV_IDS)
# set to "1" by blf-sweep in its blf-train processes: pause after each learning-curve point
PAUSE_ENV = "BLF_TRAIN_PAUSE_AT_POINTS"


def load_config(path: str | Path) -> dict[str, Any]:
    """Read a YAML config and check it against :class:`agents.config.TrainConfig` (unknown keys and
    wrong types refused, naming the file and the key)."""
    import yaml

    path = Path(path)
    if not path.is_file():
        raise ValueError(f"config not found: {path}")
    try:
        cfg = yaml.safe_load(path.read_text()) or {}
    except yaml.YAMLError as exc:
        raise ValueError(f"{path}: not valid YAML ({exc})") from None
    check_config(cfg, str(path))
    return cfg


def _stated(cfg: dict[str, Any]) -> dict[str, Any]:
    """The config as the metadata records it: with ``normalize`` stated, true or false, even when the
    YAML leaves it out (agents.loading refuses an agent whose metadata does not say it)."""
    return {**cfg, "normalize": bool(cfg.get("normalize"))}


def _make_progress_callback(total: int, start: int, enabled: bool):
    from stable_baselines3.common.callbacks import BaseCallback

    class _Progress(BaseCallback):
        def _on_training_start(self) -> None:
            self.bar = None
            if enabled:
                from tqdm import tqdm

                self.bar = tqdm(total=total, initial=start, unit="step", desc="blf-train", file=sys.stderr)

        def _on_step(self) -> bool:
            if self.bar is not None:
                self.bar.n = min(self.num_timesteps, total)
                self.bar.refresh()
            return True

        def _on_training_end(self) -> None:
            if self.bar is not None:
                self.bar.close()

        def status(self, text: str) -> None:
            """What the run does while the step count stands still (a curve point's evaluation)."""
            bar = getattr(self, "bar", None)
            if bar is not None:
                bar.set_postfix_str(text, refresh=True)

    return _Progress()


def _schedule(spec: str, where: str):
    """``"lin_<x>"``: a value decaying linearly from x to 0 over training (rl-zoo's notation); a
    number written as text (YAML 1.1 reads ``3e-4`` as the string "3e-4") is that constant."""
    try:
        if not spec.startswith("lin_"):
            return float(spec)
        start = float(spec[4:])
    except ValueError:
        raise ValueError(f"{where} must be a number or 'lin_<number>' (linear decay to 0), got {spec!r}") from None

    def value(progress_remaining: float) -> float:
        return progress_remaining * start

    return value


class _RunClock:
    """Wall time that produced the current model: the checkpoint's, plus this segment's."""

    def __init__(self, prior: float = 0.0) -> None:
        self.prior = float(prior)
        self.t0 = time.monotonic()

    def segment(self) -> float:
        return time.monotonic() - self.t0

    def model(self) -> float:
        return self.prior + self.segment()


def _make_curve_callback(every: int, out: Path, env_kwargs: dict[str, Any], meta: dict[str, Any],
                         suite_seeds: int, clock: _RunClock, on_point=None, status=None, total: int | None = None):
    """Learning curves: at the start, every ``every`` agent steps and at the end, score the
    deterministic policy with blf-eval's metrics on both paper presets and ``suite_seeds`` held-out
    randomized-suite episodes, and append the records to ``out/eval/curve.json`` (atomic; kept
    across ``--resume``). A point that was due at or before the resume checkpoint but is missing
    (the process was killed while evaluating it) is evaluated first, so no point is lost."""
    from stable_baselines3.common.callbacks import BaseCallback
    from stable_baselines3.common.vec_env import VecNormalize

    from blf_gym.results.metrics import summarize

    from .evaluate import agent_episodes, curve_scenarios

    path = out / "eval" / "curve.json"
    groups = curve_scenarios(suite_seeds, env_kwargs.get("duration"), env_kwargs.get("level", DEFAULT_LEVEL),
                             env_kwargs.get("n_links"))

    class _Curve(BaseCallback):
        def _on_training_start(self) -> None:
            self.points = json.loads(path.read_text())["points"] if path.is_file() else []
            # after --resume, points past the checkpoint belong to the abandoned stretch
            self.points = [p for p in self.points if p["timesteps"] <= self.num_timesteps]
            self.next_at = (self.num_timesteps // every + 1) * every
            due = (self.num_timesteps // every) * every
            if not self.points or (self.num_timesteps > 0 and due > self.points[-1]["timesteps"]):
                # the untrained policy (for a residual agent, about the law alone), or a point a
                # kill interrupted before it was written
                self._evaluate()
                self._pause()

        def _evaluate(self) -> None:
            if status is not None:
                status(f"evaluating the learning curve at {self.num_timesteps} steps")
            env = self.model.get_env()
            norm = env if isinstance(env, VecNormalize) else None
            point: dict[str, Any] = {"timesteps": int(self.num_timesteps), "wall_s": round(clock.model(), 1)}
            for label, scs in groups:
                # episodes reduced as they come: memory does not grow with the curve's episodes
                rec = summarize(agent_episodes(self.model, meta, norm, scs, threads=1), meta["name"], meta["mode"],
                                label, scs[0].sim.dt)
                point[label] = {k: rec[k] for k in ("rmse_deg", "violations", "failure_rate", "diverged",
                                                    "first_violation_s", "violation_fraction")}
            self.points.append(point)
            atomic_write_json(path, {"env_kwargs": env_kwargs, "suite_seeds": suite_seeds,
                                     "points": self.points})
            if on_point is not None:
                on_point()
            if status is not None:
                status("")

        def _pause(self) -> None:
            """With ``BLF_TRAIN_PAUSE_AT_POINTS=1`` (set by blf-sweep's trials), stop this process
            (SIGSTOP to itself) right after a point is written, until the sweep's trial lets it go on
            (SIGCONT) once Ray has decided on the point: a trial the scheduler stops at a rung has
            trained exactly to that rung, however fast the process or slow the machine. Training's
            numbers do not depend on the pause. Not after the last point (the run goes on to save)."""
            if os.environ.get(PAUSE_ENV) == "1" and hasattr(signal, "SIGSTOP"):
                os.kill(os.getpid(), signal.SIGSTOP)

        def _on_step(self) -> bool:
            if self.num_timesteps >= self.next_at:
                self._evaluate()
                self.next_at = (self.num_timesteps // every + 1) * every
                if total is None or self.num_timesteps < total:  # the run's requested total
                    self._pause()
            return True

        def _on_training_end(self) -> None:
            # the curve ends at the model that is saved
            if self.points and self.points[-1]["timesteps"] != self.num_timesteps:
                self._evaluate()

    return _Curve()


def _make_curriculum_callback(cur: dict[str, Any]):
    """Sets the training env's ``bound_scale`` to :func:`agents.config.curriculum_scale` of the
    step count before every step (it applies at each arm's next reset); a function of the step
    count alone, so a resumed run continues the same schedule."""
    from stable_baselines3.common.callbacks import BaseCallback

    class _Curriculum(BaseCallback):
        def _set(self) -> None:
            scale = curriculum_scale(cur, self.num_timesteps)
            if scale != self.scale:
                self.training_env.set_attr("bound_scale", scale)
                self.scale = scale
                self.logger.record("curriculum/bound_scale", scale)

        def _on_training_start(self) -> None:
            self.scale = None
            self._set()

        def _on_step(self) -> bool:
            self._set()
            return True

    return _Curriculum()


def _configured(cls, tc: TrainConfig, key: str) -> Any:
    """A hyperparameter as the run was configured: the config's value, else ``cls``'s default."""
    if key in tc.hyperparams:
        return tc.hyperparams[key]
    return inspect.signature(cls.__init__).parameters[key].default


def _make_refill_callback(model, until: int, gradient_steps: int):
    """After an off-policy run resumed without its replay buffer: the policy acts with no gradient
    steps (``model.gradient_steps`` is 0) until step ``until``, so that updates start again on a
    buffer of the run's own ``learning_starts`` transitions rather than on the first few. SB3's
    ``learning_starts`` cannot be reused for this: below it the actions are uniformly random."""
    from stable_baselines3.common.callbacks import BaseCallback

    class _Refill(BaseCallback):
        def _on_step(self) -> bool:
            if self.num_timesteps >= until and self.model.gradient_steps != gradient_steps:
                self.model.gradient_steps = gradient_steps
                self.logger.record("refill/ended_at", self.num_timesteps)
            return True

    model.gradient_steps = 0
    return _Refill()


def _make_time_budget_callback(clock: _RunClock, budget: float):
    """Ends training at the first step at which the wall time that produced the model (over all
    segments, ``clock.model()``) reaches ``budget`` seconds."""
    from stable_baselines3.common.callbacks import BaseCallback

    class _TimeBudget(BaseCallback):
        def _on_step(self) -> bool:
            return clock.model() < budget

    return _TimeBudget()


def _read_metadata(path: Path) -> dict[str, Any]:
    from .loading import read_json_object

    return read_json_object(path, "the run's metadata", "; move it away to start a new run")


def _nothing_to_do(venv: Any, out: Path, why: str) -> Path:
    """A resume that trains nothing: say why, release the env's threads, and hand back the run."""
    print(f"blf-train: {out} {why}", file=sys.stderr)
    venv.close()
    return out


def _resume_settings(meta: dict[str, Any], given: dict[str, Any], where: Path) -> dict[str, Any]:
    """The run's own settings for ``--resume``; an explicit option that contradicts them is refused."""
    env_kwargs = meta.get("env_kwargs") or {}
    recorded = {"algo": meta.get("algo"), "mode": meta.get("mode"), "controller": env_kwargs.get("controller"),
                "scenario": env_kwargs.get("scenario"), "seed": meta.get("seed"),
                "observer": env_kwargs.get("observer", "leso"), "name": meta.get("name")}
    for key, value in given.items():
        if value is not None and recorded.get(key) is not None and value != recorded[key]:
            raise ValueError(f"--{key} {value} differs from the run's {recorded[key]!r} ({where}); "
                             f"--resume continues a run with its own settings, so drop --{key} or "
                             "choose another --out")
    return {k: (given[k] if recorded.get(k) is None else recorded[k]) for k in given}


def _settle(given: dict[str, Any], timesteps: int | None, config: str | Path | None, resume: bool,
            prior: dict[str, Any] | None, meta_path: Path,
            overrides: Mapping[str, Any]) -> tuple[RunSpec, dict[str, Any], str]:
    """The run to train: its spec (options, else the resumed run's own settings, else the
    defaults), its config (the resumed run's own, or the file with the dotted ``overrides`` set)
    and the config file's path ("" when none ships for the algorithm: TrainConfig's defaults)."""
    if resume and prior is not None:
        given = _resume_settings(prior, given, meta_path)
        if given["mode"] == "plain":
            given["controller"] = None
    seed = 0 if given["seed"] is None else given["seed"]  # checked with the rest by RunSpec.checked
    if timesteps is None:
        timesteps = int(prior.get("timesteps_requested", 100_000)) if (resume and prior) else 100_000
    run = RunSpec(given["algo"] or "ppo", given["mode"] or "residual", given["controller"],
                  given["observer"] or "leso", given["scenario"] or "paper-0.1hz", timesteps, [seed]).checked()
    if resume and prior is not None and isinstance(prior.get("config"), dict):
        cfg = prior["config"]
        cfg_file = str(prior.get("config_file") or "")
        if config is not None or overrides:
            # what the options would train with: the file (else the run's own config), with --set
            asked = apply_overrides(load_config(config) if config is not None else cfg, overrides, "--set")
            if json.dumps(_stated(asked), sort_keys=True) != json.dumps(_stated(cfg), sort_keys=True):
                what = " and ".join(([f"--config {config}"] if config is not None else [])
                                    + ([f"--set {dict(overrides)}"] if overrides else []))
                raise ValueError(f"{what} differs from the config this run was trained with ({meta_path}, "
                                 "'config'); --resume keeps the run's own config")
    else:
        path = Path(config) if config else shipped_config(run.algo, run.mode)
        if path is None:
            cfg, cfg_file = {}, ""
            print(f"blf-train: no config ships for {run.algo} in {run.mode} mode; training with TrainConfig's "
                  f"defaults (agents/config.py) and {run.algo}'s own hyperparameters (--config FILE sets them)",
                  file=sys.stderr)
        else:
            cfg, cfg_file = load_config(path), str(path)
        if overrides:
            cfg = apply_overrides(cfg, overrides, f"{_where(cfg_file)} with --set")
    return run, cfg, cfg_file


def _where(cfg_file: str) -> str:
    """How an error names the config: its file, or TrainConfig's defaults."""
    return cfg_file or "the config (TrainConfig's defaults, agents/config.py)"


def _env_kwargs(run: RunSpec, tc: TrainConfig) -> dict[str, Any]:
    """The training env's keyword arguments, as the metadata records them."""
    env_kwargs: dict[str, Any] = {"scenario": run.scenario, **tc.env}
    if run.mode == "residual":
        env_kwargs["controller"] = run.controller
    if run.observer != "leso":
        env_kwargs["observer"] = run.observer
    if isinstance(env_kwargs.get("action_scale"), str):
        # "law": read from the law's torques on this env's own training draws once, and recorded
        # as numbers, so that the agent is scored with the scale it trained with wherever it goes
        import gymnasium as gym

        probe = gym.make(ENV_IDS[run.mode], **{"controller": None, **env_kwargs, "threads": 1})
        env_kwargs["action_scale"] = [float(v) for v in probe.unwrapped.core.action_scale]
        probe.close()
    return env_kwargs


def _restore(cls, venv, ckpt_dir: Path, normalize: bool, out: Path):
    """The newest complete checkpoint that loads, as (model, its steps, the wall time that produced
    it, whether an off-policy model got its replay buffer back, the set's state), or (None, 0, 0.0,
    False, {}); incomplete or unreadable sets are named and skipped, and unfinished partial sets
    removed."""
    from stable_baselines3.common.vec_env import VecNormalize

    from .checkpoints import find_checkpoints

    model, start_steps, prior_model_wall, with_buffer, state = None, 0, 0.0, False, {}
    found, skipped = find_checkpoints(ckpt_dir, normalize)
    for s in skipped:
        print(f"blf-train: skipping incomplete checkpoint {s}", file=sys.stderr)
    for ck in found:
        try:
            env = VecNormalize.load(str(ck.stats), venv) if ck.stats is not None else venv
            model = cls.load(ck.model, env=env, device="cpu")
            with_buffer = ck.buffer is not None and hasattr(model, "replay_buffer")
            if with_buffer:
                model.load_replay_buffer(ck.buffer)
        except Exception as exc:  # a damaged file SB3 or pickle cannot read: try an older set
            print(f"blf-train: skipping checkpoint at {ck.steps} steps ({ck.model.parent}): "
                  f"cannot be loaded ({type(exc).__name__}: {exc})", file=sys.stderr)
            model = None
            continue
        start_steps = ck.steps
        prior_model_wall = float(ck.state.get("wall_s_to_model", 0.0))
        state = dict(ck.state)
        print(f"blf-train: resuming {out} from its checkpoint at {start_steps} steps", file=sys.stderr)
        break
    for partial in ckpt_dir.glob(".partial_*") if ckpt_dir.is_dir() else []:
        import shutil

        shutil.rmtree(partial, ignore_errors=True)
    return model, start_steps, prior_model_wall, with_buffer, state


def _new_model(cls, run: RunSpec, tc: TrainConfig, cfg_file: str, venv, out: Path):
    """A fresh model of the registered class ``cls`` on ``venv`` (wrapped in VecNormalize when
    the config normalizes), with the config's hyperparameters."""
    from stable_baselines3.common.noise import NormalActionNoise
    from stable_baselines3.common.vec_env import VecNormalize

    if tc.normalize:
        venv = VecNormalize(venv, norm_obs=True, norm_reward=tc.normalize_reward,
                            gamma=float(tc.hyperparams.get("gamma", 0.99)))
    kwargs = dict(tc.hyperparams)
    for key in ("learning_rate", "clip_range"):
        if isinstance(kwargs.get(key), str):
            kwargs[key] = _schedule(kwargs[key], f"{_where(cfg_file)}: hyperparams.{key}")
    if tc.policy_kwargs:
        kwargs["policy_kwargs"] = dict(tc.policy_kwargs)
    if tc.action_noise_std:
        # any registered algorithm whose constructor takes SB3's action_noise (the off-policy ones)
        if "action_noise" not in inspect.signature(cls.__init__).parameters:
            raise ValueError(f"{_where(cfg_file)}: action_noise_std needs an algorithm that takes SB3's action_noise "
                             f"(an off-policy one); {run.algo} does not")
        n_act = int(np.prod(venv.action_space.shape))  # one entry per joint
        kwargs["action_noise"] = NormalActionNoise(np.zeros(n_act), float(tc.action_noise_std) * np.ones(n_act))
    tb = None
    try:
        import tensorboard  # noqa: F401

        tb = str(out / "tb")
    except ImportError:
        print("blf-train: tensorboard is not installed; no TensorBoard logs", file=sys.stderr)
    try:
        return cls(tc.policy, venv, seed=run.seeds[0], device="cpu", tensorboard_log=tb, verbose=0,
                   **kwargs)
    except TypeError as exc:
        raise ValueError(f"{_where(cfg_file)}: a hyperparameter is not accepted by {run.algo.upper()}: {exc}") from exc


def _warm_start(model, run: RunSpec, path: str, where: str) -> dict[str, Any]:
    """Copy the policy and the observation statistics of the agent at ``path`` (config key
    ``init_from``) into the new ``model``; what was copied, for the metadata. ValueError naming
    ``init_from`` when the agent cannot be loaded or does not fit the run."""
    import copy

    from .loading import load_agent

    try:
        src, meta, norm = load_agent(path)
    except ValueError as exc:
        raise ValueError(f"{where}: init_from: {exc}") from None
    if meta["mode"] != run.mode:
        raise ValueError(f"{where}: init_from: {path} is a {meta['mode']} agent; this run is {run.mode}")
    if src.observation_space != model.observation_space or src.action_space != model.action_space:
        raise ValueError(f"{where}: init_from: {path}'s spaces ({src.observation_space}, {src.action_space}) "
                         f"differ from this run's ({model.observation_space}, {model.action_space})")
    if not hasattr(src.policy, "state_dict") or type(src.policy) is not type(model.policy):
        raise ValueError(f"{where}: init_from: {path}'s policy is a {type(src.policy).__module__}."
                         f"{type(src.policy).__name__}; this run's is a {type(model.policy).__module__}."
                         f"{type(model.policy).__name__}")
    for attr in ("activation_fn", "squash_output"):  # same shapes, other functions: not caught below
        if getattr(src.policy, attr, None) != getattr(model.policy, attr, None):
            raise ValueError(f"{where}: init_from: {path}'s policy has {attr} {getattr(src.policy, attr, None)}; "
                             f"this run's has {getattr(model.policy, attr, None)}")
    try:
        model.policy.load_state_dict(src.policy.state_dict())
    except RuntimeError as exc:
        first = str(exc).strip().splitlines()
        raise ValueError(f"{where}: init_from: {path}'s policy ({type(src.policy).__name__}) does not fit this "
                         f"run's ({type(model.policy).__name__}, policy_kwargs): {' '.join(first[:2])}") from None
    target = model.get_vec_normalize_env()
    if (norm is None) != (target is None):
        raise ValueError(f"{where}: init_from: {path} was trained with normalize: {norm is not None}; "
                         f"this run has normalize: {target is not None}, so its observations would be scaled "
                         "differently")
    if norm is not None:
        target.obs_rms = copy.deepcopy(norm.obs_rms)
        if bool(norm.norm_reward) != bool(target.norm_reward):
            print(f"blf-train: init_from: {path} was trained with normalize_reward {bool(norm.norm_reward)}, this run "
                  f"has {bool(target.norm_reward)}: its value head starts on another scale", file=sys.stderr)
    return {"path": str(path), "name": meta.get("name"), "algo": meta.get("algo"),
            "timesteps": meta.get("timesteps"), "git_commit": meta.get("git_commit")}


def _segments(prior: dict[str, Any] | None, resume: bool, start_steps: int, command: str | None
              ) -> tuple[list[dict[str, Any]], dict[str, Any]]:
    """The run's segments so far (one per process that trained it; a segment left "running" by a
    process that died is closed as "killed") and this process's new one, appended."""
    segments = list(prior.get("segments") or []) if (resume and prior) else []
    if resume and prior and not segments and "wall_s" in prior:  # a run recorded before segments existed
        segments = [{"start_timesteps": 0, "end_timesteps": int(prior.get("timesteps", 0)),
                     "wall_s": float(prior["wall_s"]), "status": "completed" if prior.get("completed")
                     else "interrupted"}]
    for s in segments:
        if s.get("status") == "running":
            s["status"] = "killed"  # its process ended without closing the record
    segment = {"start_timesteps": start_steps, "end_timesteps": start_steps, "wall_s": 0.0,
               "started": time.strftime("%Y-%m-%dT%H:%M:%S%z"), "status": "running", "command": command}
    segments.append(segment)
    return segments, segment


def _save_final(model, ckpt_dir: Path, out: Path, state: dict[str, Any]) -> None:
    """The run's last checkpoint (``state`` stored with it), then ``model.zip`` and
    ``vecnormalize.pkl``, each written atomically."""
    from blf_gym.results.io import atomic_path

    from .checkpoints import save_checkpoint

    # every run ends on a checkpoint, so it can be resumed or extended from where it stopped
    save_checkpoint(model, ckpt_dir, state)
    norm = model.get_vec_normalize_env()
    if norm is not None:
        with atomic_path(out / "vecnormalize.pkl") as tmp:
            norm.save(str(tmp))
    with atomic_path(out / "model.zip") as tmp:
        model.save(tmp)


@dataclass(frozen=True)
class TrainRequest:
    """One training call as the caller states it (:func:`train`'s arguments; None: the resumed run's
    own setting, else the config's, else the default)."""

    algo: str | None = None
    mode: str | None = None
    controller: str | None = None
    scenario: str | None = None
    timesteps: int | None = None
    seed: int | None = None
    config: str | Path | None = None
    out: Path = Path("runs/run")
    resume: bool = False
    progress: bool = True
    name: str | None = None
    command: str | None = None
    observer: str | None = None
    overrides: Mapping[str, Any] | Sequence[str] = ()
    time_budget_s: float | None = None


@dataclass
class _Plan:
    """The run once settled: the request checked against its folder, the config read."""

    req: TrainRequest
    out: Path
    meta_path: Path
    ckpt_dir: Path
    prior: dict[str, Any] | None
    run: RunSpec
    cfg: dict[str, Any]
    cfg_file: str
    tc: TrainConfig
    env_kwargs: dict[str, Any]
    time_budget_s: float | None

    @property
    def timesteps(self) -> int:
        return self.run.timesteps

    @property
    def seed(self) -> int:
        return self.run.seeds[0]


@dataclass
class _Start:
    """Where training starts: the model (new, warm-started or restored from a checkpoint), its step
    count and wall time so far, and what its checkpoint stored."""

    model: Any
    steps: int = 0
    model_wall: float = 0.0
    with_buffer: bool = False
    ck_state: dict[str, Any] = field(default_factory=dict)
    spent_before: bool = False
    warm: dict[str, Any] | None = None


def train(
    algo: str | None = None,
    mode: str | None = None,
    controller: str | None = None,
    scenario: str | None = None,
    timesteps: int | None = None,
    seed: int | None = None,
    config: str | Path | None = None,
    out: str | Path = "runs/run",
    resume: bool = False,
    progress: bool = True,
    name: str | None = None,
    command: str | None = None,
    observer: str | None = None,
    overrides: Mapping[str, Any] | Sequence[str] = (),
    time_budget_s: float | None = None,
) -> Path:
    """Train (or resume, or extend) one agent; returns the run folder. See the module docstring.

    ``time_budget_s`` ends the run, as completed, once the wall time that produced its model (over
    all its segments, curve evaluations included) reaches it, even short of ``timesteps``: "as many
    steps as this wall clock allows". A resume keeps the run's budget unless given a new one, and a
    larger one extends a run that its budget ended.

    ``overrides`` sets config keys over the file's: {dotted key: value}, or ``KEY=VALUE`` strings as
    ``--set`` takes them (``agents.config.SET_HELP``).

    Defaults: ppo, residual over the proposed law, paper-0.1hz, 100,000 steps, seed 0. With
    ``resume=True`` the run's own settings (``metadata.json``) are used, ``timesteps`` defaults to
    the run's requested total, and a larger ``timesteps`` extends a finished run.
    """
    return run_training(TrainRequest(algo, mode, controller, scenario, timesteps, seed, config, Path(out), resume,
                                     progress, name, command, observer, overrides, time_budget_s))


def run_training(req: TrainRequest) -> Path:
    """:func:`train` over a :class:`TrainRequest`, in its named steps: settle the run, build the
    envs, build or resume the model, record the run and make the callbacks, learn, save."""
    plan = _plan(req)
    cls = _learner(plan)
    venv = _build_envs(plan)
    start = _build_or_resume(plan, cls, venv)
    if isinstance(start, Path):  # a resume with nothing to do
        return start
    session = _Session(plan, start, cls)
    interrupted = _learn(plan, session, _callbacks(plan, session))
    _save(plan, session, interrupted)
    venv.close()
    print(f"blf-train: wrote {plan.out / 'model.zip'} and {plan.meta_path} ({session.model.num_timesteps} steps)")
    return plan.out


def _plan(req: TrainRequest) -> _Plan:
    """The request checked against the run folder (a new run, or one to resume) and its time budget,
    and the run's spec and config settled (:func:`_settle`)."""
    out, budget = Path(req.out), req.time_budget_s
    if budget is not None and not (np.isfinite(budget) and budget > 0):
        raise ValueError(f"--time-budget must be a number of seconds > 0, got {budget!r}")
    meta_path = out / "metadata.json"
    ckpt_dir = out / "checkpoints"
    prior = _read_metadata(meta_path) if meta_path.is_file() else None
    if req.resume and prior is not None:
        recorded = prior.get("time_budget_s")
        if recorded is not None and budget is not None and budget < float(recorded):
            raise ValueError(f"--time-budget {budget:g} is below the run's budget of {float(recorded):g} s "
                             f"({meta_path}); a resume keeps a run's budget or extends it")
        if budget is None and recorded is not None:
            budget = float(recorded)
    if not req.resume and prior is not None:
        raise ValueError(f"{out} already holds a run; pass --resume to continue it (or --resume --timesteps N "
                         "to extend it), or choose another --out")
    if req.resume and prior is None and not ckpt_dir.is_dir():
        raise ValueError(f"--resume: {out} holds no run to resume (no metadata.json, no checkpoints/)")
    given = {"algo": req.algo, "mode": req.mode, "controller": req.controller, "scenario": req.scenario,
             "seed": req.seed, "observer": req.observer, "name": req.name}
    overrides = req.overrides if isinstance(req.overrides, Mapping) else parse_overrides(req.overrides)
    run, cfg, cfg_file = _settle(given, req.timesteps, req.config, req.resume, prior, meta_path, overrides)
    tc = TrainConfig.of(cfg, _where(cfg_file))
    return _Plan(req, out, meta_path, ckpt_dir, prior, run, cfg, cfg_file, tc, _env_kwargs(run, tc), budget)


def _learner(plan: _Plan):
    """The algorithm's class, with torch on one thread unless OMP_NUM_THREADS asks for more: the env
    has its own, and two runs at once share the two cores (docs/budget.md measures both)."""
    import torch

    from .loading import algorithm_class

    omp = os.environ.get("OMP_NUM_THREADS", "")
    torch.set_num_threads(int(omp) if omp.isdigit() and int(omp) >= 1 else 1)
    return algorithm_class(plan.run.algo)


def _build_envs(plan: _Plan):
    """The training envs: ``n_envs`` arms in one native vector env, monitored; a curriculum's first
    episodes at its width (of the run's last recorded step on a resume)."""
    from stable_baselines3.common.vec_env import VecMonitor

    from .vec_env import BLFVecEnv

    tc, start_env = plan.tc, {}
    if tc.curriculum:
        if "bound_scale" in tc.env:
            raise ValueError(f"{_where(plan.cfg_file)}: env.bound_scale and curriculum both set the funnel's "
                             "width; keep one")
        at = int((plan.prior or {}).get("timesteps", 0)) if plan.req.resume else 0
        start_env["bound_scale"] = curriculum_scale(tc.curriculum, at)
    return VecMonitor(BLFVecEnv(tc.n_envs, seed=plan.seed, threads=1,
                                **{"controller": None, **plan.env_kwargs, **start_env}))


def _build_or_resume(plan: _Plan, cls, venv) -> _Start | Path:
    """The model to train: restored from the run's last complete checkpoint on a resume, else new
    (warm-started when the config says ``init_from``). A resume with nothing left to train returns
    the run folder instead."""
    out, prior, budget = plan.out, plan.prior, plan.time_budget_s
    start = _Start(None)
    if plan.req.resume:
        model, steps, wall, with_buffer, ck_state = _restore(cls, venv, plan.ckpt_dir, plan.tc.normalize, out)
        start = _Start(model, steps, wall, with_buffer, ck_state)
        if model is None:
            if prior is None:
                raise ValueError(f"--resume: no complete checkpoint in {plan.ckpt_dir}")
            print(f"blf-train: no complete checkpoint in {plan.ckpt_dir}; starting {out} again from step 0",
                  file=sys.stderr)
        else:
            if prior is not None and int(prior.get("timesteps", -1)) == steps:
                # a checkpoint keeps the wall time of its writing (a later save at the same step leaves
                # it as it is); the metadata, recorded last, also counts what followed at that step
                # (a curve point, the final save)
                start.model_wall = max(wall, float(prior.get("wall_s_to_model", 0.0)))
            finished = bool(prior is not None and prior.get("completed") and (out / "model.zip").is_file())
            if finished and steps >= plan.timesteps:
                return _nothing_to_do(venv, out, f"already has {steps} steps (requested {plan.timesteps}); nothing "
                                      f"to do. Pass --resume --timesteps N with N > {steps} to extend it.")
            if budget is not None and start.model_wall >= budget:
                if finished:
                    return _nothing_to_do(venv, out, f"has spent its time budget ({start.model_wall:.0f} s of "
                                          f"{budget:g} s, {steps} steps); nothing to do. Pass --resume "
                                          "--time-budget S with a larger S to extend it.")
                # its last job ended (a kill, a restore elsewhere) before it recorded the run as finished
                print(f"blf-train: {out} had spent its time budget ({start.model_wall:.0f} s of {budget:g} s) "
                      f"at its checkpoint of {steps} steps; training nothing, writing its final model",
                      file=sys.stderr)
                start.spent_before = True
    start.warm = (prior or {}).get("init_from") if plan.req.resume else None
    if start.model is None:
        try:
            start.model = _new_model(cls, plan.run, plan.tc, plan.cfg_file, venv, out)
            if plan.tc.init_from:
                start.warm = _warm_start(start.model, plan.run, plan.tc.init_from, _where(plan.cfg_file))
        except BaseException:
            venv.close()  # its worker threads would outlive a refused run in a long-lived process
            raise
    return start


class _Session:
    """One process's stretch of a run (a segment): its model, clock and metadata record, written now
    and after every checkpoint and curve point so that a killed run keeps its record; and, for an
    off-policy learner resumed without a full replay buffer, the refill that fills it first."""

    def __init__(self, plan: _Plan, start: _Start, cls) -> None:
        from blf_gym.results.metrics import provenance

        self.model, self.start = start.model, start
        self.continuing = start.steps > 0
        plan.out.mkdir(parents=True, exist_ok=True)
        self.clock = _RunClock(start.model_wall)
        self.segments, self.segment = _segments(plan.prior, plan.req.resume, start.steps, plan.req.command)
        self.meta_path = plan.meta_path
        prior, req = plan.prior or {}, plan.req
        prov = provenance()
        self.meta: dict[str, Any] = {
            "name": req.name or prior.get("name") or plan.out.name, "algo": plan.run.algo, "mode": plan.run.mode,
            "env_id": ENV_IDS[plan.run.mode], "env_kwargs": dict(plan.env_kwargs), "config_file": plan.cfg_file,
            "config": _stated(plan.cfg), "seed": plan.seed, "timesteps": start.steps,
            "timesteps_requested": plan.timesteps, "time_budget_s": plan.time_budget_s, "status": "running",
            "completed": False, "resumed": len(self.segments) > 1, "wall_s": 0.0, "wall_s_to_model": start.model_wall,
            "segments": self.segments, "versions": prov["versions"], "git_commit": prov["git_commit"],
            "command": prior.get("command") if req.resume else req.command, "host": {"cpus": os.cpu_count()},
        }
        if start.warm:
            self.meta["init_from"] = start.warm
        self.refill, self.gradient_steps, self.until = None, None, 0
        model = self.model
        if self.continuing and hasattr(model, "replay_buffer"):
            # from the config, not the checkpoint: a checkpoint written during a refill holds 0
            self.gradient_steps = int(_configured(cls, plan.tc, "gradient_steps"))
            model.gradient_steps = self.gradient_steps
            if not start.with_buffer:  # e.g. a checkpoint kept without it (docs/budget/keep.sh)
                self.until = start.steps + max(int(_configured(cls, plan.tc, "learning_starts")),
                                               int(model.batch_size))
            # a checkpoint written during a refill holds a part-filled buffer: the refill goes on
            self.until = max(self.until, int(start.ck_state.get("refill_until", 0)))
            if self.until > start.steps:
                print(f"blf-train: {plan.out}'s checkpoint has {'a part-refilled' if start.with_buffer else 'no'} "
                      f"replay buffer; the policy fills it without updates until step {self.until}", file=sys.stderr)
                self.segment["replay_buffer"] = {"resumed": start.with_buffer, "refilled_until": self.until}
                self.refill = _make_refill_callback(model, self.until, self.gradient_steps)
        self.record()

    def record(self, status: str = "running") -> None:
        """Write the run's metadata with this segment's progress (atomically)."""
        self.segment["end_timesteps"] = int(self.model.num_timesteps)
        self.segment["wall_s"] = round(self.clock.segment(), 3)
        self.segment["status"] = status
        meta = self.meta
        meta["timesteps"] = int(self.model.num_timesteps)
        meta["wall_s"] = round(sum(float(s.get("wall_s", 0.0)) for s in self.segments), 3)
        meta["wall_s_to_model"] = round(self.clock.model(), 3)
        meta["status"] = status
        meta["completed"] = status == "completed"
        atomic_write_json(self.meta_path, meta)

    def ck_state(self) -> dict[str, Any]:
        """What a checkpoint stores beside its files: the training wall time so far, and the step
        an unfinished refill runs to."""
        extra = {"refill_until": self.until} if self.refill is not None and self.model.num_timesteps < self.until \
            else {}
        return {"wall_s_to_model": round(self.clock.model(), 3), **extra}


def _callbacks(plan: _Plan, session: _Session) -> list[Any]:
    """SB3 callbacks: atomic checkpoints, the learning curve, the progress bar, and as configured the
    curriculum, the replay buffer's refill and the time budget."""
    from .checkpoints import AtomicCheckpointCallback

    tc, run = plan.tc, plan.run
    freq = max(1, tc.checkpoint_freq // tc.n_envs)
    progress = _make_progress_callback(plan.timesteps, session.start.steps, plan.req.progress)
    callbacks = [
        AtomicCheckpointCallback(freq, str(plan.ckpt_dir), state=session.ck_state,
                                 on_saved=lambda _folder: session.record(), name_prefix="model",
                                 save_replay_buffer=True, save_vecnormalize=tc.normalize),
        _make_curve_callback(tc.eval_freq, plan.out, plan.env_kwargs,
                             {"name": session.meta["name"], "mode": run.mode, "env_kwargs": plan.env_kwargs},
                             tc.curve_suite_seeds, session.clock, on_point=session.record, status=progress.status,
                             total=plan.timesteps),
        progress,
    ]
    if tc.curriculum:
        callbacks.append(_make_curriculum_callback(tc.curriculum))
    if session.refill is not None:
        callbacks.append(session.refill)
    if plan.time_budget_s is not None:
        callbacks.append(_make_time_budget_callback(session.clock, plan.time_budget_s))
    return callbacks


def _learn(plan: _Plan, session: _Session, callbacks: list[Any]) -> bool:
    """SB3's ``learn`` for the steps left; True if a KeyboardInterrupt cut it short."""
    from stable_baselines3.common.callbacks import CallbackList

    model = session.model
    remaining = 0 if session.start.spent_before else max(0, plan.timesteps - session.start.steps)
    try:
        if not session.start.spent_before:
            model.learn(remaining, callback=CallbackList(callbacks), reset_num_timesteps=not session.continuing,
                        tb_log_name=plan.run.algo)
    except KeyboardInterrupt:
        print(f"\nblf-train: interrupted at {model.num_timesteps} steps; resume with --resume "
              f"--out {plan.out}", file=sys.stderr)
        return True
    return False


def _save(plan: _Plan, session: _Session, interrupted: bool) -> None:
    """The final checkpoint, model and statistics, their sha256 in the metadata, and the run's
    status. A SIGTERM now (a scheduler's at the budget, a second one, a dying parent's) must not cut
    the final save short: it is ignored until the run is recorded."""
    import threading

    from .loading import file_hashes

    model = session.model
    main_thread = threading.current_thread() is threading.main_thread()
    previous = signal.signal(signal.SIGTERM, signal.SIG_IGN) if main_thread else None
    if session.gradient_steps is not None:  # a refill cut short must not be saved as the run's setting
        model.gradient_steps = session.gradient_steps
    try:
        print(f"blf-train: saving {plan.out} (checkpoint, model, statistics)", file=sys.stderr, flush=True)
        _save_final(model, plan.ckpt_dir, plan.out, session.ck_state())
        session.meta["files"] = file_hashes(plan.out)  # what the loader checks the folder against (agents.loading)
        budget = plan.time_budget_s
        spent = budget is not None and session.clock.model() >= budget
        done = not interrupted and (model.num_timesteps >= plan.timesteps or spent)
        session.record("completed" if done else "interrupted")
    finally:
        if main_thread:
            signal.signal(signal.SIGTERM, previous)


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="blf-train", description=help_text(__doc__.split("\n\n")[0]),
                                formatter_class=argparse.RawDescriptionHelpFormatter,
                                epilog="With --resume, the run's own algo, mode, controller, scenario, seed and "
                                       "config are used (an option that contradicts them is refused).")
    from .loading import available_algorithms

    p.add_argument("--algo", default=None, choices=available_algorithms(),
                   help="SB3 algorithm (default ppo; tqc needs sb3-contrib; ppo has the tuned residual config)")
    p.add_argument("--mode", default=None, choices=MODES,
                   help="plain: the action is the torque; residual: added to the inner law (default residual)")
    p.add_argument("--controller", default=None, metavar="NAME",
                   help="inner law in residual mode: bc, lesobc, proposed or a registered plug-in "
                        "(default proposed)")
    p.add_argument("--observer", default=None, metavar="NAME",
                   help="observer plug-in of the env (registered in blf_gym.observers; default leso)")
    p.add_argument("--scenario", default=None, metavar="NAME",
                   help="training scenario: paper-0.1hz, paper-0.5hz or randomized (default paper-0.1hz)")
    p.add_argument("--timesteps", type=int, default=None, metavar="N",
                   help="total agent steps, one per control_period (default 100000; with --resume, the "
                        "run's requested total, and a larger N extends a finished run)")
    p.add_argument("--time-budget", type=float, default=None, metavar="S",
                   help="end the run, as completed, once its model has taken S seconds of wall clock over all "
                        "its segments, even short of --timesteps (default: none; with --resume, the run's own, "
                        "which a larger S extends)")
    p.add_argument("--seed", type=int, default=None, metavar="S",
                   help="seed of the networks, the envs and the scenario draws (default 0)")
    p.add_argument("--config", default=None, metavar="YAML",
                   help="hyperparameters (default agents/configs/<algo>_<env id>.yaml)")
    add_config_options(p)
    p.add_argument("--out", default="runs/run", metavar="DIR", help="run folder (default runs/run)")
    p.add_argument("--name", default=None,
                   help="agent name in results (default: the run folder's name)")
    p.add_argument("--resume", action="store_true",
                   help="continue the run in --out from its newest complete checkpoint (default off)")
    p.add_argument("--no-progress", action="store_true", help="hide the progress bar (default: shown)")
    return p


def main(argv: Sequence[str] | None = None) -> int:
    import shlex

    argv = list(sys.argv[1:] if argv is None else argv)
    args = _parser().parse_args(argv)
    # a scheduler's SIGTERM ends the run like Ctrl-C: a final checkpoint and metadata are written
    previous = signal.signal(signal.SIGTERM, signal.default_int_handler)
    try:
        out = train(algo=args.algo, mode=args.mode, controller=args.controller, scenario=args.scenario,
                    timesteps=args.timesteps, seed=args.seed, config=args.config, out=args.out, resume=args.resume,
                    progress=not args.no_progress, name=args.name, command=shlex.join(["blf-train", *argv]),
                    observer=args.observer, overrides=args.overrides, time_budget_s=args.time_budget)
    except ValueError as exc:
        print(f"blf-train: error: {exc}", file=sys.stderr)
        return 2
    except OSError as exc:
        print(f"blf-train: error: cannot write {exc.filename or args.out}: {exc.strerror or exc}", file=sys.stderr)
        return 2
    finally:
        signal.signal(signal.SIGTERM, previous)
    meta = json.loads((out / "metadata.json").read_text())
    return 130 if meta.get("status") == "interrupted" else 0


if __name__ == "__main__":
    raise SystemExit(main())
