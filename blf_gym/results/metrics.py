"""Evaluation metrics on the 1 ms grid and the one results schema every command writes (docs/model.md).

A *record* pools the episodes of one policy on one scenario group. ``results.json`` is
``{"schema_version": 2, "provenance": {...}, "records": [...]}``; ``results.csv`` has one row per
record with per-joint fields spread over ``<field>_<joint>`` columns (joints numbered from 1) and
without the per-episode arrays, which only the JSON holds.

The benchmark's score is :func:`score_vs_law`: per episode, the geometric mean over joints of
RMSE_law_j / RMSE_policy_j, where the law is the proposed law on the same scenario and the same
noise sequence. It is 1 at the law's level and higher for better tracking. Violations are never
folded into it; they are reported beside it (``failure_rate``, ``violations``, and
``certificate_broken``: the share of episodes in which the policy breaks a bound while the law
alone does not).
"""

from __future__ import annotations

import csv
import io
import math
import os
from pathlib import Path
from typing import Any, Iterable, NamedTuple, Sequence

import numpy as np

from blf_gym.results.io import atomic_write_json, atomic_write_text

__all__ = [
    "SCHEMA_VERSION",
    "RECORD_FIELDS",
    "REFERENCE_FIELDS",
    "violation_mask",
    "score_vs_law",
    "summarize",
    "EpisodeStats",
    "episode_stats",
    "write_results",
    "read_results",
    "read_provenance",
    "provenance",
]

SCHEMA_VERSION = 2

RECORD_FIELDS = (
    "policy", "kind", "scenario", "episodes", "dt", "rmse_deg", "violations", "violation_fraction",
    "max_excursion_deg", "min_margin_deg", "first_violation_s", "failure_rate", "rmse_cvar_deg",
    "torque_rms", "torque_peak", "saturated_fraction", "diverged", "wall_s",
    "score_vs_law", "certificate_broken", "law_failure_rate",
    "per_episode_rmse_deg", "per_episode_score", "per_episode_violations", "per_episode_failed",
)
PER_EPISODE = ("per_episode_rmse_deg", "per_episode_score", "per_episode_violations", "per_episode_failed")
PROVENANCE_FIELDS = ("suite", "suite_seeds", "scenario_kwargs", "env_kwargs", "train_seed", "noise_seeds",
                     "observer", "law_reused", "registered_policy", "policy_report", "level")
"""Optional per-record fields saying what produced it (the CSV carries them as JSON text).
``level`` is the difficulty level of the episodes (blf_gym.envs.levels; absent in files written before
the levels, which were all at level 3, the full benchmark).
``registered_policy`` names a ``blf_gym.policies`` entry point scored like an agent, and
``policy_report`` is that policy's own account of the run (the NMPC's solve times and fallbacks,
over all of its episodes in the run)."""
REFERENCE_FIELDS = ("reference", "score_vs_reference", "per_episode_score_vs_reference")
"""Optional per-record fields of the second yardstick: the reference controller's name, the
record's score against it (the same geometric mean as ``score_vs_law``, the reference's RMSE in
place of the law's, pooled) and per episode. None (or absent, in files written before them) where
no reference was run, and for the reference's own rows."""
PER_JOINT = ("rmse_deg", "violations", "violation_fraction", "max_excursion_deg", "min_margin_deg",
             "torque_rms", "torque_peak", "saturated_fraction")
KINDS = ("baseline", "plain", "residual")


def violation_mask(e1: np.ndarray, k_a: np.ndarray, k_b: np.ndarray) -> np.ndarray:
    """True where e1 is outside the open interval (-k_b, k_a) (eq. 17)."""
    return (e1 >= k_a) | (e1 <= -k_b)


def score_vs_law(rmse_policy: Sequence[float] | None, rmse_law: Sequence[float] | None) -> float | None:
    """The benchmark's score of one episode: the geometric mean over joints of
    RMSE_law_j / RMSE_policy_j (1 at the law's level, higher is better).

    An episode with no samples (diverged at once) scores 0; without the law's RMSE there is no
    score (None). RMSEs are floored at 1e-12 degrees so that a perfect joint stays finite.
    """
    if rmse_law is None or any(v is None for v in rmse_law):
        return None
    if rmse_policy is None or any(v is None for v in rmse_policy):
        return 0.0
    p = np.maximum(np.asarray(rmse_policy, dtype=float), 1e-12)
    law = np.maximum(np.asarray(rmse_law, dtype=float), 1e-12)
    return float(np.exp(np.mean(np.log(law / p))))


def _episode(traj: Any) -> tuple[dict[str, np.ndarray], np.ndarray | None, list[float] | None, int, bool]:
    """One trajectory's (signals, violation mask or None, per-joint RMSE in degrees or None,
    violating 1 ms samples, failed): the per-episode facts every record and score is built on."""
    a = _traj_arrays(traj)
    e1 = a["e1"]
    if e1.shape[0] == 0:
        return a, None, None, 0, True
    mask = violation_mask(e1, a["k_a"], a["k_b"])
    rmse = np.degrees(np.sqrt(np.sum(e1 ** 2, axis=0) / e1.shape[0])).tolist()
    failed = bool(mask.any() or getattr(traj, "step_violations", 0) > 0 or getattr(traj, "diverged", False))
    return a, mask, rmse, int(mask.any(axis=1).sum()), failed


def cvar_upper(values: Sequence[float], alpha: float = 0.5) -> float:
    """Mean of the worst ``1 - alpha`` share of ``values`` (largest ones), at least one value."""
    v = np.sort(np.asarray(values, dtype=float))[::-1]
    k = max(1, int(math.ceil((1.0 - alpha) * v.size)))
    return float(np.mean(v[:k]))


METRIC_CHANNELS = ("t", "e1", "k_a", "k_b", "u", "saturated")
"""The signals of a trajectory that :func:`episode_stats` and the records read (an env that records
only these, ``record_channels=METRIC_CHANNELS``, keeps about a third of the memory)."""


def _traj_arrays(traj: Any) -> dict[str, np.ndarray]:
    s = traj.signals if hasattr(traj, "signals") else traj
    return {k: np.asarray(s[k]) for k in METRIC_CHANNELS}


class EpisodeStats(NamedTuple):
    """One episode reduced to what a results record needs (:func:`episode_stats`), so that many
    episodes can be scored without keeping their signals: per joint, the sum of e1^2 (rad^2), the
    violating samples, the largest distance beyond a bound and the closest approach to one (rad),
    the sum of u^2 and the peak |u| (N m), the saturated samples; the sample count, the per-joint
    RMSE (degrees, None for an episode without samples), the violating samples (any joint), whether
    it failed or diverged, and its earliest violation (s, a sample or an integration step)."""

    samples: int
    sq: "np.ndarray | None"
    viol: "np.ndarray | None"
    excursion: "np.ndarray | None"
    margin: "np.ndarray | None"
    u_sq: "np.ndarray | None"
    u_peak: "np.ndarray | None"
    saturated: "np.ndarray | None"
    rmse_deg: "list[float] | None"
    violating_samples: int
    failed: bool
    diverged: bool
    first_violation_s: "float | None"
    n_joints: int


def _joints(a: dict[str, np.ndarray]) -> int:
    """The number of joints of an episode's signals: the width of its joint signals, (samples, n)
    (an episode without samples keeps that shape, (0, n)). ValueError if none is two-dimensional."""
    for k in ("e1", "u", "saturated"):
        if a[k].ndim == 2:
            return int(a[k].shape[1])
    raise ValueError("episode_stats: the joint signals e1, u and saturated must be (samples, n joints), got shapes "
                     f"{[a[k].shape for k in ('e1', 'u', 'saturated')]}")


def episode_stats(traj: Any) -> EpisodeStats:
    """A :class:`blf_gym.kernel.simulate.Trajectory` (or a dict of its signals) as :class:`EpisodeStats`;
    an ``EpisodeStats`` is returned as it is."""
    if isinstance(traj, EpisodeStats):
        return traj
    a, mask, ep_rmse, ep_viol, ep_failed = _episode(traj)
    e1, ka, kb, u = a["e1"], a["k_a"], a["k_b"], a["u"]
    n_joints = _joints(a)
    diverged = bool(getattr(traj, "diverged", False))
    if mask is None:
        return EpisodeStats(0, None, None, None, None, None, None, None, None, 0, True, True, None, n_joints)
    beyond = np.maximum(np.maximum(e1 - ka, -kb - e1), 0.0)
    marg = np.minimum(ka - e1, e1 + kb)
    # earliest violation: a 1 ms sample, or an integration step between samples
    candidates = []
    if mask.any():
        candidates.append(float(a["t"][np.argmax(mask.any(axis=1))]))
    step_t = getattr(traj, "first_violation_step_time", None)
    if step_t is not None:
        candidates.append(float(step_t))
    return EpisodeStats(
        samples=int(e1.shape[0]), sq=np.sum(e1 ** 2, axis=0), viol=mask.sum(axis=0), excursion=beyond.max(axis=0),
        margin=marg.min(axis=0), u_sq=np.sum(u ** 2, axis=0), u_peak=np.abs(u).max(axis=0),
        saturated=a["saturated"].sum(axis=0), rmse_deg=ep_rmse, violating_samples=ep_viol, failed=ep_failed,
        diverged=diverged, first_violation_s=min(candidates) if candidates else None, n_joints=n_joints)


def summarize(
    trajectories: Iterable[Any],
    policy: str,
    kind: str,
    scenario: str,
    dt: float,
    wall_s: float = 0.0,
    law: Sequence[Any] | None = None,
    provenance: dict[str, Any] | None = None,
    reference: Sequence[Any] | None = None,
    reference_name: str | None = None,
) -> dict[str, Any]:
    """Pool episodes into one results record.

    ``trajectories`` are :class:`blf_gym.kernel.simulate.Trajectory` objects (or dicts of their signals),
    or their :class:`EpisodeStats` (:func:`episode_stats`; the record is the same, to the bit, so
    a caller can reduce each episode as it finishes and keep no signals).
    RMSE pools the squared error of all 1 ms samples of all episodes, per joint; an episode fails
    if any of its samples or integration steps violated a bound, or it diverged. ``rmse_cvar_deg``
    is the mean of the worst half of the episodes' RMSE, each averaged over the joints first.
    ``max_excursion_deg`` and ``min_margin_deg`` are per joint, over all episodes.

    ``law``: the proposed law's trajectories (or their EpisodeStats) on the same episodes (same
    scenario, same noise sequence), one per episode, for :func:`score_vs_law` per episode
    (``per_episode_score``), its pooled form (``score_vs_law``: the same geometric mean on the
    pooled RMSEs), ``law_failure_rate`` and ``certificate_broken``. Without it those fields are
    None. ``provenance`` (see :data:`PROVENANCE_FIELDS`) is copied into the record.

    ``reference`` and ``reference_name``: a second yardstick, another controller's trajectories (or
    EpisodeStats) on the same episodes, for the record's :data:`REFERENCE_FIELDS` (its score against
    that controller, pooled and per episode, computed as ``score_vs_law`` is).
    """
    if kind not in KINDS:
        raise ValueError(f"kind must be one of {KINDS}, got {kind!r}")
    pool = _Pool()
    for traj in trajectories:
        pool.add(episode_stats(traj))
    if pool.episodes == 0:
        raise ValueError("summarize needs at least one trajectory")
    eps = pool.eps
    extra: dict[str, Any] = {
        "per_episode_rmse_deg": [e[0] for e in eps],
        "per_episode_violations": [e[1] for e in eps],
        "per_episode_failed": [e[2] for e in eps],
        "per_episode_score": None, "score_vs_law": None, "certificate_broken": None, "law_failure_rate": None,
    }
    pooled = pool.rmse_deg()
    if law is not None:
        law_st = _yardstick_stats(law, len(eps), "law")
        extra["per_episode_score"] = [score_vs_law(p[0], q.rmse_deg) for p, q in zip(eps, law_st)]
        extra["law_failure_rate"] = sum(q.failed for q in law_st) / len(law_st)
        extra["certificate_broken"] = sum(p[2] and not q.failed for p, q in zip(eps, law_st)) / len(eps)
        extra["score_vs_law"] = score_vs_law(pooled, _pooled_rmse(law_st))
    extra.update(reference=reference_name if reference is not None else None, score_vs_reference=None,
                 per_episode_score_vs_reference=None)
    if reference is not None:
        ref_st = _yardstick_stats(reference, len(eps), "reference")
        extra["per_episode_score_vs_reference"] = [score_vs_law(p[0], q.rmse_deg) for p, q in zip(eps, ref_st)]
        extra["score_vs_reference"] = score_vs_law(pooled, _pooled_rmse(ref_st))
    if provenance:
        unknown = set(provenance) - set(PROVENANCE_FIELDS)
        if unknown:
            raise ValueError(f"summarize: unknown provenance field(s) {sorted(unknown)}; known: {PROVENANCE_FIELDS}")
        extra.update(provenance)
    head = {"policy": policy, "kind": kind, "scenario": scenario, "episodes": pool.episodes, "dt": dt}
    return {**head, **pool.fields(), "wall_s": wall_s, **extra}


def _yardstick_stats(trajectories: Sequence[Any], episodes: int, what: str) -> list[EpisodeStats]:
    """The EpisodeStats of a yardstick's episodes (the law's, a reference's), one per episode."""
    stats = [episode_stats(t) for t in trajectories]
    if len(stats) != episodes:
        raise ValueError(f"summarize: {len(stats)} {what} trajectories for {episodes} episodes")
    return stats


class _Pool:
    """:func:`summarize`'s running sums over a record's episodes, per joint, in episode order."""

    def __init__(self) -> None:
        self.sq_sum: np.ndarray | None = None
        self.count = 0
        self.first: float | None = None
        self.fails = 0
        self.diverged = False
        self.per_episode_rmse: list[float] = []
        self.eps: list[tuple[list[float] | None, int, bool]] = []
        self.episodes = 0
        self.n_joints = 0

    def add(self, st: EpisodeStats) -> None:
        self.eps.append((st.rmse_deg, st.violating_samples, st.failed))
        self.episodes += 1
        self.n_joints = st.n_joints
        if st.sq is None:
            self.diverged = True
            self.fails += 1
            return
        if self.sq_sum is None:
            n = st.sq.shape[0]
            self.sq_sum, self.viol, self.exc = np.zeros(n), np.zeros(n, dtype=np.int64), np.zeros(n)
            self.margin, self.u_sq, self.u_peak, self.sat = np.full(n, np.inf), np.zeros(n), np.zeros(n), np.zeros(n)
        self.sq_sum += st.sq
        self.count += st.samples
        self.viol += st.viol
        self.exc = np.maximum(self.exc, st.excursion)
        self.margin = np.minimum(self.margin, st.margin)
        self.u_sq += st.u_sq
        self.u_peak = np.maximum(self.u_peak, st.u_peak)
        self.sat += st.saturated
        self.per_episode_rmse.append(float(np.mean(st.rmse_deg)))
        self.diverged |= st.diverged
        if st.first_violation_s is not None:
            self.first = st.first_violation_s if self.first is None else min(self.first, st.first_violation_s)
        self.fails += st.failed

    def rmse_deg(self) -> list[float] | None:
        """Per joint, the RMSE of every sample of every episode that did not diverge (None: all did)."""
        return np.degrees(np.sqrt(self.sq_sum / self.count)).tolist() if self.sq_sum is not None else None

    def fields(self) -> dict[str, Any]:
        """The record's pooled fields (every per-joint field None when every episode diverged)."""
        if self.sq_sum is None:
            return {**{k: [None] * self.n_joints for k in PER_JOINT}, "first_violation_s": None,
                    "failure_rate": 1.0, "rmse_cvar_deg": None, "diverged": True}
        count = self.count
        return {
            "rmse_deg": self.rmse_deg(),
            "violations": self.viol.tolist(),
            "violation_fraction": (self.viol / count).tolist(),
            "max_excursion_deg": np.degrees(self.exc).tolist(),
            "min_margin_deg": np.degrees(self.margin).tolist(),
            "first_violation_s": self.first,
            "failure_rate": self.fails / self.episodes,
            "rmse_cvar_deg": cvar_upper(self.per_episode_rmse, 0.5) if self.per_episode_rmse else None,
            "torque_rms": np.sqrt(self.u_sq / count).tolist(),
            "torque_peak": self.u_peak.tolist(),
            "saturated_fraction": (self.sat / count).tolist(),
            "diverged": self.diverged,
        }


def _pooled_rmse(stats: Sequence[Any]) -> list[float] | None:
    """Per joint, the RMSE (degrees) of all 1 ms samples of the episodes' EpisodeStats pooled."""
    sq, n = 0.0, 0
    for q in stats:
        if q.samples:
            sq = sq + q.sq
            n += q.samples
    return np.degrees(np.sqrt(sq / n)).tolist() if n else None


def _csv_text(records: Sequence[dict[str, Any]]) -> str:
    # the joints' columns: as many as the records' joints (a file without records gets the paper's
    # arm's three, as it always did)
    n = max((len(r["rmse_deg"]) for r in records), default=3)  # paper: no record to read n from
    import json

    fields_ = [f for f in RECORD_FIELDS if f not in PER_EPISODE] + list(REFERENCE_FIELDS[:2]) + list(PROVENANCE_FIELDS)
    header: list[str] = []
    for f in fields_:
        header.extend([f"{f}_{j + 1}" for j in range(n)] if f in PER_JOINT else [f])
    buf = io.StringIO()
    w = csv.writer(buf)
    w.writerow(header)
    for r in records:
        row: list[Any] = []
        for f in fields_:
            v = r.get(f)
            if f in PER_JOINT:
                row.extend(list(v) + [""] * (n - len(v)))
            elif f in PROVENANCE_FIELDS and v is not None:
                row.append(json.dumps(v, sort_keys=True))
            else:
                row.append("" if v is None else v)
        w.writerow(row)
    return buf.getvalue()


def provenance(command: str | None = None, **extra: Any) -> dict[str, Any]:
    """What produced a results file: package versions, the git commit, the command line, and
    anything given in ``extra``."""
    import importlib.metadata as md
    import platform
    import subprocess

    versions = {"python": platform.python_version()}
    # the optional ones when installed: sb3-contrib (TQC), sbx-rl and jax (the sbx learners), casadi (the NMPC)
    for pkg in ("blf-gym", "numpy", "numba", "gymnasium", "stable-baselines3", "torch", "sb3-contrib", "sbx-rl", "jax",
                "casadi"):
        try:
            versions[pkg] = md.version(pkg)
        except md.PackageNotFoundError:
            pass
    try:
        commit = subprocess.run(["git", "rev-parse", "HEAD"], cwd=Path(__file__).parent, capture_output=True,
                                text=True, timeout=5, check=True).stdout.strip() or None
    except (OSError, subprocess.SubprocessError):
        commit = None
    return {"versions": versions, "git_commit": commit, "command": command, **extra}


def write_results(records: Sequence[dict[str, Any]], out_dir: str | os.PathLike,
                  meta: dict[str, Any] | None = None) -> tuple[Path, Path]:
    """Write ``results.json`` and ``results.csv`` atomically into ``out_dir``; return their paths.

    ``meta`` (see :func:`provenance`) goes into ``results.json`` as ``"provenance"``."""
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
    atomic_write_json(jp, {"schema_version": SCHEMA_VERSION, "provenance": meta or {}, "records": list(records)})
    atomic_write_text(cp, _csv_text(records))
    return jp, cp


def read_results(path: str | os.PathLike) -> list[dict[str, Any]]:
    """Read a ``results.json`` and check its schema version (1, the earlier schema without scores,
    per-episode arrays and provenance, is read with those fields set to None)."""
    import json

    data = json.loads(Path(path).read_text())
    version = data.get("schema_version")
    if version not in (1, SCHEMA_VERSION):
        raise ValueError(f"{path}: schema_version {version!r}, expected {SCHEMA_VERSION} (or 1)")
    records = data["records"]
    if version == 1:
        records = [{**{f: None for f in RECORD_FIELDS}, **r} for r in records]
    return records


def read_provenance(path: str | os.PathLike) -> dict[str, Any]:
    """The ``provenance`` block of a ``results.json`` (empty for schema 1)."""
    import json

    return json.loads(Path(path).read_text()).get("provenance") or {}
