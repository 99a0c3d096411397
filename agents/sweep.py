"""``blf-sweep`` (also ``python -m agents.sweep``): many ``blf-train`` runs, scheduled by Ray Tune.

A sweep is one YAML file (``agents/configs/sweeps/`` has examples; docs/sweeps.md is the guide)::

    name: smoke                    # the runs are named <name>-<config id>_s<seed>
    base: ../ppo_PlanarBLFResidual-v0.yaml   # the blf-train config (relative to this file)
    algo: ppo                      # blf-train --algo, --mode, --controller, --observer, --scenario
                                   # (any registered plug-in by name; never the stress suite)
    mode: residual
    scenario: randomized
    timesteps: 2048                # the budget of every trial, in agent steps
    seeds: [0, 1]                  # every configuration is trained once per seed
    search: random                 # grid | random | optuna (Optuna's TPE, through Ray's OptunaSearch)
    num_samples: 2                 # configurations to sample (random, optuna)
    search_seed: 0                 # seed of the sampler
    overrides: {eval_freq: 1024}   # fixed changes to the base config, by dotted key
    space:                         # the search space, by dotted key (config keys and env kwargs)
      hyperparams.learning_rate: {loguniform: [1.0e-4, 1.0e-3]}
      env.residual_scale: {choice: [4.0, 8.0]}
    scheduler: {asha: {grace_period: 1024, reduction_factor: 2}}   # optional early stopping

Distributions: Ray Tune's names (``uniform``, ``loguniform``, ``quniform: [lo, hi, q]``,
``randint: [lo, hi)``, ``lograndint``, ``choice``, ``grid``) or Optuna's
(``float: {low, high, log, step}``, ``int: {low, high, log, step}`` with ``high`` included,
``categorical``). ``config: {grid: [a.yaml, b.yaml]}`` searches over whole config files.

**The objective** is the benchmark's ``score_vs_law`` at each learning-curve point that
``blf-train`` writes (``eval/curve.json``): per group, the geometric mean over joints of the law's
RMSE over the policy's, on the two paper presets and the held-out training-suite episodes, pooled
over the three groups by their geometric mean. The stress suite is never read. **A violation
loses**: a point at which any curve episode failed (a bound crossed, or the simulation diverged)
scores minus the fraction of curve episodes that failed, a number in [-1, 0), below every point
without a failure (score_vs_law > 0). The searcher sees each configuration's objective averaged
over its seeds (Ray's ``Repeater``); the ranked table puts every configuration with a failed
episode on any seed below every configuration without one.

Every trial is a real ``blf-train`` process with its own folder ``OUT/runs/<run>`` (model, curve,
metadata, ``config.yaml``, ``trial.json`` with the exact command, ``train.log``), so ``blf-eval
--agents OUT/runs/<run>`` re-evaluates it and the recorded command reproduces it bit for bit.

Local by default: a Ray instance on this machine with one trial per core. ``--address`` (or
``RAY_ADDRESS``) runs the same sweep on an existing cluster. An interrupted sweep resumes with the
same command (Ray Tune's restore; finished trials are kept, unfinished ones continue from their
``blf-train`` checkpoints). ``OUT/sweep.json`` and ``OUT/sweep.md`` (the ranked table) are
rewritten as trials finish.
"""

from __future__ import annotations

import argparse
import copy
import hashlib
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Any, Callable, Mapping, Sequence

import numpy as np

from blf_gym.results.io import atomic_write_json, atomic_write_text, help_text
from blf_gym.model.params import is_integer, is_real

from .config import (CONFIG_KEYS, RunSpec, TrainConfig, add_config_options, check_config, env_keys, parse_overrides, set_dotted,
                     shipped_config)
from blf_gym.envs.protocol import CURVE_GROUPS
from .train import PAUSE_ENV

__all__ = ["main", "load_sweep", "score_point", "law_levels", "run_sweep", "trial_config"]

SPEC_KEYS = ("name", "base", "algo", "mode", "controller", "observer", "scenario", "timesteps", "seeds", "search",
             "num_samples", "search_seed", "overrides", "space", "scheduler", "concurrency", "time_budget_s",
             "note")
SEARCHES = ("grid", "random", "optuna")
RAY_DISTS = {"uniform": 2, "loguniform": 2, "quniform": 3, "qloguniform": 3, "randint": 2, "lograndint": 2}
LIST_DISTS = ("choice", "grid", "categorical")
OPTUNA_DISTS = ("float", "int")
# keys a space may not search: every trial of a sweep is scored against the law on the same scenarios
FIXED_KEYS = ("curve_suite_seeds", "env.duration")
SWEEP_EXTRA = "pip install -c constraints-cpu.txt -e \".[sweep]\"  (or pip install \"blf-gym[sweep]\")"


# ---------------------------------------------------------------------------------------------
# the score


def law_levels(suite_seeds: int, duration: float | None = None, controller: str = "proposed",
               level: int = 3) -> dict[str, list[float]]:
    """RMSE (deg, per joint) of a baseline controller on the learning-curve scenarios at ``level``."""
    from blf_gym.results.metrics import summarize

    from .evaluate import controller_episodes, curve_scenarios

    out = {}
    for label, scs in curve_scenarios(suite_seeds, duration, level):
        # episodes reduced as they come (summarize consumes the generator): memory does not grow with them
        rec = summarize(controller_episodes(controller, scs, threads=1), controller, "baseline", label, scs[0].sim.dt)
        out[label] = [float(v) for v in rec["rmse_deg"]]
    return out


def score_point(point: dict[str, Any], law: dict[str, list[float]], suite_seeds: int) -> dict[str, Any]:
    """One learning-curve point scored against the law: per-group RMSE ratios and scores, the
    pooled ``score_vs_law`` (geometric mean of the three groups' scores, which is 1 / the geometric
    mean of the nine per-joint ratios), failures, and the sweep's ``objective`` (see the module
    docstring: -failed fraction if any curve episode failed, else score_vs_law)."""
    from blf_gym.results.metrics import score_vs_law

    row: dict[str, Any] = {"timesteps": int(point["timesteps"]), "wall_s": float(point.get("wall_s", 0.0))}
    ratios, failed, episodes = [], 0, 0
    for g in CURVE_GROUPS:
        rec = point[g]
        rmse = np.asarray(rec["rmse_deg"], dtype=float)
        r = rmse / np.asarray(law[g], dtype=float)
        ratios.extend(r.tolist())
        n = suite_seeds if g == "randomized" else 1
        failed += int(round(float(rec["failure_rate"]) * n))
        episodes += n
        row[g] = {"rmse_deg": rmse.tolist(), "ratio": r.tolist(), "violations": rec["violations"],
                  "failure_rate": rec["failure_rate"], "score": score_vs_law(rmse.tolist(), law[g])}
    row["score_vs_law"] = float(np.exp(np.mean([np.log(row[g]["score"]) for g in CURVE_GROUPS])))
    row["worst_ratio"] = float(np.max(ratios))
    row["violations"] = int(sum(sum(row[g]["violations"]) for g in CURVE_GROUPS))
    row["failed_episodes"] = failed
    row["episodes"] = episodes
    row["objective"] = -failed / episodes if failed else row["score_vs_law"]
    return row


# ---------------------------------------------------------------------------------------------
# the sweep file


def _err(where: str, msg: str) -> ValueError:
    return ValueError(f"{where}: {msg}")




def _check_space_key(key: str, where: str, searched: bool = True) -> None:
    if key == "config":
        return
    if searched and key in FIXED_KEYS:
        raise _err(where, f"space key {key!r} cannot be searched: every trial is scored against the law on "
                          "the same scenarios; set it in the base config or overrides")
    head, _, tail = key.partition(".")
    if head not in CONFIG_KEYS:
        raise _err(where, f"unknown config key {head!r} in {key!r}; accepted: 'config', {list(CONFIG_KEYS)} "
                          "(nested ones by dotted key, e.g. hyperparams.learning_rate, env.residual_scale)")
    if head == "env" and tail and tail.split(".")[0] not in env_keys():
        raise _err(where, f"unknown env kwarg {tail!r} in {key!r}; accepted: {list(env_keys())}")
    if head in ("env", "hyperparams", "policy_kwargs") and not tail:
        return
    if tail and head not in ("env", "hyperparams", "policy_kwargs"):
        raise _err(where, f"{head!r} has no nested keys (in {key!r})")


def _check_dist(key: str, spec: Any, search: str, where: str) -> None:
    """Validate one distribution of the space (the shapes of the module docstring)."""
    w = f"{where}: space.{key}"
    if not isinstance(spec, dict) or len(spec) != 1:
        raise ValueError(f"{w} must be a mapping with one distribution, e.g. {{loguniform: [1.0e-4, 1.0e-3]}} or "
                         f"{{choice: [a, b]}}; got {spec!r}")
    (kind, arg), = spec.items()
    if kind in RAY_DISTS:
        n = RAY_DISTS[kind]
        if not isinstance(arg, list) or len(arg) != n or not all(is_real(a) for a in arg):
            raise ValueError(f"{w}: {kind} takes a list of {n} numbers, got {arg!r}")
        if not arg[0] < arg[1]:
            raise ValueError(f"{w}: {kind} needs low < high, got {arg!r}")
        if kind.startswith("log") or kind == "qloguniform":
            if arg[0] <= 0:
                raise ValueError(f"{w}: {kind} needs low > 0, got {arg!r}")
        if "randint" in kind and not (is_integer(arg[0]) and is_integer(arg[1])):
            raise ValueError(f"{w}: {kind} takes integers [low, high) (high excluded), got {arg!r}")
    elif kind in LIST_DISTS:
        if not isinstance(arg, list) or not arg:
            raise ValueError(f"{w}: {kind} takes a non-empty list of values, got {arg!r}")
    elif kind in OPTUNA_DISTS:
        if not isinstance(arg, dict) or not {"low", "high"} <= set(arg) or set(arg) - {"low", "high", "log", "step"}:
            raise ValueError(f"{w}: {kind} takes {{low, high, log (optional), step (optional)}}, got {arg!r}")
        check = is_integer if kind == "int" else is_real
        if not (check(arg["low"]) and check(arg["high"])) or not arg["low"] < arg["high"]:
            raise ValueError(f"{w}: {kind} needs {'integers' if kind == 'int' else 'numbers'} low < high, "
                             f"got {arg!r}")
        if "log" in arg and not isinstance(arg["log"], bool):
            raise ValueError(f"{w}: log must be true or false, got {arg['log']!r}")
        if arg.get("log") and arg["low"] <= 0:
            raise ValueError(f"{w}: log needs low > 0, got {arg!r}")
        if arg.get("log") and arg.get("step") is not None:
            raise ValueError(f"{w}: log and step cannot be combined (as in Optuna)")
        if "step" in arg and not (check(arg["step"]) and arg["step"] > 0):
            raise ValueError(f"{w}: step must be a positive {'integer' if kind == 'int' else 'number'}, "
                             f"got {arg['step']!r}")
    else:
        raise ValueError(f"{w}: unknown distribution {kind!r}; accepted: {[*RAY_DISTS, *LIST_DISTS, *OPTUNA_DISTS]}")
    if search == "grid" and kind != "grid":
        raise ValueError(f"{w}: search: grid takes only grid: [...] values; use search: random or optuna "
                         f"for {kind}")
    if search != "grid" and kind == "grid":
        raise ValueError(f"{w}: grid values need search: grid (with {search}, use choice: [...])")


def _merged(file_overrides: Any, cli: Mapping[str, Any] | None) -> Any:
    """The sweep file's overrides with the command line's ``--set`` ones over them."""
    if not cli or not isinstance(file_overrides, dict):
        return file_overrides
    return {**file_overrides, **cli}


def _resolve_config_path(value: str, folder: Path) -> Path:
    from .config import CONFIG_DIR

    p = Path(value)
    for cand in (p if p.is_absolute() else folder / p, CONFIG_DIR / p):
        if cand.is_file():
            return cand.resolve()
    raise ValueError(f"config file not found: {value} (looked next to the sweep file and in {CONFIG_DIR})")


def load_sweep(path: str | Path | dict[str, Any], folder: Path | None = None,
               overrides: Mapping[str, Any] | None = None) -> dict[str, Any]:
    """Read and check a sweep file (or an already-parsed mapping); returns the normalized spec.

    Raises ValueError naming the key and the accepted values for anything wrong."""
    raw, spec, where, folder = _read_sweep(path, folder, overrides)
    _check_sweep(spec, where)
    _check_scheduler(spec, where)
    _sweep_configs(raw, spec, where, folder)
    return spec


def _read_sweep(path: str | Path | dict[str, Any], folder: Path | None, overrides: Mapping[str, Any] | None
                ) -> tuple[dict[str, Any], dict[str, Any], str, Path]:
    """(the file's mapping, the spec with every default filled in, where to say an error is, the
    folder config paths are relative to)."""
    import yaml

    if isinstance(path, dict):
        raw, where, folder = copy.deepcopy(path), "sweep", Path(folder or ".")
    else:
        path = Path(path)
        if not path.is_file():
            raise ValueError(f"sweep file not found: {path}")
        try:
            raw = yaml.safe_load(path.read_text()) or {}
        except yaml.YAMLError as exc:
            raise ValueError(f"{path}: not valid YAML ({exc})") from None
        where, folder = str(path), path.resolve().parent
    if not isinstance(raw, dict):
        raise ValueError(f"{where}: a sweep file is a mapping of {list(SPEC_KEYS)}")
    unknown = sorted(set(raw) - set(SPEC_KEYS))
    if unknown:
        raise _err(where, f"unknown sweep key(s) {unknown}; accepted: {list(SPEC_KEYS)}")
    spec: dict[str, Any] = {
        "name": raw.get("name") or (path.stem if not isinstance(path, dict) else "sweep"),
        "algo": raw.get("algo", "ppo"), "mode": raw.get("mode", "residual"), "controller": raw.get("controller"),
        "observer": raw.get("observer"),
        "scenario": raw.get("scenario", "randomized"), "timesteps": raw.get("timesteps", 300_000),
        "seeds": raw.get("seeds", [0]), "search": raw.get("search", "grid"), "num_samples": raw.get("num_samples"),
        "search_seed": raw.get("search_seed", 0), "overrides": _merged(raw.get("overrides") or {}, overrides),
        "space": raw.get("space") or {}, "scheduler": raw.get("scheduler"), "concurrency": raw.get("concurrency"),
        "time_budget_s": raw.get("time_budget_s"), "note": raw.get("note"),
    }
    return raw, spec, where, folder


def _check_sweep(spec: dict[str, Any], where: str) -> None:
    """The spec's name, run, search, budget, overrides and space, as :func:`load_sweep` accepts them."""
    name = spec["name"]
    if not isinstance(name, str) or not name or not all(c.isalnum() or c in "-_." for c in name):
        raise _err(where, f"name must be letters, digits, '-', '_' or '.', got {name!r}")
    try:  # the same checks as blf-train's (agents.config.RunSpec)
        RunSpec(spec["algo"], spec["mode"], spec["controller"], spec["observer"] or "leso", spec["scenario"],
                spec["timesteps"], spec["seeds"]).checked()
    except ValueError as exc:
        raise _err(where, str(exc)) from None
    if spec["search"] not in SEARCHES:
        raise _err(where, f"unknown search {spec['search']!r}; accepted: {list(SEARCHES)}")
    if spec["search"] == "grid":
        if spec["num_samples"] not in (None, 1):
            raise _err(where, "num_samples applies to search: random or optuna (a grid's size is its values')")
        spec["num_samples"] = 1
    else:
        ns = spec["num_samples"]
        if not is_integer(ns) or ns < 1:
            raise _err(where, f"num_samples must be an integer >= 1 for search: {spec['search']}, got {ns!r}")
    if not is_integer(spec["search_seed"]) or spec["search_seed"] < 0:
        raise _err(where, f"search_seed must be an integer >= 0, got {spec['search_seed']!r}")
    if spec["concurrency"] is not None and (not is_integer(spec["concurrency"]) or spec["concurrency"] < 1):
        raise _err(where, f"concurrency must be an integer >= 1, got {spec['concurrency']!r}")
    tb = spec["time_budget_s"]
    if tb is not None and (not is_real(tb) or not 0 < tb < float("inf")):
        raise _err(where, f"time_budget_s must be a number of seconds > 0 (or absent), got {tb!r}")
    if not isinstance(spec["overrides"], dict) or not isinstance(spec["space"], dict):
        raise _err(where, "overrides and space are mappings of dotted config keys")
    for key in spec["overrides"]:
        if key == "config":
            raise _err(where, "overrides cannot set 'config'; use base")
        _check_space_key(key, where, searched=False)
    for key, dist in spec["space"].items():
        _check_space_key(key, where)
        if key in spec["overrides"]:
            raise _err(where, f"{key!r} is both in overrides and in space")
        _check_dist(key, dist, spec["search"], where)


def _check_scheduler(spec: dict[str, Any], where: str) -> None:
    """The ASHA scheduler's keys, their defaults filled in."""
    sched = spec["scheduler"]
    if sched is not None:
        if not isinstance(sched, dict) or set(sched) != {"asha"} or not isinstance(sched["asha"] or {}, dict):
            raise _err(where, f"scheduler must be {{asha: {{grace_period, reduction_factor}}}} or absent, got {sched!r}")
        asha = dict(sched["asha"] or {})
        bad = sorted(set(asha) - {"grace_period", "reduction_factor", "brackets"})
        if bad:
            raise _err(where, f"unknown asha key(s) {bad}; accepted: ['grace_period', 'reduction_factor', 'brackets']")
        gp, rf = asha.setdefault("grace_period", max(1, spec["timesteps"] // 4)), asha.setdefault("reduction_factor", 2)
        if not is_integer(gp) or not 1 <= gp <= spec["timesteps"]:
            raise _err(where, f"asha.grace_period must be an integer in [1, timesteps], got {gp!r}")
        if not is_real(rf) or rf <= 1:
            raise _err(where, f"asha.reduction_factor must be a number > 1, got {rf!r}")
        spec["scheduler"] = {"asha": asha}


def _sweep_configs(raw: dict[str, Any], spec: dict[str, Any], where: str, folder: Path) -> None:
    """The base config, every config file a grid names (checked with the overrides), and the
    scoring they share (``curve_suite_seeds``, ``duration``), into ``spec``."""
    from .train import load_config

    base = raw.get("base")
    if base is None:  # the shipped config, or TrainConfig's defaults for an algorithm that ships none
        shipped = shipped_config(spec["algo"], spec["mode"])
        base = {} if shipped is None else str(shipped)
    if isinstance(base, dict):
        check_config(base, f"{where}: base")
        spec["base"], spec["base_file"] = copy.deepcopy(base), None
    else:
        bp = _resolve_config_path(str(base), folder)
        spec["base"], spec["base_file"] = load_config(bp), str(bp)
    files = []
    if "config" in spec["space"]:
        (kind, vals), = spec["space"]["config"].items()
        if kind not in ("grid", "choice", "categorical"):
            raise _err(where, "space.config takes grid: or choice: a list of config files")
        files = [str(_resolve_config_path(str(v), folder)) for v in vals]
        spec["space"]["config"] = {kind: files}
    scoring = set()
    for cfg in ([load_config(f) for f in files] or [spec["base"]]):
        trial = copy.deepcopy(cfg)
        for k, v in spec["overrides"].items():
            set_dotted(trial, k, v)
        TrainConfig.of(trial, f"{where}: the base config with the overrides")
        scoring.add((trial.get("curve_suite_seeds", 4), (trial.get("env") or {}).get("duration")))
    if len(scoring) > 1:
        raise _err(where, "all configs must share curve_suite_seeds and env.duration (every trial is scored "
                          f"on the same scenarios); got {sorted(scoring, key=str)}")
    spec["curve_suite_seeds"], spec["duration"] = scoring.pop()


def trial_config(spec: dict[str, Any], params: dict[str, Any]) -> dict[str, Any]:
    """The blf-train config of one trial: the base (or the config file ``params['config']``), then
    the overrides, then the sampled values."""
    from .train import load_config

    cfg = load_config(params["config"]) if "config" in params else copy.deepcopy(spec["base"])
    for k, v in spec["overrides"].items():
        set_dotted(cfg, k, v)
    for k, v in params.items():
        if k != "config":
            set_dotted(cfg, k, v)
    TrainConfig.of(cfg, "trial config")
    return cfg


def config_id(params: dict[str, Any]) -> str:
    """A short content hash of a configuration's sampled values (the seed left out)."""
    return hashlib.sha1(json.dumps(params, sort_keys=True, default=str).encode()).hexdigest()[:6]


def run_name(spec: dict[str, Any], params: dict[str, Any], seed: int) -> str:
    """``<name>_s<seed>`` with no space; ``<config file stem>_s<seed>`` for a grid over config files
    alone (blf-tune's names, which blf-eval and agents.report pool by seed); else
    ``<name>-<config id>_s<seed>``."""
    if not params:
        stem = spec["name"]
    elif set(params) == {"config"}:
        stem = Path(params["config"]).stem
    else:
        stem = f"{spec['name']}-{config_id(params)}"
    return f"{stem}_s{seed}"


def _decode(params: dict[str, Any], spec: dict[str, Any]) -> dict[str, Any]:
    """Values of the space that were encoded for the searcher (lists and mappings, which Optuna's
    categorical distribution does not hold) back to what the config needs."""
    out = {}
    for k, v in params.items():
        if k in ("seed", "__trial_index__"):
            continue
        dist = spec["space"].get(k)
        if isinstance(v, str) and dist is not None and next(iter(dist)) in LIST_DISTS and v.startswith("json:"):
            v = json.loads(v[5:])
        out[k] = v
    return out


def trial_identity(config: dict[str, Any], spec: dict[str, Any]) -> tuple[dict[str, Any], int, str]:
    """(sampled values, seed, run name) of a Ray trial's config: the seed is the grid's ``seed``
    axis, or the Repeater's ``__trial_index__`` into the sweep's seeds."""
    params = _decode(config, spec)
    seed = int(config["seed"]) if "seed" in config else int(spec["seeds"][int(config["__trial_index__"])])
    return params, seed, run_name(spec, params, seed)


def _encode_choice(vals: list[Any]) -> list[Any]:
    return [v if v is None or isinstance(v, (bool, int, float, str)) else "json:" + json.dumps(v) for v in vals]


def _ray_space(spec: dict[str, Any]) -> dict[str, Any]:
    """The space as Ray Tune domains (OptunaSearch converts them for Optuna)."""
    from ray import tune

    space: dict[str, Any] = {}
    for key, dist in spec["space"].items():
        (kind, a), = dist.items()
        if kind == "grid":
            space[key] = tune.grid_search(list(a))
        elif kind in ("choice", "categorical"):
            space[key] = tune.choice(_encode_choice(list(a)))
        elif kind == "float":
            if a.get("step") is not None:
                space[key] = tune.quniform(a["low"], a["high"], a["step"])
            else:
                space[key] = (tune.loguniform if a.get("log") else tune.uniform)(a["low"], a["high"])
        elif kind == "int":  # Optuna's int includes high; Ray's randint excludes it
            if a.get("log"):
                space[key] = tune.lograndint(a["low"], a["high"] + 1)
            else:
                space[key] = tune.qrandint(a["low"], a["high"], a.get("step", 1)) if a.get("step", 1) != 1 \
                    else tune.randint(a["low"], a["high"] + 1)
        else:
            space[key] = getattr(tune, kind)(*a)
    if spec["search"] == "grid":
        space["seed"] = tune.grid_search(list(spec["seeds"]))
    return space


def n_trials(spec: dict[str, Any]) -> int:
    if spec["search"] == "grid":
        n = len(spec["seeds"])
        for dist in spec["space"].values():
            n *= len(next(iter(dist.values())))
        return n
    return int(spec["num_samples"]) * len(spec["seeds"])


# ---------------------------------------------------------------------------------------------
# one trial (runs in a Ray worker)


def _die_with_parent() -> None:  # pragma: no cover - runs in the child between fork and exec
    """The blf-train child gets SIGTERM (a final checkpoint) if the Ray worker that started it dies."""
    try:
        import ctypes

        ctypes.CDLL("libc.so.6", use_errno=True).prctl(1, signal.SIGTERM)  # PR_SET_PDEATHSIG
    except OSError:
        pass


def trial_command(spec: dict[str, Any], seed: int, cfg_path: Path, run: Path) -> list[str]:
    """The blf-train arguments of one trial (without the program name)."""
    cmd = ["--algo", spec["algo"], "--mode", spec["mode"]]
    if spec["controller"]:
        cmd += ["--controller", spec["controller"]]
    if spec["observer"]:
        cmd += ["--observer", spec["observer"]]
    return cmd + ["--scenario", spec["scenario"], "--timesteps", str(spec["timesteps"]), "--seed", str(seed),
                  "--config", str(cfg_path), "--out", str(run), "--name", run.name, "--no-progress"]


def _metrics(row: dict[str, Any], run: str, seed: int, node: str | None) -> dict[str, Any]:
    return {"timesteps": row["timesteps"], "objective": row["objective"], "score_vs_law": row["score_vs_law"],
            "failed_episodes": row["failed_episodes"], "violations": row["violations"],
            "worst_ratio": row["worst_ratio"], "run": run, "seed": seed, "node_id": node,
            **{f"score/{g}": row[g]["score"] for g in CURVE_GROUPS}}


def _trainable():
    """The Ray Tune trainable: one blf-train process per trial, its learning-curve points reported
    as they appear. A class (not a function) so that a trial the scheduler stops gets ``cleanup``,
    which ends blf-train with SIGTERM (a final checkpoint) before Ray ends the worker. Its methods
    are :class:`_TrialLogic`'s; Ray is imported only here."""
    from ray import tune

    return type("BLFTrial", (_TrialLogic, tune.Trainable), {"__module__": __name__})


class _TrialLogic:
    """The methods of :func:`_trainable`'s class (Ray's hooks ``setup``, ``step``, ``save_checkpoint``,
    ``load_checkpoint`` and ``cleanup``), kept apart from ``tune.Trainable`` so that this module
    imports no Ray until a sweep runs."""

    def setup(self, config, spec=None, law=None, out=None, poll_s=1.0, deadline=None):  # noqa: D401 - Ray's hook
        import yaml

        self.spec, self.law, self.poll_s = spec, law, poll_s
        # the wall-clock budget's end (time.time()), or None: once it passes, blf-train gets its
        # SIGTERM from here, without waiting for a curve point the stopper could act on (on a
        # loaded machine the next point could be minutes away)
        self.deadline, self.termed, self.handshake = deadline, False, False
        params, seed, name = trial_identity(config, spec)
        self.seed = seed
        run = self.run = Path(out) / "runs" / name
        run.mkdir(parents=True, exist_ok=True)
        cfg_path = run / "config.yaml"
        atomic_write_text(cfg_path, yaml.safe_dump(trial_config(spec, params), sort_keys=False))
        args = trial_command(spec, seed, cfg_path, run)
        import ray

        self.node = ray.get_runtime_context().get_node_id()
        atomic_write_json(run / "trial.json", {
            "run": run.name, "seed": seed, "params": params, "config_id": config_id(params),
            "command": " ".join(["blf-train", *args]), "sweep": spec["name"], "node_id": self.node})
        self.reported, self.queue, self.last, self.proc = -1, [], None, None
        meta_path = run / "metadata.json"
        prior = json.loads(meta_path.read_text()) if meta_path.is_file() else None
        if prior is not None and prior.get("completed") and int(prior.get("timesteps", 0)) >= spec["timesteps"]:
            return  # a finished run (after a restore): its curve is reported, nothing is trained
        if prior is not None or (run / "checkpoints").is_dir():
            args.append("--resume")
        # on Linux, blf-train stops itself after each curve point (see _paused) until the next
        # step() lets it go on, so that a trial stopped at a rung has trained to that rung
        self.handshake = sys.platform.startswith("linux") and hasattr(signal, "SIGSTOP")
        env = dict(os.environ, **({PAUSE_ENV: "1"} if self.handshake else {}))
        with open(run / "train.log", "ab") as log:
            self.proc = subprocess.Popen(
                [sys.executable, "-m", "agents.train", *args], stdout=log, stderr=subprocess.STDOUT, env=env,
                preexec_fn=_die_with_parent if sys.platform.startswith("linux") else None)

    def _refresh(self) -> None:
        curve = self.run / "eval" / "curve.json"
        if not curve.is_file():
            return
        try:
            pts = json.loads(curve.read_text())["points"]
        except (OSError, ValueError, KeyError):
            return
        for p in pts:
            if p["timesteps"] > self.reported:
                self.queue.append(p)
                self.reported = p["timesteps"]

    def _alive(self) -> bool:
        return self.proc is not None and self.proc.poll() is None

    def _paused(self) -> bool:
        """Whether blf-train has stopped itself (state T in /proc/<pid>/stat). A point becomes
        visible just before the process stops; the trial waits for the stop before it reports
        the point, so its SIGCONT for the next point cannot arrive before the SIGSTOP."""
        try:
            stat = Path(f"/proc/{self.proc.pid}/stat").read_text()
        except OSError:
            return False
        return stat[stat.rfind(")") + 2:][:1] in ("T", "t")

    def step(self):
        self._go_on()
        self._refresh()
        # the point at the budget is held until blf-train has saved the model and exited:
        # reaching max_t makes Ray stop the trial, and the run must be complete by then; any
        # other point is reported once blf-train has paused after it (or exited)
        while self._alive() and (not self.queue or self.queue[0]["timesteps"] >= self.spec["timesteps"]
                                 or (self.handshake and len(self.queue) == 1 and not self._paused())):
            time.sleep(min(self.poll_s, 0.05) if self.queue else self.poll_s)
            self._refresh()
            self._stop_at_deadline()
        exited = self.proc is None or self.proc.poll() is not None
        if exited:
            self._refresh()
            # 130: blf-train's exit after the SIGTERM sent at the budget's end (its final save done)
            if self.proc is not None and self.proc.returncode != 0 and not (self.termed and
                                                                            self.proc.returncode == 130):
                tail = (self.run / "train.log").read_text(errors="replace").strip().splitlines()[-5:]
                raise RuntimeError(f"blf-train exited with {self.proc.returncode} for {self.run.name}: "
                                   + " | ".join(tail))
        if self.queue:
            row = score_point(self.queue.pop(0), self.law, self.spec["curve_suite_seeds"])
            self.last = _metrics(row, self.run.name, self.seed, self.node)
        elif self.last is None:
            raise RuntimeError(f"blf-train wrote no learning curve for {self.run.name}")
        return dict(self.last, done=exited and not self.queue)

    def _go_on(self) -> None:
        """SIGCONT to a blf-train that paused after its last point (harmless to a running one):
        Ray has asked for the next point. Its numbers do not depend on the pause; its wall
        clock counts it."""
        if self.handshake and self._alive():
            self.proc.send_signal(signal.SIGCONT)

    def _stop_at_deadline(self) -> None:
        """SIGTERM to blf-train once the budget's end has passed and it has written its first curve
        point (its handler is installed by then: it saves a final checkpoint and exits)."""
        if (self.deadline is not None and not self.termed and self.reported >= 0 and self._alive()
                and time.time() >= self.deadline):
            self.proc.send_signal(signal.SIGTERM)
            self.termed = True

    def save_checkpoint(self, checkpoint_dir):
        # the trial's real state is blf-train's own checkpoints in its run folder; Ray's
        # checkpoint only records which run and how far its curve was reported
        atomic_write_json(Path(checkpoint_dir) / "trial.json", {"run": str(self.run), "reported": self.reported})

    def load_checkpoint(self, checkpoint):
        pass  # setup already reconnected to the run folder (blf-train --resume)

    def cleanup(self):
        p = self.proc
        if p is not None and p.poll() is None:  # stopped by the scheduler or by Ctrl-C
            p.send_signal(signal.SIGTERM)
            self._go_on()  # a paused process takes its SIGTERM when it runs again
            try:
                p.wait(120)
            except subprocess.TimeoutExpired:
                p.kill()



# ---------------------------------------------------------------------------------------------
# the ranked table


def collect(out: Path, spec: dict[str, Any], law: dict[str, list[float]],
            statuses: dict[str, str]) -> dict[str, Any]:
    """Trials and configurations of a sweep folder, scored at their last curve point, ranked."""
    trials = []
    for tj in sorted((out / "runs").glob("*/trial.json")):
        run = tj.parent
        try:
            t = json.loads(tj.read_text())
            pts = json.loads((run / "eval" / "curve.json").read_text())["points"] if \
                (run / "eval" / "curve.json").is_file() else []
            meta = json.loads((run / "metadata.json").read_text()) if (run / "metadata.json").is_file() else {}
        except (OSError, ValueError):
            continue
        if t.get("sweep") != spec["name"]:
            continue
        row = score_point(pts[-1], law, spec["curve_suite_seeds"]) if pts else None
        status = statuses.get(run.name) or ("done" if meta.get("completed") else "stopped")
        trials.append({"run": run.name, "config_id": t["config_id"], "params": t["params"], "seed": t["seed"],
                       "status": status, "command": t["command"], "node_id": t.get("node_id"),
                       "timesteps": row["timesteps"] if row else 0, "score": row})
    configs: dict[str, dict[str, Any]] = {}
    for t in trials:
        c = configs.setdefault(t["config_id"], {"config_id": t["config_id"], "params": t["params"], "trials": []})
        c["trials"].append(t)
    ranked = []
    for c in configs.values():
        scored = [t["score"] for t in c["trials"] if t["score"] is not None]
        c["seeds"] = sorted(t["seed"] for t in c["trials"])
        c["statuses"] = sorted(t["status"] for t in c["trials"])
        if scored:
            c["objective"] = float(np.mean([s["objective"] for s in scored]))
            c["score_vs_law"] = float(np.mean([s["score_vs_law"] for s in scored]))
            c["score_range"] = [float(min(s["score_vs_law"] for s in scored)), float(max(s["score_vs_law"] for s in scored))]
            c["failed_episodes"] = int(sum(s["failed_episodes"] for s in scored))
            c["groups"] = {g: {"score": float(np.mean([s[g]["score"] for s in scored])),
                               "ratio": np.mean([s[g]["ratio"] for s in scored], axis=0).tolist()} for g in CURVE_GROUPS}
            c["worst_ratio"] = float(max(s["worst_ratio"] for s in scored))
            c["timesteps"] = int(min(s["timesteps"] for s in scored))
        ranked.append(c)
    ranked.sort(key=rank_key)
    return {"configs": ranked, "trials": trials}


def rank_key(c: dict[str, Any]) -> tuple:
    """Best first: configurations with a score before those without; no failed episode on any seed
    before any failed episode; then the higher mean objective (the mean score_vs_law when clean)."""
    if "objective" not in c:
        return (2, 0.0)
    return (int(c["failed_episodes"] > 0), -c["objective"])


def _fmt_params(p: dict[str, Any]) -> str:
    if not p:
        return "(base)"
    return ", ".join(f"{k}={Path(v).stem if k == 'config' else (f'{v:.4g}' if isinstance(v, float) else v)}"
                     for k, v in sorted(p.items()))


def markdown(spec: dict[str, Any], table: dict[str, Any], law: dict[str, list[float]], counts: dict[str, int]) -> str:
    joints = " ".join(f"j{j + 1}" for j in range(len(law[CURVE_GROUPS[0]])))
    lines = [f"# Sweep `{spec['name']}`", "",
             f"{spec['search']} search, {spec['algo']} {spec['mode']} on {spec['scenario']}, "
             f"{spec['timesteps']} steps per trial, seeds {spec['seeds']}. Trials: "
             + ", ".join(f"{v} {k}" for k, v in counts.items()) + ".", "",
             "Ranked by the objective (score_vs_law pooled over the paper presets and the held-out "
             "training-suite episodes of the learning curve's last point; a configuration with a failed "
             "episode on any seed ranks below every one without). Ratios are the policy's RMSE over the "
             "law's, per joint, averaged over seeds.", "",
             "| rank | configuration | seeds | objective | score_vs_law [min, max] | score 0.1 Hz / 0.5 Hz / suite "
             f"| RMSE / law, 0.1 Hz ({joints}) | 0.5 Hz | suite | failed eps | worst ratio | steps | status |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for i, c in enumerate(table["configs"], 1):
        status = ", ".join(f"{c['statuses'].count(s)} {s}" for s in sorted(set(c["statuses"])))
        if "objective" not in c:
            lines.append(f"| {i} | {_fmt_params(c['params'])} | {c['seeds']} | - | - | - | - | - | - | - | - | 0 "
                         f"| {status} |")
            continue
        cells = [" ".join(f"{v:.3f}" for v in c["groups"][g]["ratio"]) for g in CURVE_GROUPS]
        scores = " / ".join(f"{c['groups'][g]['score']:.3f}" for g in CURVE_GROUPS)
        lo, hi = c["score_range"]
        lines.append(f"| {i} | {_fmt_params(c['params'])} | {' '.join(map(str, c['seeds']))} | {c['objective']:.4f} "
                     f"| {c['score_vs_law']:.4f} [{lo:.4f}, {hi:.4f}] | {scores} | " + " | ".join(cells)
                     + f" | {c['failed_episodes']} | {c['worst_ratio']:.3f} | {c['timesteps']} | {status} |")
    if spec.get("time_budget_s"):
        lines += ["", f"Wall-clock budget {spec['time_budget_s']:.0f} s for the whole sweep; status `budget` = a "
                  "trial stopped when it ran out (ranked on its last curve point, at the steps shown), `pending` "
                  "= never started."]
    lines += ["", "| run | seed | status | steps | objective | score_vs_law | node |", "|---|---|---|---|---|---|---|"]
    for t in sorted(table["trials"], key=lambda t: t["run"]):
        s = t["score"]
        lines.append(f"| {t['run']} | {t['seed']} | {t['status']} | {t['timesteps']} | "
                     + (f"{s['objective']:.4f} | {s['score_vs_law']:.4f}" if s else "- | -")
                     + f" | {(t['node_id'] or '-')[:8]} |")
    lines += ["", f"Law level (proposed, RMSE deg {joints}): " + "; ".join(
        f"{g}: " + " ".join(f"{v:.4f}" for v in law[g]) for g in CURVE_GROUPS),
        "", "Each run's `trial.json` holds the blf-train command that reproduces it; "
            "`blf-eval --agents runs/<run>` re-evaluates it."]
    return "\n".join(lines) + "\n"


# ---------------------------------------------------------------------------------------------
# the driver


def _counts(statuses: dict[str, str], total: int) -> dict[str, int]:
    c = {k: sum(1 for v in statuses.values() if v == k) for k in ("done", "pruned", "running", "error", "stopped",
                                                                  "budget")}
    c["pending"] = max(0, total - sum(c.values()))
    return {k: v for k, v in c.items() if v or k in ("done", "running", "pending")}


def _write_tables(out: Path, spec: dict[str, Any], law: dict[str, list[float]], statuses: dict[str, str],
                  extra: dict[str, Any]) -> dict[str, Any]:
    table = collect(out, spec, law, statuses)
    counts = _counts({t["run"]: t["status"] for t in table["trials"]} | statuses, n_trials(spec))
    atomic_write_json(out / "sweep.json", {"spec": spec, "law": law, "counts": counts, "statuses": statuses,
                                           **extra, **table})
    atomic_write_text(out / "sweep.md", markdown(spec, table, law, counts))
    return {"table": table, "counts": counts}


def _make_callback(out: Path, spec: dict[str, Any], law: dict[str, list[float]], statuses: dict[str, str],
                   extra: dict[str, Any], printer: Callable[[str], None], budget: "_Budget | None" = None):
    from ray.tune import Callback

    class _Progress(Callback):
        """Keeps the trials' status, rewrites the tables when a trial ends, prints one line a change."""

        def _name(self, trial) -> str:
            return trial_identity(trial.config, spec)[2]

        def _line(self, what: str, name: str) -> None:
            info = _write_tables(out, spec, law, statuses, extra)
            best = next((c for c in info["table"]["configs"] if "objective" in c), None)
            counts = " · ".join(f"{v} {k}" for k, v in info["counts"].items())
            b = f" | best {best['objective']:.4f} ({_fmt_params(best['params'])})" if best else ""
            printer(f"blf-sweep: {what} {name} | {counts}{b}")

        def on_trial_start(self, iteration, trials, trial, **info):
            statuses[self._name(trial)] = "running"
            self._line("started", self._name(trial))

        def on_trial_complete(self, iteration, trials, trial, **info):
            name = self._name(trial)
            steps = int((trial.last_result or {}).get("timesteps", 0))
            # the run's own record decides when it finished: Ray may end a trial before its last
            # report (the final curve point) reaches the callback, more so on a loaded machine
            statuses[name] = ("done" if steps >= spec["timesteps"] or _completed(out / "runs" / name) else
                              "budget" if budget is not None and budget.exhausted() else "pruned")
            self._line({"done": "finished", "pruned": "pruned", "budget": "stopped by the budget"}[statuses[name]],
                       name)

        def on_trial_error(self, iteration, trials, trial, **info):
            name = self._name(trial)
            statuses[name] = "error"
            self._line("FAILED (see its train.log)", name)

    return _Progress()


def _searcher(spec: dict[str, Any]):
    """Ray's search algorithm for the spec: the grid's variant generator, or OptunaSearch (random
    or TPE sampler, seeded) with every sampled configuration repeated once per seed."""
    if spec["search"] == "grid":
        return None
    import optuna
    from ray.tune.search import Repeater
    from ray.tune.search.optuna import OptunaSearch

    sampler = (optuna.samplers.RandomSampler(seed=spec["search_seed"]) if spec["search"] == "random"
               else optuna.samplers.TPESampler(seed=spec["search_seed"]))
    return Repeater(OptunaSearch(sampler=sampler), repeat=len(spec["seeds"]), set_index=True)


def _scheduler(spec: dict[str, Any]):
    if not spec["scheduler"]:
        return None
    from ray.tune.schedulers import ASHAScheduler

    a = spec["scheduler"]["asha"]
    return ASHAScheduler(time_attr="timesteps", max_t=spec["timesteps"], grace_period=a["grace_period"],
                         reduction_factor=a["reduction_factor"], brackets=a.get("brackets", 1))


class _Budget:
    """A sweep's wall-clock budget: the seconds Ray Tune has run this sweep, kept across resumes in
    ``OUT/budget.json``. Not Ray Tune's own ``time_budget_s`` (its ``TimeoutStopper``), which stops
    the whole experiment at once: that ends a running trial's blf-train without its final save
    (seen in issue 16's first sweeps, docs/plain_search.md); see ``stopper``."""

    def __init__(self, out: Path, limit: float | None):
        self.path, self.limit, self.t0 = out / "budget.json", limit, None
        self.spent = float(json.loads(self.path.read_text())["used_s"]) if self.path.is_file() else 0.0

    @property
    def used(self) -> float:
        return self.spent + (time.time() - self.t0 if self.t0 is not None else 0.0)

    def deadline(self) -> float | None:
        """When the budget ends (``time.time()``), with its clock running; None without a limit."""
        if self.limit is None or self.t0 is None:
            return None
        return self.t0 + (self.limit - self.spent)

    def exhausted(self) -> bool:
        return self.limit is not None and self.used >= self.limit

    def start(self) -> None:
        self.t0 = time.time()

    def stop(self) -> None:
        if self.t0 is not None:
            self.spent, self.t0 = self.used, None
            if self.limit is not None:
                atomic_write_json(self.path, {"used_s": round(self.spent, 3), "limit_s": self.limit})

    def stopper(self, statuses: dict[str, str]):
        """Ray Tune's stopper for the budget. Once it is spent, each running trial ends the way ASHA
        stops one: its blf-train gets SIGTERM (from the trial itself at the budget's end,
        :func:`_trainable`'s deadline, or at its next report) and saves its final checkpoint
        (stopping the whole experiment at once would kill a trial mid-step, losing the steps since
        its last checkpoint); the experiment stops when no trial is left running, so a trial
        overruns the budget by the time its final save and curve point take."""
        if self.limit is None:
            return None
        from ray.tune.stopper import Stopper

        budget = self

        class _Stop(Stopper):
            def __call__(self, trial_id, result):
                return budget.exhausted()

            def stop_all(self):
                return budget.exhausted() and "running" not in statuses.values()

        return _Stop()


def _completed(run: Path) -> bool:
    """Whether the run folder's blf-train recorded its run as completed."""
    try:
        return bool(json.loads((run / "metadata.json").read_text()).get("completed"))
    except (OSError, ValueError):
        return False


def _budget_statuses(out: Path, spec: dict[str, Any], statuses: dict[str, str]) -> None:
    """Once the budget has ended the sweep: every trial of it that started (its run folder holds a
    trial.json) and did not finish belongs to the budget, whether the callback saw it run or not.
    Ray may start a trial, and its blf-train write its folder, before the trial's start reaches the
    callback (the wider on a loaded machine); such a trial used to fall through to 'stopped'."""
    for tj in (out / "runs").glob("*/trial.json"):
        run = tj.parent
        try:
            if json.loads(tj.read_text()).get("sweep") != spec["name"]:
                continue
        except (OSError, ValueError):
            continue  # not a trial of this sweep that can be read
        if statuses.get(run.name) in (None, "running"):
            statuses[run.name] = "done" if _completed(run) else "budget"


def _spec_digest(spec: dict[str, Any]) -> str:
    keep = {k: v for k, v in spec.items() if k not in ("concurrency", "note")}
    return hashlib.sha1(json.dumps(keep, sort_keys=True, default=str).encode()).hexdigest()


def _stamp_out(spec: dict[str, Any], out: Path) -> None:
    """Create ``out`` and stamp it with the spec's digest; ValueError if it holds another sweep."""
    out.mkdir(parents=True, exist_ok=True)
    digest = _spec_digest(spec)
    stamp = out / "sweep_spec.json"
    if stamp.is_file():
        old = json.loads(stamp.read_text())
        if old.get("digest") != digest:
            raise ValueError(f"{out} holds another sweep ({old.get('spec', {}).get('name')!r}, a different spec); "
                             "choose another --out, or move it away to start again")
    else:
        atomic_write_json(stamp, {"digest": digest, "spec": spec})


def _ray_init(ray: Any, address: str | None) -> str | None:
    """Start Ray: the cluster at ``address``, or a local instance; returns ``address``."""
    import logging

    if address:
        ray.init(address=address, logging_level=logging.WARNING, log_to_driver=False)
    else:
        # Ray starts its workers at nice 15, to keep its own processes responsive; here the workers'
        # trials are the work itself, and at nice 15 beside any other busy process on the machine
        # they starve (seen: a trial's blf-train at 1.8 % of a core beside two busy processes, a
        # 90 s budget spent before it trained a step). The local instance runs them at the
        # priority the sweep was started with; a cluster (--address) keeps its own setting.
        os.environ.setdefault("RAY_worker_niceness", "0")
        ray.init(num_cpus=os.cpu_count(), include_dashboard=False, logging_level=logging.WARNING,
                 log_to_driver=False)
    return address


def _previous_statuses(out: Path) -> dict[str, str]:
    """The trials' statuses of an earlier run of the sweep in ``out`` (a trial that was running is
    now stopped); empty for a new sweep."""
    prev = out / "sweep.json"
    if not prev.is_file():
        return {}
    try:
        return {k: ("stopped" if v == "running" else v)
                for k, v in json.loads(prev.read_text()).get("statuses", {}).items()}
    except ValueError:
        return {}


def run_sweep(spec: dict[str, Any], out: Path, address: str | None = None, concurrency: int | None = None,
              storage: str | None = None, printer: Callable[[str], None] | None = None,
              command: str | None = None) -> dict[str, Any]:
    """Run (or resume) a sweep into ``out``; returns the final table and counts."""
    printer = printer or (lambda s: print(s, file=sys.stderr, flush=True))
    out = Path(out).resolve()
    _stamp_out(spec, out)
    os.environ.setdefault("RAY_USAGE_STATS_ENABLED", "0")
    os.environ.setdefault("RAY_AIR_NEW_OUTPUT", "0")
    import optuna
    import ray
    from ray import tune

    optuna.logging.set_verbosity(optuna.logging.WARNING)

    from blf_gym.results.metrics import provenance

    printer(f"blf-sweep: scoring the law on the curve scenarios ({spec['curve_suite_seeds']} suite episodes)")
    # the benchmark's score is always against the proposed law, whatever the trials' inner law
    law = law_levels(int(spec["curve_suite_seeds"]), spec["duration"], "proposed")
    address = _ray_init(ray, address or os.environ.get("RAY_ADDRESS"))
    try:
        cpus = int(ray.cluster_resources().get("CPU", 1))
        nodes = [n for n in ray.nodes() if n.get("Alive")]
        conc = concurrency or spec["concurrency"] or cpus
        prov = provenance()
        extra = {"command": command, "versions": prov["versions"], "git_commit": prov["git_commit"],
                 "ray": {"address": address or "local", "nodes": len(nodes), "cpus": cpus, "concurrency": conc}}
        total = n_trials(spec)
        statuses = _previous_statuses(out)
        printer(f"blf-sweep: {spec['name']}: {total} trials ({spec['search']}, {len(spec['seeds'])} seed(s)), "
                f"{conc} at a time on {len(nodes)} node(s) with {cpus} CPU(s)")
        budget = _Budget(out, spec["time_budget_s"])
        storage_path = storage or str(out / "ray")
        exp = f"{storage_path.rstrip('/')}/{spec['name']}"
        callback = _make_callback(out, spec, law, statuses, extra, printer, budget)
        extra["time_budget_s"], extra["budget_used_s"] = spec["time_budget_s"], round(budget.used, 1)
        if budget.exhausted():
            printer(f"blf-sweep: the wall-clock budget ({spec['time_budget_s']:.0f} s) is spent; nothing to resume")
            return _write_tables(out, spec, law, statuses, extra)
        t0 = time.time()
        budget.start()
        try:
            _fit(tune, spec, law, out, storage_path, exp, statuses, callback, budget, printer, conc, total)
        finally:
            budget.stop()
        extra["wall_s"] = round(time.time() - t0, 1)
        extra["budget_used_s"] = round(budget.used, 1)
        if budget.exhausted():
            _budget_statuses(out, spec, statuses)
            printer(f"blf-sweep: the wall-clock budget ({spec['time_budget_s']:.0f} s) is spent")
        info = _write_tables(out, spec, law, statuses, extra)
        c = info["counts"]
        if not budget.exhausted() and c.get("done", 0) + c.get("pruned", 0) + c.get("error", 0) < total:
            # Ray Tune caught a Ctrl-C (or SIGTERM), stopped the trials and saved its state
            raise KeyboardInterrupt
    finally:
        ray.shutdown()
    return info


def _fit(tune: Any, spec: dict[str, Any], law: Any, out: Path, storage_path: str, exp: str, statuses: dict[str, str],
         callback: Any, budget: _Budget, printer: Any, conc: int, total: int) -> None:
    """Build (or restore) Ray Tune's tuner for the sweep and run it, the budget's clock running: the
    trials get the budget's end as a deadline (:func:`_trainable`) and the stopper its rule."""
    deadline = budget.deadline()
    trainable = tune.with_resources(tune.with_parameters(_trainable(), spec=spec, law=law, out=str(out),
                                                         deadline=deadline), {"cpu": 1})
    stopper = budget.stopper(statuses)
    run_config = tune.RunConfig(name=spec["name"], storage_path=storage_path, callbacks=[callback], verbose=0,
                                failure_config=tune.FailureConfig(max_failures=0), stop=stopper)
    if tune.Tuner.can_restore(exp):
        printer(f"blf-sweep: resuming {exp} (finished trials are kept)")
        tuner = tune.Tuner.restore(exp, trainable=trainable, resume_unfinished=True, resume_errored=True,
                                   param_space=_ray_space(spec))
        # callbacks are not part of the saved state: give the restored run ours (Ray keeps the
        # run config on its internal tuner; without it the sweep still runs, without progress lines)
        try:
            tuner._local_tuner._run_config.callbacks = [callback]  # noqa: SLF001
            if stopper is not None:
                tuner._local_tuner._run_config.stop = stopper  # noqa: SLF001
        except AttributeError:
            printer("blf-sweep: this Ray version does not let a restored sweep take callbacks; "
                    "progress lines and table updates come at the end")
    else:
        tuner = tune.Tuner(trainable, param_space=_ray_space(spec), run_config=run_config,
                           tune_config=tune.TuneConfig(metric="objective", mode="max",
                                                       num_samples=total if spec["search"] != "grid" else 1,
                                                       search_alg=_searcher(spec), scheduler=_scheduler(spec),
                                                       max_concurrent_trials=conc))
    tuner.fit()


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="blf-sweep", description=help_text(__doc__.split("\n\n")[0]),
                                epilog="See docs/sweeps.md for the sweep file, clusters and the scaling figures.",
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("sweep", type=Path, help="the sweep file (YAML; agents/configs/sweeps/ has examples)")
    add_config_options(p)
    p.add_argument("--out", type=Path, default=None, metavar="DIR",
                   help="folder for the runs, sweep.json and sweep.md (default runs/sweeps/<name>); on a "
                        "cluster, a folder every node can write (a shared file system)")
    p.add_argument("--address", default=None, metavar="ADDRESS",
                   help="an existing Ray cluster (host:port; also RAY_ADDRESS); default: a local Ray "
                        "instance with one trial per core")
    p.add_argument("--concurrency", type=int, default=None, metavar="N",
                   help="trials at the same time (default: the sweep file's, else one per CPU of the cluster)")
    p.add_argument("--storage", default=None, metavar="PATH",
                   help="Ray Tune's storage_path for its experiment state (default OUT/ray; a shared path "
                        "or a URI such as s3://bucket/sweeps on a cluster)")
    return p


def main(argv: Sequence[str] | None = None) -> int:
    import shlex

    argv = list(sys.argv[1:] if argv is None else argv)
    args = _parser().parse_args(argv)
    try:
        if args.concurrency is not None and args.concurrency < 1:
            raise ValueError("--concurrency must be >= 1")
        spec = load_sweep(args.sweep, overrides=parse_overrides(args.overrides))  # --set over the file's overrides
        try:
            import optuna  # noqa: F401
            import ray.tune  # noqa: F401
        except ImportError as exc:
            raise ValueError(f"blf-sweep needs Ray Tune and Optuna ({exc.name} is missing): {SWEEP_EXTRA}") from None
        out = args.out or Path("runs") / "sweeps" / spec["name"]
        info = run_sweep(spec, out, args.address, args.concurrency, args.storage,
                         command=shlex.join(["blf-sweep", *argv]))
    except ValueError as exc:
        print(f"blf-sweep: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("\nblf-sweep: interrupted; finished trials are kept, run the same command to resume", file=sys.stderr)
        return 130
    except ConnectionError as exc:
        print(f"blf-sweep: error: cannot reach the Ray cluster: {exc}", file=sys.stderr)
        return 2
    print((Path(out) / "sweep.md").read_text())
    bad = info["counts"].get("error", 0)
    if bad:
        print(f"blf-sweep: {bad} trial(s) failed; their train.log says why", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
