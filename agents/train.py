"""``blf-train`` (also ``python -m agents.train``): train an SB3 agent on PlanarBLF.

Examples::

    blf-train --mode residual --scenario randomized --timesteps 1000000 --out runs/ppo_residual
    blf-train --algo sac --mode residual --timesteps 200000 --out runs/sac_residual
    blf-train --algo ppo --mode plain --scenario randomized --seed 3 --out runs/ppo_plain
    blf-train --resume --out runs/ppo_residual          # continue an interrupted run

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
import json
import os
import platform
import subprocess
import sys
import time
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from blf_gym.io import atomic_write_json

__all__ = ["main", "load_config", "train"]

CONFIG_DIR = Path(__file__).resolve().parent / "configs"
ALGOS = ("ppo", "sac", "td3", "tqc")
MODES = ("plain", "residual")
ENV_IDS = {"plain": "PlanarBLF-v0", "residual": "PlanarBLFResidual-v0"}
ENV_KEYS = ("control_period", "residual_scale", "privileged", "reward_weights", "angle_noise_std",
            "variations", "duration", "max_torque")
CONFIG_KEYS = ("policy", "n_envs", "normalize", "env", "hyperparams", "policy_kwargs", "action_noise_std",
               "normalize_reward", "eval_freq", "curve_suite_seeds", "checkpoint_freq", "note")


def load_config(path: str | Path) -> dict[str, Any]:
    """Read a YAML config and reject unknown keys by name."""
    import yaml

    path = Path(path)
    if not path.is_file():
        raise ValueError(f"config not found: {path}")
    cfg = yaml.safe_load(path.read_text()) or {}
    unknown = sorted(set(cfg) - set(CONFIG_KEYS))
    if unknown:
        raise ValueError(f"{path}: unknown config key(s) {unknown}; accepted: {list(CONFIG_KEYS)}")
    env_unknown = sorted(set(cfg.get("env", {}) or {}) - set(ENV_KEYS))
    if env_unknown:
        raise ValueError(f"{path}: unknown env key(s) {env_unknown}; accepted: {list(ENV_KEYS)}")
    for key in ("n_envs", "eval_freq", "checkpoint_freq", "curve_suite_seeds"):
        v = cfg.get(key)
        if v is not None and (isinstance(v, bool) or not isinstance(v, int) or v < 1):
            raise ValueError(f"{path}: {key} must be an integer >= 1, got {v!r}")
    return cfg


def _algo_class(name: str):
    import stable_baselines3 as sb3

    if name == "tqc":
        try:
            from sb3_contrib import TQC
        except ImportError as exc:
            raise ValueError("--algo tqc needs sb3-contrib (pip install sb3-contrib)") from exc
        return TQC
    return {"ppo": sb3.PPO, "sac": sb3.SAC, "td3": sb3.TD3}[name]


def _versions() -> dict[str, str]:
    import importlib.metadata as md

    out = {"python": platform.python_version()}
    for pkg in ("blf-gym", "numpy", "numba", "gymnasium", "stable-baselines3", "torch", "sb3-contrib"):
        try:
            out[pkg] = md.version(pkg)
        except md.PackageNotFoundError:
            pass
    return out


def _git_commit() -> str | None:
    try:
        return subprocess.run(["git", "rev-parse", "HEAD"], cwd=Path(__file__).parent, capture_output=True,
                              text=True, timeout=5, check=True).stdout.strip() or None
    except (OSError, subprocess.SubprocessError):
        return None


def _latest_checkpoint(ckpt: Path) -> tuple[Path, int] | None:
    best = None
    for f in ckpt.glob("model_*_steps.zip"):
        try:
            steps = int(f.stem.split("_")[1])
        except (IndexError, ValueError):
            continue
        if best is None or steps > best[1]:
            best = (f, steps)
    return best


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

    return _Progress()


def _schedule(spec: str, where: str):
    """``"lin_<x>"``: a value decaying linearly from x to 0 over training (rl-zoo's notation)."""
    try:
        if not spec.startswith("lin_"):
            raise ValueError
        start = float(spec[4:])
    except ValueError:
        raise ValueError(f"{where} must be a number or 'lin_<number>' (linear decay to 0), got {spec!r}") from None

    def value(progress_remaining: float) -> float:
        return progress_remaining * start

    return value


def _make_curve_callback(every: int, out: Path, env_kwargs: dict[str, Any], meta: dict[str, Any],
                         suite_seeds: int, start_wall: float):
    """Learning curves: at the start, every ``every`` agent steps and at the end, score the
    deterministic policy with blf-eval's metrics on both paper presets and ``suite_seeds`` held-out
    randomized-suite episodes, and append the records to ``out/eval/curve.json`` (atomic; kept
    across ``--resume``)."""
    from stable_baselines3.common.callbacks import BaseCallback
    from stable_baselines3.common.vec_env import VecNormalize

    from blf_gym.metrics import summarize

    from .evaluate import build_scenarios, evaluate_agent

    path = out / "eval" / "curve.json"
    groups = build_scenarios(["paper-0.1hz", "paper-0.5hz"], suite_seeds, {}, env_kwargs.get("duration"))

    class _Curve(BaseCallback):
        def _on_training_start(self) -> None:
            self._t0 = time.time()
            self.points = json.loads(path.read_text())["points"] if path.is_file() else []
            # after --resume, points past the checkpoint belong to the abandoned stretch
            self.points = [p for p in self.points if p["timesteps"] <= self.num_timesteps]
            self.next_at = (self.num_timesteps // every + 1) * every
            if not self.points:
                self._evaluate()  # the untrained policy (for a residual agent, about the law alone)

        def _evaluate(self) -> None:
            env = self.model.get_env()
            norm = env if isinstance(env, VecNormalize) else None
            point: dict[str, Any] = {"timesteps": int(self.num_timesteps),
                                     "wall_s": round(start_wall + time.time() - self._t0, 1)}
            for label, scs in groups:
                trajs = evaluate_agent(self.model, meta, norm, scs, threads=1)
                rec = summarize(trajs, meta["name"], meta["mode"], label, scs[0].sim.dt)
                point[label] = {k: rec[k] for k in ("rmse_deg", "violations", "failure_rate", "diverged")}
            self.points.append(point)
            atomic_write_json(path, {"env_kwargs": env_kwargs, "suite_seeds": suite_seeds,
                                     "points": self.points})

        def _on_step(self) -> bool:
            if self.num_timesteps >= self.next_at:
                self._evaluate()
                self.next_at = (self.num_timesteps // every + 1) * every
            return True

        def _on_training_end(self) -> None:
            # the curve ends at the model that is saved
            if self.points and self.points[-1]["timesteps"] != self.num_timesteps:
                self._evaluate()

    return _Curve()


def train(
    algo: str = "ppo",
    mode: str = "residual",
    controller: str | None = None,
    scenario: str = "paper-0.1hz",
    timesteps: int = 100_000,
    seed: int = 0,
    config: str | Path | None = None,
    out: str | Path = "runs/run",
    resume: bool = False,
    progress: bool = True,
    name: str | None = None,
) -> Path:
    """Train (or resume) one agent; returns the run folder. See the module docstring."""
    if algo not in ALGOS:
        raise ValueError(f"unknown algo {algo!r}; accepted values: {list(ALGOS)}")
    if mode not in MODES:
        raise ValueError(f"unknown mode {mode!r}; accepted values: {list(MODES)}")
    if timesteps < 1:
        raise ValueError(f"timesteps must be >= 1, got {timesteps}")
    from blf_gym.controller import available_controllers
    from blf_gym.scenarios import resolve_scenario

    if mode == "plain" and controller is not None:
        raise ValueError("--controller applies to --mode residual only (plain mode has no inner law)")
    controller = controller or "proposed"
    if mode == "residual" and controller not in available_controllers():
        raise ValueError(f"unknown controller {controller!r}; accepted values: {available_controllers()}")
    resolve_scenario(scenario)
    out = Path(out)
    if not resume and (out / "metadata.json").exists():
        raise ValueError(f"{out} already holds a run; pass --resume to continue it, or choose another --out")
    cfg_path = Path(config) if config else CONFIG_DIR / f"{algo}_{ENV_IDS[mode]}.yaml"
    cfg = load_config(cfg_path)
    if cfg.get("normalize_reward") and not cfg.get("normalize"):
        raise ValueError(f"{cfg_path}: normalize_reward needs normalize: true")
    env_kwargs: dict[str, Any] = {"scenario": scenario, **(cfg.get("env") or {})}
    if mode == "residual":
        env_kwargs["controller"] = controller

    import torch
    from stable_baselines3.common.callbacks import CallbackList, CheckpointCallback
    from stable_baselines3.common.noise import NormalActionNoise
    from stable_baselines3.common.vec_env import VecMonitor, VecNormalize

    from .vec_env import BLFVecEnv

    torch.set_num_threads(1)
    cls = _algo_class(algo)
    n_envs = int(cfg.get("n_envs", 1))
    venv = VecMonitor(BLFVecEnv(n_envs, seed=seed, threads=1, **env_kwargs))
    ckpt_dir = out / "checkpoints"
    start_steps = 0
    t_start = time.time()
    prior_wall = 0.0
    if resume:
        latest = _latest_checkpoint(ckpt_dir)
        if latest is None:
            raise ValueError(f"--resume: no checkpoint in {ckpt_dir}")
        ckpt, start_steps = latest
        if cfg.get("normalize"):
            stats = ckpt_dir / f"model_vecnormalize_{start_steps}_steps.pkl"
            venv = VecNormalize.load(str(stats), venv)
        model = cls.load(ckpt, env=venv, device="cpu")
        buf = ckpt_dir / f"model_replay_buffer_{start_steps}_steps.pkl"
        if hasattr(model, "replay_buffer") and buf.is_file():
            model.load_replay_buffer(buf)
        meta_old = out / "metadata.json"
        if meta_old.is_file():
            prior_wall = float(json.loads(meta_old.read_text()).get("wall_s_at_checkpoint", 0.0))
    else:
        if cfg.get("normalize"):
            venv = VecNormalize(venv, norm_obs=True, norm_reward=bool(cfg.get("normalize_reward", False)),
                                gamma=float((cfg.get("hyperparams") or {}).get("gamma", 0.99)))
        kwargs = dict(cfg.get("hyperparams") or {})
        for key in ("learning_rate", "clip_range"):
            if isinstance(kwargs.get(key), str):
                kwargs[key] = _schedule(kwargs[key], f"{cfg_path}: hyperparams.{key}")
        if cfg.get("policy_kwargs"):
            kwargs["policy_kwargs"] = dict(cfg["policy_kwargs"])
        if cfg.get("action_noise_std") and algo in ("td3", "sac", "tqc"):
            kwargs["action_noise"] = NormalActionNoise(np.zeros(3), float(cfg["action_noise_std"]) * np.ones(3))
        tb = None
        try:
            import tensorboard  # noqa: F401

            tb = str(out / "tb")
        except ImportError:
            print("blf-train: tensorboard is not installed; no TensorBoard logs", file=sys.stderr)
        try:
            model = cls(cfg.get("policy", "MlpPolicy"), venv, seed=seed, device="cpu", tensorboard_log=tb,
                        verbose=0, **kwargs)
        except TypeError as exc:
            raise ValueError(f"{cfg_path}: a hyperparameter is not accepted by {algo.upper()}: {exc}") from exc
    out.mkdir(parents=True, exist_ok=True)
    freq = max(1, int(cfg.get("checkpoint_freq", 10_000)) // n_envs)
    callbacks = [
        CheckpointCallback(freq, str(ckpt_dir), name_prefix="model", save_replay_buffer=True,
                           save_vecnormalize=bool(cfg.get("normalize"))),
        _make_curve_callback(int(cfg.get("eval_freq", 20_000)), out, env_kwargs,
                             {"name": name or out.name, "mode": mode, "env_kwargs": env_kwargs},
                             int(cfg.get("curve_suite_seeds", 4)), prior_wall),
        _make_progress_callback(timesteps, start_steps, progress),
    ]
    remaining = max(0, timesteps - start_steps)
    interrupted = False
    try:
        model.learn(remaining, callback=CallbackList(callbacks), reset_num_timesteps=not resume,
                    tb_log_name=algo)
    except KeyboardInterrupt:
        interrupted = True
        print(f"\nblf-train: interrupted at {model.num_timesteps} steps; resume with --resume "
              f"--out {out}", file=sys.stderr)
    wall = prior_wall + time.time() - t_start
    model.save(out / "model.zip")
    if isinstance(model.get_env(), VecNormalize):
        model.get_env().save(str(out / "vecnormalize.pkl"))
    meta = {
        "name": name or out.name,
        "algo": algo,
        "mode": mode,
        "env_id": ENV_IDS[mode],
        "env_kwargs": {k: v for k, v in env_kwargs.items()},
        "config_file": str(cfg_path),
        "config": cfg,
        "seed": seed,
        "timesteps": int(model.num_timesteps),
        "timesteps_requested": timesteps,
        "completed": not interrupted and model.num_timesteps >= timesteps,
        "wall_s": wall,
        "wall_s_at_checkpoint": wall,
        "versions": _versions(),
        "git_commit": _git_commit(),
        "command": " ".join(["blf-train", *sys.argv[1:]]) if sys.argv and "blf-train" in sys.argv[0] else None,
        "host": {"cpus": os.cpu_count()},
    }
    atomic_write_json(out / "metadata.json", meta)
    venv.close()
    return out


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="blf-train", description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    p.add_argument("--algo", default="ppo", choices=ALGOS,
                   help="SB3 algorithm (tqc needs sb3-contrib; ppo has the tuned residual config)")
    p.add_argument("--mode", default="residual", choices=MODES,
                   help="plain: the action is the torque; residual: added to the inner law")
    p.add_argument("--controller", default=None,
                   help="inner law in residual mode: bc, lesobc, proposed (default proposed)")
    p.add_argument("--scenario", default="paper-0.1hz",
                   help="training scenario: paper-0.1hz, paper-0.5hz or randomized")
    p.add_argument("--timesteps", type=int, default=100_000, help="total agent steps (10 ms each by default)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--config", default=None, help="YAML hyperparameters (default agents/configs/<algo>_<env id>.yaml)")
    p.add_argument("--out", default="runs/run", help="run folder")
    p.add_argument("--name", default=None, help="agent name in results (default: the run folder's name)")
    p.add_argument("--resume", action="store_true", help="continue from the latest checkpoint in --out")
    p.add_argument("--no-progress", action="store_true", help="hide the progress bar")
    return p


def main(argv: Sequence[str] | None = None) -> int:
    args = _parser().parse_args(argv)
    try:
        out = train(args.algo, args.mode, args.controller, args.scenario, args.timesteps, args.seed,
                    args.config, args.out, args.resume, not args.no_progress, args.name)
    except ValueError as exc:
        print(f"blf-train: error: {exc}", file=sys.stderr)
        return 2
    print(f"blf-train: wrote {out / 'model.zip'} and {out / 'metadata.json'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
