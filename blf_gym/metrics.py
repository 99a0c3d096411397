"""Evaluation metrics on the 1 ms grid and the one results schema every command writes (SPEC section 8).

A *record* pools the episodes of one policy on one scenario. ``results.json`` is
``{"schema_version": 1, "records": [...]}``; ``results.csv`` has one row per record with per-joint
fields spread over ``<field>_<joint>`` columns (joints numbered from 1).
"""

from __future__ import annotations

import csv
import io
import math
import os
from pathlib import Path
from typing import Any, Iterable, Sequence

import numpy as np

from .io import atomic_write_json, atomic_write_text

__all__ = [
    "SCHEMA_VERSION",
    "RECORD_FIELDS",
    "violation_mask",
    "summarize",
    "write_results",
    "read_results",
]

SCHEMA_VERSION = 1

RECORD_FIELDS = (
    "policy", "kind", "scenario", "episodes", "dt", "rmse_deg", "violations", "violation_fraction",
    "max_excursion_deg", "min_margin_deg", "first_violation_s", "failure_rate", "rmse_cvar_deg",
    "torque_rms", "torque_peak", "saturated_fraction", "diverged", "wall_s",
)
PER_JOINT = ("rmse_deg", "violations", "violation_fraction", "max_excursion_deg", "min_margin_deg",
             "torque_rms", "torque_peak", "saturated_fraction")
KINDS = ("baseline", "plain", "residual")


def violation_mask(e1: np.ndarray, k_a: np.ndarray, k_b: np.ndarray) -> np.ndarray:
    """True where e1 is outside the open interval (-k_b, k_a) (eq. 17)."""
    return (e1 >= k_a) | (e1 <= -k_b)


def cvar_upper(values: Sequence[float], alpha: float = 0.5) -> float:
    """Mean of the worst ``1 - alpha`` share of ``values`` (largest ones), at least one value."""
    v = np.sort(np.asarray(values, dtype=float))[::-1]
    k = max(1, int(math.ceil((1.0 - alpha) * v.size)))
    return float(np.mean(v[:k]))


def _traj_arrays(traj: Any) -> dict[str, np.ndarray]:
    s = traj.signals if hasattr(traj, "signals") else traj
    return {k: np.asarray(s[k]) for k in ("t", "e1", "k_a", "k_b", "u", "saturated")}


def summarize(
    trajectories: Iterable[Any],
    policy: str,
    kind: str,
    scenario: str,
    dt: float,
    wall_s: float = 0.0,
) -> dict[str, Any]:
    """Pool episodes into one results record.

    ``trajectories`` are :class:`blf_gym.simulate.Trajectory` objects (or dicts of their signals).
    RMSE pools the squared error of all 1 ms samples of all episodes; an episode fails if any of
    its samples or integration steps violated a bound.
    """
    if kind not in KINDS:
        raise ValueError(f"kind must be one of {KINDS}, got {kind!r}")
    sq_sum = None
    count = 0
    viol = None
    exc = None
    margin = None
    u_sq = None
    u_peak = None
    sat = None
    first: float | None = None
    fails = 0
    diverged = False
    per_episode_rmse: list[float] = []
    episodes = 0
    for traj in trajectories:
        a = _traj_arrays(traj)
        e1, ka, kb, u = a["e1"], a["k_a"], a["k_b"], a["u"]
        episodes += 1
        n_joints = e1.shape[1] if e1.ndim == 2 else 3
        if e1.shape[0] == 0:
            diverged = True
            fails += 1
            continue
        mask = violation_mask(e1, ka, kb)
        beyond = np.maximum(np.maximum(e1 - ka, -kb - e1), 0.0)
        marg = np.minimum(ka - e1, e1 + kb)
        sq = np.sum(e1 ** 2, axis=0)
        if sq_sum is None:
            n = e1.shape[1]
            sq_sum = np.zeros(n)
            viol = np.zeros(n, dtype=np.int64)
            exc = np.zeros(n)
            margin = np.full(n, np.inf)
            u_sq = np.zeros(n)
            u_peak = np.zeros(n)
            sat = np.zeros(n)
        sq_sum += sq
        count += e1.shape[0]
        viol += mask.sum(axis=0)
        exc = np.maximum(exc, beyond.max(axis=0))
        margin = np.minimum(margin, marg.min(axis=0))
        u_sq += np.sum(u ** 2, axis=0)
        u_peak = np.maximum(u_peak, np.abs(u).max(axis=0))
        sat += a["saturated"].sum(axis=0)
        per_episode_rmse.append(float(np.mean(np.degrees(np.sqrt(sq / e1.shape[0])))))
        step_viol = getattr(traj, "step_violations", 0)
        ep_div = bool(getattr(traj, "diverged", False))
        diverged |= ep_div
        # earliest violation: a 1 ms sample, or an integration step between samples
        candidates = []
        if mask.any():
            candidates.append(float(a["t"][np.argmax(mask.any(axis=1))]))
        step_t = getattr(traj, "first_violation_step_time", None)
        if step_t is not None:
            candidates.append(float(step_t))
        if candidates:
            first = min(candidates) if first is None else min(first, *candidates)
        if mask.any() or step_viol > 0 or ep_div:
            fails += 1
    if episodes == 0:
        raise ValueError("summarize needs at least one trajectory")
    if sq_sum is None:
        return {"policy": policy, "kind": kind, "scenario": scenario, "episodes": episodes, "dt": dt,
                **{k: [None] * n_joints for k in PER_JOINT}, "first_violation_s": None,
                "failure_rate": 1.0, "rmse_cvar_deg": None, "diverged": True, "wall_s": wall_s}
    return {
        "policy": policy,
        "kind": kind,
        "scenario": scenario,
        "episodes": episodes,
        "dt": dt,
        "rmse_deg": np.degrees(np.sqrt(sq_sum / count)).tolist(),
        "violations": viol.tolist(),
        "violation_fraction": (viol / count).tolist(),
        "max_excursion_deg": np.degrees(exc).tolist(),
        "min_margin_deg": np.degrees(margin).tolist(),
        "first_violation_s": first,
        "failure_rate": fails / episodes,
        "rmse_cvar_deg": cvar_upper(per_episode_rmse, 0.5) if per_episode_rmse else None,
        "torque_rms": np.sqrt(u_sq / count).tolist(),
        "torque_peak": u_peak.tolist(),
        "saturated_fraction": (sat / count).tolist(),
        "diverged": diverged,
        "wall_s": wall_s,
    }


def _csv_text(records: Sequence[dict[str, Any]]) -> str:
    n = max((len(r["rmse_deg"]) for r in records), default=3)
    header: list[str] = []
    for f in RECORD_FIELDS:
        header.extend([f"{f}_{j + 1}" for j in range(n)] if f in PER_JOINT else [f])
    buf = io.StringIO()
    w = csv.writer(buf)
    w.writerow(header)
    for r in records:
        row: list[Any] = []
        for f in RECORD_FIELDS:
            v = r.get(f)
            if f in PER_JOINT:
                row.extend(list(v) + [""] * (n - len(v)))
            else:
                row.append("" if v is None else v)
        w.writerow(row)
    return buf.getvalue()


def write_results(records: Sequence[dict[str, Any]], out_dir: str | os.PathLike) -> tuple[Path, Path]:
    """Write ``results.json`` and ``results.csv`` atomically into ``out_dir``; return their paths."""
    out = Path(out_dir)
    for r in records:
        missing = [f for f in RECORD_FIELDS if f not in r]
        if missing:
            raise ValueError(f"record for {r.get('policy')!r} lacks fields {missing}")
        if r["kind"] not in KINDS:
            raise ValueError(f"record for {r.get('policy')!r}: kind must be one of {KINDS}, got {r['kind']!r}")
        lengths = {len(r[f]) for f in PER_JOINT}
        if len(lengths) != 1:
            raise ValueError(f"record for {r.get('policy')!r}: per-joint fields differ in length {sorted(lengths)}")
    jp, cp = out / "results.json", out / "results.csv"
    atomic_write_json(jp, {"schema_version": SCHEMA_VERSION, "records": list(records)})
    atomic_write_text(cp, _csv_text(records))
    return jp, cp


def read_results(path: str | os.PathLike) -> list[dict[str, Any]]:
    """Read a ``results.json`` and check its schema version."""
    import json

    data = json.loads(Path(path).read_text())
    if data.get("schema_version") != SCHEMA_VERSION:
        raise ValueError(f"{path}: schema_version {data.get('schema_version')!r}, expected {SCHEMA_VERSION}")
    return data["records"]
